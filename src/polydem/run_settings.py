"""RunSettings: the settings of a run that depend on all of its bodies, decided once from the whole scene.

The time step and the derived friction springs (set by the lightest and stiffest free shapes), the
Verlet skin (by the smallest body), the default thickness of a mesh wall (by the largest), the broad
phase's reference radius (its size classes decide which body of a pair is A) and the speeds above
which a body may tunnel all depend on the scene's bodies. :func:`run_settings` decides them from the
whole scene; :class:`~polydem.model.Model` and :class:`~polydem.Simulation` take them as given, so that
a simulation of some of the bodies (a rank of :class:`~polydem.distributed.DistributedSimulation`) steps
them as the whole scene's run does. The scene layer keeps its own rules (:meth:`polydem.Scene.time_step`,
:meth:`polydem.Scene.mesh_wall_thickness`, :meth:`polydem.Scene.tunnelling_limits`: ``polydem validate``
reports them without Warp); this module asks each of them once. Host only: numpy, no Warp.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np

from polydem.scene import BodyKind
from polydem.scene.values import distinct_codes

if TYPE_CHECKING:
    from polydem.scene import Scene
    from polydem.scene.checks import TunnelLimits

SKIN_FRACTION = 0.2
"""Default Verlet skin as a fraction of the smallest bounding radius of a free body: the broad phase is
rebuilt after a body has moved half of it."""

__all__ = ["SKIN_FRACTION", "RunSettings", "run_settings"]


@dataclass(frozen=True, eq=False)
class RunSettings:
    """The settings of a run derived from its whole scene (build it with :func:`run_settings`).

    Attributes:
        dt: time step [s]: the scene's dt, or the recommended step for dt = "auto".
        dt_recommended: the step the scene's contacts resolve well [s] (:class:`~polydem.scene.TimeStep`).
        dt_toe: the step whose resolved toe the hertz and power (m < 2) laws take [s] (``TimeStep.toe_dt``).
        dt_limit: the largest accurate step [s].
        tangential_stiffness: (M, M) float64 friction spring stiffness of every material pair [N/m]
            (read-only): the materials' value, else the one derived from the free shapes.
        skin: Verlet skin of the broad phase [m]: the one given, else :data:`SKIN_FRACTION` of the
            smallest float32 bounding radius of a free body (of any body where none is free).
        mesh_wall_thickness: (W,) depth of each mesh wall's solid [m]: its ``thickness``, else the
            largest bounding diameter of a free shape.
        radius_min: the smallest bounding radius of a free body [m], the grain size of the settling
            criterion's speed limit (:func:`polydem.settle.grain_radius`); None where no body is free.
        radius_ref: the smallest positive float32 bounding radius of a free body [m], the unit of the
            broad phase's size classes; None where no free body has one (the broad phase then takes
            the smallest of its own bodies).
        radius_max: the largest bounding radius of a free body (of any body where none is free) [m].
        tunnel: the :class:`~polydem.scene.checks.TunnelLimits` of the scene's N bodies at ``dt``,
            indexed by the scene's body index.
        starts_too_fast: whether some body's initial speed is above its tunnelling limit (the scene's
            validation warns of that, so a run does not warn again).
    """

    dt: float
    dt_recommended: float
    dt_toe: float
    dt_limit: float
    tangential_stiffness: np.ndarray
    skin: float
    mesh_wall_thickness: tuple[float, ...]
    radius_min: float | None
    radius_ref: float | None
    radius_max: float
    tunnel: TunnelLimits
    starts_too_fast: bool


def run_settings(scene: Scene, skin: float | None = None) -> RunSettings:
    """The :class:`RunSettings` of ``scene`` (validated) over all of its bodies.

    Args:
        scene: the whole scene.
        skin: Verlet skin [m], >= 0 (default: :data:`SKIN_FRACTION` of the smallest free bounding radius).

    Raises:
        SceneError: the scene gives no time step (:meth:`polydem.Scene.time_step`).
        ValueError: ``skin`` is negative or not finite.
    """
    ts = scene.time_step()
    arrays = scene.body_arrays()
    shape_radius = np.array([scene.shapes[name].radius for name in scene.shape_names], dtype=np.float64)
    # A body's radius is its shape's: the least and largest over the shapes in use, never a gather over the bodies.
    n_shapes = len(shape_radius)
    free = arrays["kind"] == BodyKind.FREE
    free_shapes = distinct_codes(np.where(free, arrays["shape"], n_shapes), n_shapes + 1)
    free_shapes = free_shapes[free_shapes < n_shapes]
    pool = shape_radius[free_shapes if free_shapes.size else distinct_codes(arrays["shape"], n_shapes)]
    # float32, as the broad phase holds the radii: the undivided run has always taken the skin so.
    r32 = shape_radius.astype(np.float32)
    if skin is None:
        skin = SKIN_FRACTION * float(pool.astype(np.float32).min())
    skin = float(skin)
    if not (math.isfinite(skin) and skin >= 0.0):
        raise ValueError(f"skin must be >= 0 [m], got {skin!r}")
    free_r32 = r32[free_shapes]
    kt = np.array(ts.tangential_stiffness, dtype=np.float64)
    kt.setflags(write=False)
    tunnel = scene.tunnelling_limits(arrays, ts.dt)
    return RunSettings(
        dt=float(ts.dt),
        dt_recommended=float(ts.recommended),
        dt_toe=float(ts.toe_dt),
        dt_limit=float(ts.limit),
        tangential_stiffness=kt,
        skin=skin,
        mesh_wall_thickness=tuple(float(scene.mesh_wall_thickness(w)) for w in scene.mesh_walls),
        radius_min=float(shape_radius[free_shapes].min()) if free_shapes.size else None,
        radius_ref=float(free_r32[free_r32 > 0.0].min()) if (free_r32 > 0.0).any() else None,
        radius_max=float(pool.max()),
        tunnel=tunnel,
        starts_too_fast=bool(scene.check_tunnelling(arrays, ts.dt, tunnel)),
    )
