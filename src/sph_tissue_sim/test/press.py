"""Shared test motions (lower the tool onto the top centre of a block, tilt a shaft, run free) and
settings."""

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


def rotation_y(angle: float) -> np.ndarray:
    """Rotation by ``angle`` [rad] about the y axis: the tool's +z axis goes to (sin, 0, cos)."""
    c, s = np.cos(angle), np.sin(angle)
    return np.array([[c, 0.0, s], [0.0, 1.0, 0.0], [-s, 0.0, c]])


def tilted_shaft_press(X: np.ndarray, tool, particle_radius: float, tilt: float, depth: float,
                       frames: int = 400, ramp: int = 250):
    """A capsule ``tool`` tilted ``tilt`` [rad] down towards +x, its shaft's middle above the model
    centre, lowered from first touch to ``depth`` [m] over ``ramp`` frames, then held.

    Returns ``(tips (frames, 3), rotation (3, 3), shaft axis (3,))`` in the model's frame.
    """
    rot = rotation_y(np.pi / 2 + tilt)              # tool +z -> (cos tilt, 0, -sin tilt)
    axis = rot[:, 2]
    centre = np.array([X[:, 0].mean(), X[:, 1].mean(), X[:, 2].max() + 0.03])
    tip = centre - 0.5 * tool.length * axis
    gap = float((tool.signed_distance(X, tip, rot)[0] - particle_radius).min())
    assert gap > 0.0, 'the shaft starts inside the model'
    tip = tip - [0.0, 0.0, gap]                     # touching now
    tips = np.array([tip - [0.0, 0.0, depth * min(1.0, (k + 1) / ramp)] for k in range(frames)])
    return tips, rot, axis


def momentum_drift(solver, velocities, frames: int = 200, dt: float = 1e-3) -> tuple[float, float]:
    """Run ``solver`` free (no tool) from ``velocities``; returns (largest change of a linear
    momentum component, the momentum scale sum |m v|) [kg m/s]."""
    solver.velocities[:] = velocities
    p0 = solver.velocities.sum(axis=0) * solver.mass
    scale = float(np.abs(solver.velocities).sum() * solver.mass)
    for _ in range(frames):
        solver.step(None, dt)
    p1 = solver.velocities.sum(axis=0) * solver.mass
    return float(np.abs(p1 - p0).max()), scale


def organ_too_large(monkeypatch) -> None:
    """Make every organ too large for its own far field (``solver.ORGAN_MAX_FREE`` 0), so local mode
    takes the half-space's, as on the 12k, 30k and 100k livers."""
    from sph_tissue_sim.core import solver
    monkeypatch.setattr(solver, 'ORGAN_MAX_FREE', 0)
