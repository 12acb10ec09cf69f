"""Errors raised by tissue_viz (the pure modules never import rclpy)."""


class VizError(Exception):
    """Base class of every tissue_viz error."""


class VizConfigError(VizError, ValueError):
    """A parameter or target is out of range or inconsistent."""


class ReportError(VizError):
    """A report could not be written or its input could not be read."""
