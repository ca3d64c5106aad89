"""Rendering stage (Mitsuba 3): both cameras under 365 nm UV and white light, plus depth, only what is
asked for. Inputs are plain numpy dataclasses (``rendering.inputs``); ``rendering.renderer.Renderer``
renders frames; ``rendering.demo_scene`` builds a representative sensor from plain numbers."""
