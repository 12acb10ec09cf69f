"""Exceptions of the haptic_omni_driver package (none of them import rclpy)."""


class DriverError(Exception):
    """Base class of every error this package raises on purpose."""


class ConfigError(DriverError, ValueError):
    """A parameter or script value is out of range or inconsistent."""


class BagError(DriverError):
    """A bag is missing, corrupt, empty, lacks a topic or carries the wrong message type."""


class OutputError(BagError):
    """A bag cannot be created or written: it exists, or the file system refuses (read-only, not a
    directory, no permission, disk full)."""


class DeviceError(DriverError):
    """The haptic device library is absent or the device failed (init, calibration, scheduler)."""


class LockstepTimeout(DriverError):
    """No force reply arrived for a pose within the lockstep timeout (and the action is 'abort')."""
