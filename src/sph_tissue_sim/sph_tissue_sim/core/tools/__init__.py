"""Tool shapes, chosen by name (``SolverConfig.tool_shape``, the node's ``tool_shape`` parameter).

A new shape is one file here with a class following :class:`~.base.Tool` (usually a
:class:`~.base.SweptSphere` that says which segment it puts where, built by
``from_dimensions(radius, length)``), plus its line in :data:`TOOLS`.
"""

from __future__ import annotations

from ..errors import ConfigError
from .base import NO_ROTATION, SweptSphere, Tool
from .blade import Blade
from .capsule import Capsule
from .needle import Needle
from .sphere import Sphere

#: every shape by name
TOOLS = {'sphere': Sphere, 'capsule': Capsule, 'blade': Blade, 'needle': Needle}


def make_tool(shape: str, radius: float, length: float = 0.0) -> Tool:
    """The tool ``shape`` with its dimensions [m] (``length``: the capsule's or the needle's shaft, the blade's edge)."""
    if shape not in TOOLS:
        raise ConfigError(f'tool_shape must be one of {", ".join(TOOLS)}, got {shape!r}')
    return TOOLS[shape].from_dimensions(radius=radius, length=length)


__all__ = ['NO_ROTATION', 'TOOLS', 'Blade', 'Capsule', 'Needle', 'Sphere', 'SweptSphere', 'Tool', 'make_tool']
