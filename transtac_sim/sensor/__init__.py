"""Sensor assembly: hardware model + materials + marker layout -> a Sensor with its calibration."""
