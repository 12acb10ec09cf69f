"""Exceptions raised by the simulation core."""


class SimError(Exception):
    """Base class of all errors raised by :mod:`sph_tissue_sim.core`."""


class ConfigError(SimError, ValueError):
    """A parameter is out of range or inconsistent (material, solver or model settings)."""


class ModelError(SimError):
    """A tissue model cannot be built or loaded (empty model, unreadable mesh, bad particle count)."""


class OrganFactorError(SimError):
    """The process that factors the organ's stiffness failed or ended before it answered."""
