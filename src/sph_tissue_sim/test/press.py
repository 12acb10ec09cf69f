"""Shared test motion: lower the tool onto the top centre of a block."""

import numpy as np


def press(solver, depth: float, frames: int = 300, dt: float = 1e-3):
    """Lower the tool onto the top centre of the model to ``depth`` [m] below first touch.

    The tool reaches full depth at 70 % of ``frames`` and holds; returns the last StepResult.
    """
    X = solver.model.positions
    top = X[:, 2].max()
    centre = np.array([X[:, 0].mean() + 1e-3, X[:, 1].mean() + 5e-4, top + solver.contact_reach])
    res = None
    for k in range(frames):
        d = depth * min(1.0, (k + 1) / (0.7 * frames))
        res = solver.step(centre - np.array([0.0, 0.0, d]), dt)
    return res
