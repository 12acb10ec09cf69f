"""Haptic rendering: how the tissue's force reaches the hand at 1 kHz (numpy only, no rclpy).

The device's sampled, encoder-quantised positions pass a velocity estimator
(:mod:`tissue_common.estimator`, which omni_driver's ``measured_cv`` uses too); a virtual coupling
(:mod:`.coupling`) joins the device point to the simulated tool through a spring-damper against a
local contact model that the solver refreshes; a passivity observer and controller
(:mod:`.passivity`) watch the energy at the device port and add just the damping that keeps it
non-negative. :class:`.renderer.HapticRenderer` chains them for one device.
"""
