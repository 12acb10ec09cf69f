"""haptic_omni_driver package."""
