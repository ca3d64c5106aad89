"""Metrics against a dataset's exact labels: detection (``detection``) and tracking (``tracking``)."""
