"""What a run needs of a scene: float32 ranges, the time step, contacts stiff enough for the loads."""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from polydem.kernels.laws import LAW_SPECS, LAW_UNITS
from polydem.quaternions import quat_to_matrix
from polydem.scene.bodies import KIND_FIXED, KIND_FREE, KIND_KINEMATIC, KINDS
from polydem.scene.overlaps import INITIAL_OVERLAP_WARNING, report_overlaps
from polydem.scene.settings import MAX_STEPS
from polydem.scene.values import (
    F32_HIGH,
    F32_LOW,
    F32_MARGIN,
    FEW_CODES,
    RADIUS_HIGH,
    RADIUS_LOW,
    body_codes,
    check_quats,
    distinct_codes,
    first_of_each_code,
    first_with_code,
    row_norms,
)
from polydem.scene.walls import mesh_wall_memo
from polydem.shapes import largest_face_area

# The time step resolves a contact oscillation at the reference overlap (0.1% of a body's size,
# over its face area) in this many steps; above 1/8 of the period symplectic Euler loses accuracy
# fast (it is unstable past 1/pi of it).
STEPS_PER_CONTACT_PERIOD = 50
MAX_DT_FRACTION = 1.0 / 8.0
REFERENCE_DEPTH = 0.001


# Expected overlap depths (of a face contact under a body's weight or at the initial speeds), as a
# fraction of the body's size V^(1/3): above the first a warning, above the second an error.
OVERLAP_WARNING = 0.1
OVERLAP_ERROR = 0.5

# Tunnelling (see tunnelling_limits). Per step a body moves at most this fraction of
# the smallest half-thickness in the scene: a contact across the thinnest body (thickness 2 h) then
# spans at least 4 steps, the fewest in which a step-wise force can turn a body round; beyond it the
# first step that sees the overlap may already find the body past the middle of the thin one.
TUNNEL_STEP_FRACTION = 0.5
# ... and its kinetic energy is at most this fraction of what a contact stores before the thinner
# body is crossed through (past that the overlap stops growing and its gradient, the force, ends):
# the margin covers the estimate of the crossing area (an oblique body meets the thin one with more
# or less than its mean cross-section) and the partner's own motion.
TUNNEL_ENERGY_FRACTION = 0.5
# A gravity is blamed (rather than the materials) where its weight needs a k beyond float32's range but
# this one's would not.
STANDARD_GRAVITY = 9.80665
# A run whose length comes from the command's default (no steps or duration anywhere) and covers less
# simulated time than this is most likely a time step far shorter than meant (a k or a density off by
# powers of ten, or a dt in the wrong unit): the default steps are meant to show a scene moving.
DEFAULT_RUN_MIN_TIME = 1.0e-6
# A given dt above this many recommended steps under a law with the resolved toe is warned about
# (check_toe_step): at 2 the 1000-cube pour's pile is the recommended step's, at 4 it is not.
TOE_STEP_WARNING = 2.0
# Below this restitution a law without the resolved toe (power, m >= 2) rings at rest (check_resting_ringing):
# a steel cube set down on the floor reported 0.79-1.20 of its weight 0.3 s later at e = 0.1 (m = 2; m = 3:
# 0.85-1.21), exactly it by then at 0.2 (BENCHMARKS.md section 26e).
RINGING_RESTITUTION = 0.2


def reference_stiffness(law, k, exponent, volume, area=None, width=None):
    """Secant normal stiffness [N/m] of a face contact of area ``area`` [m^2] pressed to 0.1% of ``width`` [m].

    ``area`` defaults to V^(2/3) and ``width`` to the size V^(1/3) (``volume`` V [m^3]); a shape's own
    values come from :func:`face_contact_size`. With W'(V) the law, a face of area A pressed to depth d
    gives V = A d and a force W'(A d) A; the secant stiffness is that force over d. Computed in float64
    numpy (never an OverflowError: out-of-range values become 0 or inf, which :meth:`Scene.validate`
    rejects beforehand).
    """
    volume = np.float64(volume)
    with np.errstate(all="ignore"):
        area = volume ** (2.0 / 3.0) if area is None else np.float64(area)
        depth = REFERENCE_DEPTH * (np.cbrt(volume) if width is None else np.float64(width))
        v = area * depth
        dw = LAW_SPECS[law].derivative(v, np.asarray(k, dtype=np.float64), np.float64(exponent))
        return dw * area / depth


def resting_stiffness(law, k, exponent, volume, weight, area=None):
    """Tangent normal stiffness [N/m] of a face contact of area ``area`` [m^2] (default V^(2/3), V =
    ``volume`` [m^3]) carrying ``weight`` [N]: a body resting on a face under its own weight. NaN for
    the linear law (its force k A does not depend on the depth: no resting depth).

    With W'(V) the law and V = A d, the force W'(A d) A equals the weight at the resting depth d;
    hertz (W' = k sqrt(V)): d = (F / (k A^1.5))^2 and dF/dd = F / (2 d); power (W' = k V^(m-1)):
    A d = (F / (k A))^(1/(m-1)) and dF/dd = (m - 1) F / d. Far stiffer than the reference overlap's
    secant stiffness when the weight is small against k: the hertz flat face is infinitely stiff at
    zero depth.
    """
    volume = np.float64(volume)
    weight = np.float64(weight)
    k = np.asarray(k, dtype=np.float64)
    with np.errstate(all="ignore"):
        area = volume ** (2.0 / 3.0) if area is None else np.float64(area)
        return LAW_SPECS[law].resting_stiffness(k, exponent, area, weight)


def has_toe(law, exponent) -> bool:
    """Whether the simulator continues the law below a small volume V_c as a resolved toe (hertz, and power
    laws with 1 < m < 2, whose face stiffness W''(V) A^2 grows without bound as V -> 0): it chooses V_c
    per pair from the step so that a face contact is never stiffer than the step resolves (polydem.kernels
    .response.toe_volume), so a body resting on a face needs no shorter step than the law's elsewhere."""
    return LAW_SPECS[law].has_toe(exponent)


def face_contact_size(shape) -> tuple[float, float]:
    """``(area [m^2], width [m])`` of the stiffest face contact of a shape, for the time step: its largest face
    (:func:`largest_face_area`), at least V^(2/3), and its thinnest width (:func:`shape_width`, of the
    union's surface for a compound shape), at most V^(1/3). A cube gives V^(2/3) and V^(1/3); a plate its face
    and its thickness (a face contact of a flat body is as stiff as its face is large, and a step resolves
    it at an overlap of 0.1% of its thickness, not of its mean size)."""
    size = float(np.cbrt(shape.volume))
    area = max(largest_face_area(shape), size * size)
    # A compound grain's own surface (the union's), not its parts': a grain cut in two is as thick as the whole.
    width = min(shape_width(shape), size)
    return area, width


def rotation_factor(shape, mass, inertia) -> float:
    """``1 + m max (p x t).I^-1.(p x t)`` over the shape's vertices p and unit directions t (body frame,
    principal inertia ``inertia`` [kg m^2], mass ``mass`` [kg]): how much lighter a body feels to a
    tangential force at its farthest points than to one at its centre (a cube: 5.5; a sphere: 3.5).
    1 for a body without a positive inertia."""
    inertia = np.asarray(inertia, dtype=np.float64)
    if not (mass > 0.0 and np.all(inertia > 0.0)):
        return 1.0
    inv = 1.0 / inertia
    best = 0.0
    for p in np.asarray(shape.vertices, dtype=np.float64):
        # (p x t).I^-1.(p x t) = t.A.t with A = [p]x^T diag(1/I) [p]x
        px = np.array([[0.0, -p[2], p[1]], [p[2], 0.0, -p[0]], [-p[1], p[0], 0.0]])
        best = max(best, float(np.linalg.eigvalsh(px.T @ (inv[:, None] * px))[-1]))
    return 1.0 + mass * best


@dataclass(frozen=True)
class TimeStep:
    """The time step of a run (see :meth:`Scene.time_step`).

    Attributes:
        dt: the step a run uses [s]: the scene's dt, or ``recommended`` for dt = "auto".
        recommended: 1/50 of ``period``, or less where a free body resting on a face under its own
            weight needs less (``resting``) [s].
        resting: the step that resolves a free body resting on a face under its own weight, min(1, 2 e) /
            omega with omega the frequency of that contact's tangent stiffness and e the smallest
            restitution, the least over the free shapes [s]; inf without gravity or with the linear law.
        limit: 1/8 of ``period``, the largest accurate step [s].
        period: the shortest contact period of a free shape [s]: 2 pi sqrt(m / k) with m the mass of its
            lightest body and k the stiffest pair's secant stiffness of its largest face pressed to 0.1%
            of its thinnest width (:func:`face_contact_size`), or a larger tangential stiffness.
        lightest: index of the lightest body of the shape that sets ``period``.
        tangential_stiffness: (M, M) tangential stiffness of every material pair [N/m], the derived
            value (the least over the free shapes of the reference normal stiffness over the shape's
            :func:`rotation_factor`) where the materials give none.
    """

    dt: float
    recommended: float
    limit: float
    period: float
    lightest: int
    tangential_stiffness: np.ndarray
    resting: float = math.inf

    @property
    def toe_dt(self) -> float:
        """The step whose resolved toe a run takes [s] (:func:`toe_step` of ``dt`` and ``recommended``)."""
        return toe_step(self.dt, self.recommended)


def toe_step(dt: float, recommended: float) -> float:
    """The step [s] whose resolved toe (kernels/response.py, toe_volume) a run at ``dt`` takes: the recommended
    step's at and below it, so that a shorter step integrates the same law (a toe that shrank with dt made each
    refinement another law); the run's above it, so that a face at rest stays resolved (the recommended step's toe
    made a cube on the floor chatter at 4x it: BENCHMARKS.md section 25)."""
    return max(dt, recommended)


def _ln(x) -> float:
    """Natural log of a positive float, -inf for 0 (log-space arithmetic of the range checks)."""
    return math.log(x) if x > 0.0 else -math.inf


def _exp(x) -> float:
    return math.exp(min(x, 700.0))


def _fmt_exp(x) -> str:
    """exp(x) for a message, also beyond the range of a float."""
    return f"{math.exp(x):.3g}" if abs(x) < 700.0 else f"1e{x / math.log(10.0):+.0f}"


def _face_overlap(load, m, ln_k, ln_a, ln_l) -> float:
    """ln(A d) of a face contact (area A, size L, law W = k V^m / m) under a load.

    ``load > 0`` is a force F: W'(A d) A = F, so k (A d)^(m - 1) = F / A; for m = 1 the force
    k A does not depend on d, and d / L = F / (k A) stands in (see Scene.check_loads).
    ``load < 0`` is an energy E = -load: W(A d) = E, so (A d)^m = m E / k.
    """
    if load < 0.0:
        return (_ln(-m * load) - ln_k) / m
    if m == 1.0:
        return _ln(load) - ln_k + ln_l  # ln(A d) with d / L = F / (k A)
    return (_ln(load) - ln_a - ln_k) / (m - 1.0)


def _stiffness_for(load, m, ln_ad, ln_a, ln_l) -> float:
    """ln k for which a face contact under ``load`` has ln(A d) = ``ln_ad`` (inverse of _face_overlap)."""
    if load < 0.0:
        return _ln(-m * load) - m * ln_ad
    if m == 1.0:
        return _ln(load) - ln_a - (ln_ad - ln_a - ln_l)
    return _ln(load) - ln_a - (m - 1.0) * ln_ad


def _loads(mass, ln_l, g, v_hit) -> list[tuple]:
    """The loads a free body of mass ``mass`` and size exp(ln_l) puts on its contacts: its weight where ``g``
    > 0 (something carries it), the energy of its impact at ``v_hit`` > 0. Each is ``(load, cause, into,
    time scale text, time scale)``: a force F > 0 or an energy -E < 0 (see :func:`_face_overlap`)."""
    loads = []
    if g > 0.0:
        t_scale = math.sqrt(2.0 * _exp(ln_l) / g)
        loads.append(
            (
                mass * g,
                f"under its own weight ({mass * g:.3g} N) it would sink",
                "into what carries it",
                f"the {t_scale:.3g} s it takes to fall its own size",
                t_scale,
            )
        )
    if v_hit > 0.0:
        t_scale = _exp(ln_l) / v_hit
        loads.append(
            (
                -0.5 * mass * v_hit * v_hit,  # negative: an energy, not a force
                f"hitting a body or wall at the scene's fastest initial speed ({v_hit:.3g} m/s) it would sink",
                "into what it hits",
                f"the {t_scale:.3g} s it takes to cross its own size at that speed",
                t_scale,
            )
        )
    return loads


def shape_width(shape) -> float:
    """Smallest width of a shape's hull over its face normals [m] (the thickness of a plate)."""
    proj = np.asarray(shape.vertices, dtype=np.float64) @ np.asarray(shape.face_normals, dtype=np.float64).T
    return float(np.min(proj.max(axis=0) - proj.min(axis=0)))


@dataclass(frozen=True)
class TunnelLimits:
    """The speeds above which a body may pass through a thin body or wall (see
    :func:`tunnelling_limits`).

    Attributes:
        body_speed_limit: (N,) largest safe speed of each body's fastest point [m/s].
        body_step_bound: (N,) whether the step bound (not the energy one) sets that limit.
        half_thickness: the smallest half-thickness of any body [m].
        thinnest: index of the body that has it.
    """

    body_speed_limit: np.ndarray
    body_step_bound: np.ndarray
    half_thickness: float
    thinnest: int

    def describe(self, i: int, speed: float, dt: float) -> str:
        """Why ``speed`` [m/s] of body ``i`` is too fast (the end of a warning)."""
        limit = float(self.body_speed_limit[i])
        if self.body_step_bound[i]:
            why = (
                f"above the {limit:.3g} m/s at which a step of {dt:.3g} s moves it {TUNNEL_STEP_FRACTION:g} times the "
                f"smallest half-thickness ({self.half_thickness:.3g} m)"
            )
            fix = "lower dt"
        else:
            why = (
                f"above the {limit:.3g} m/s at which its kinetic energy is {TUNNEL_ENERGY_FRACTION:g} times what its "
                f"contact stores before it has crossed the thinnest body ({2.0 * self.half_thickness:.3g} m thick)"
            )
            fix = "raise k, or make the thin bodies thicker"
        return f"{speed:.3g} m/s, {why}: it may pass through what it hits; {fix}"


def check_body_arrays(scene, a):
    """Indices in range, finite numbers, unit quaternions, valid kinds, pivots only on kinematic bodies,
    fixed bodies at rest and free bodies with a mass; ``a`` holds the scene's body arrays."""
    # (Each test first over the whole array at once, the bodies one by one only to name the first that fails.)
    for name, count in (("shape", len(scene.shape_names)), ("material", len(scene.material_names))):
        if len(a[name]) and a[name].min() >= 0 and a[name].max() < count:
            continue
        bad = np.flatnonzero((a[name] < 0) | (a[name] >= count))
        if bad.size:
            i = int(bad[0])
            raise scene.error(
                f"{name} index {int(a[name][i])} out of range: the scene has {count} {name}s", f"bodies[{i}].{name}"
            )
    for name in ("position", "orientation", "velocity", "angular_velocity"):
        with np.errstate(over="ignore", invalid="ignore"):
            if np.isfinite(a[name].sum()):  # a finite sum has no inf or NaN in it
                continue
        bad = np.flatnonzero(~np.isfinite(a[name]).all(axis=1))
        if bad.size:
            i = int(bad[0])
            raise scene.error(f"expected finite numbers, got {a[name][i].tolist()}", f"bodies[{i}].{name}")
    check_quats(a["orientation"], lambda i: f"bodies[{i}].orientation", scene.file)
    ok = not len(a["kind"]) or (a["kind"].min() >= 0 and a["kind"].max() < len(KINDS))
    bad = np.zeros(0, dtype=np.int64) if ok else np.flatnonzero((a["kind"] < 0) | (a["kind"] >= len(KINDS)))
    if bad.size:
        i = int(bad[0])
        raise scene.error(
            f"kind code {int(a['kind'][i])} is not one of 0 (free), 1 (fixed), 2 (kinematic)", f"bodies[{i}].kind"
        )
    pivoted = np.zeros(0, dtype=np.int64)
    if not np.isnan(a["pivot"]).all():
        pivoted = np.flatnonzero(~np.isnan(a["pivot"]).any(axis=1) & (a["kind"] != KIND_KINEMATIC))
    if pivoted.size:
        i = int(pivoted[0])
        raise scene.error(
            "only a kinematic body can turn about a pivot; use kind = 'kinematic' or leave pivot out",
            f"bodies[{i}].pivot",
        )
    fixed = np.flatnonzero(a["kind"] == KIND_FIXED)
    moving = fixed[np.any(a["velocity"][fixed] != 0, axis=1) | np.any(a["angular_velocity"][fixed] != 0, axis=1)]
    if moving.size:
        i = int(moving[0])
        raise scene.error(
            "a fixed body cannot move; set its velocity and angular_velocity to zero or use kind = 'kinematic'",
            f"bodies[{i}].velocity",
        )
    shapes = list(scene.shapes.values())
    massless = np.array(
        [
            not (
                s.volume > 0.0
                and math.isfinite(s.volume)
                and np.all(np.asarray(s.inertia) > 0.0)
                and np.all(np.isfinite(s.inertia))
            )
            for s in shapes
        ]
    )
    bad = np.flatnonzero((a["kind"] == KIND_FREE) & massless[a["shape"]]) if massless.any() else massless[:0]
    if bad.size:
        i = int(bad[0])
        s = shapes[int(a["shape"][i])]
        raise scene.error(
            f"free body uses shape {s.name!r} with volume {s.volume:g} m^3 and inertia {np.asarray(s.inertia)}; a "
            "free body needs a positive volume and inertia to have mass: use a solid shape or kind = 'fixed'",
            f"bodies[{i}].shape",
        )


def lightest_of_each_shape(scene) -> tuple[np.ndarray, np.ndarray]:
    """(the shapes in use, ascending; the lightest body of each: the least mass, then the least index) among the
    free bodies, or where none is free among the bodies with a mass; both empty where no body has a mass.

    A body's mass is its material's density times its shape's volume (:meth:`Scene.body_mass`): the masses are
    worked out per (shape, material) code, never per body, and the bodies are scanned for the first of a code."""
    shapes = list(scene.shapes.values())
    n_mat = len(scene.material_names)
    volume = np.array([sh.volume for sh in shapes], dtype=np.float64)
    density = np.array([mat.density for mat in scene.materials.values()], dtype=np.float64)
    code_mass = (density[None, :] * volume[:, None]).reshape(-1)
    code = body_codes(scene.body_shape, scene.body_material, len(shapes), n_mat)
    n_code = len(shapes) * n_mat
    free = scene.body_kind == KIND_FREE
    pool = free if free.any() else code_mass[code] > 0.0
    pool_code = np.where(pool, code, n_code)  # n_code: out of the pool
    in_pool = np.flatnonzero(np.bincount(pool_code, minlength=n_code + 1)[:n_code])
    used = distinct_codes(in_pool // n_mat, len(shapes))
    # a pass per shape where there are few, else the first body of every code in one pass
    first = first_of_each_code(pool_code, n_code) if used.size > FEW_CODES else None
    lightest = []
    for s in used.tolist():
        codes = in_pool[in_pool // n_mat == s]
        light = codes[code_mass[codes] == code_mass[codes].min()]
        lightest.append(first_with_code(pool_code, light, n_code) if first is None else int(first[light].min()))
    return used, np.array(lightest, dtype=np.int64)


def time_step(scene) -> TimeStep:
    """The time step of a run and its bounds (host-only: ``polydem validate`` needs no Warp).

    Per free shape (the lightest body of each; fixed bodies do not move): the period ``2 pi sqrt(m /
    k_n)``, with ``k_n`` of the stiffest pair the secant stiffness of the shape's largest face pressed
    to 0.1% of its thinnest width (:func:`face_contact_size`, :func:`reference_stiffness`: for a cube
    the face V^(2/3) and the size V^(1/3); a plate's face contact is far stiffer and the step resolves
    it at a fraction of its thickness), or a larger tangential stiffness. The shortest period of the
    free shapes sets the step. ``dt = "auto"`` takes 1/50 of it, or less where a body resting on a
    face under its own weight needs less (:func:`resting_stiffness`, ``TimeStep.resting``); a given
    dt must not exceed 1/8 of the period (SceneError, key ``simulation.dt``).
    """
    if scene.num_bodies == 0:
        raise scene.error("the scene has no bodies; add at least one with [[bodies]] or Scene.add_body()", "bodies")
    table = scene.pair_table()
    law, m = table["law"], float(table["exponent"])
    k = np.asarray(table["k"], dtype=np.float64)
    kt = np.asarray(table["tangential_stiffness"], dtype=np.float64)
    shapes = list(scene.shapes.values())
    # The free bodies (or, with none, the bodies with a mass) set the step, the lightest body of
    # each shape with the stiffest pair: a light compact grain may need a longer step than a heavier
    # plate, whose large face is stiff, so every shape in use is looked at (once, whatever the count).
    used, lightest = lightest_of_each_shape(scene)
    if not used.size:
        raise scene.error(
            "no body has a mass (all are fixed with zero volume), so no time step can be derived; add a free "
            "body or give dt in seconds",
            "simulation.dt",
        )
    density = np.array([mat.density for mat in scene.materials.values()], dtype=np.float64)
    unit_inertia = np.array([sh.inertia for sh in shapes], dtype=np.float64).reshape(-1, 3)
    # Scene.body_mass and Scene.body_inertia of these bodies alone (the same products)
    mass = {int(b): density[scene.body_material[b]] * shapes[scene.body_shape[b]].volume for b in lightest}
    inertia = {int(b): density[scene.body_material[b]] * unit_inertia[scene.body_shape[b]] for b in lightest}
    gravity = float(np.linalg.norm(np.asarray(scene.gravity, dtype=np.float64)))
    e_min = max(float(np.min(np.asarray(table["restitution"], dtype=np.float64))), 0.1)
    toe = has_toe(law, m)
    period, light, k_n, resting = math.inf, int(lightest[0]), None, math.inf
    kt_derived = np.full(k.shape, np.inf)
    for s, body in zip(used.tolist(), lightest.tolist(), strict=True):
        shape, mb = shapes[s], float(mass[body])
        area, width = face_contact_size(shape)
        kn_s = reference_stiffness(law, k, m, shape.volume, area, width)
        # A sticking tangential spring turns the body as well as moving it: at a contact point p
        # (body frame) a tangential force along t meets the inverse mass 1/m + (p x t).I^-1.(p x t),
        # up to `rotation` / m. The derived spring is the reference normal stiffness over `rotation`,
        # so that this tangential-rotational oscillation has the normal one's frequency (for a sphere,
        # rotation = 7/2 and kt = 2/7 k_n, the usual choice); a spring given in the materials enters
        # the step with the factor.
        rotation = rotation_factor(shape, mb, inertia[body])
        kt_derived = np.minimum(kt_derived, kn_s / rotation)
        with np.errstate(all="ignore"):
            stiffest = max(float(np.max(kn_s)), float(np.max(np.where(np.isnan(kt), kn_s, kt * rotation))))
            p_s = float(2.0 * np.pi * np.sqrt(mb / stiffest))
        if not (math.isfinite(p_s) and p_s > 0.0):
            raise scene.error(
                f"the contact period 2 pi sqrt(m / k) of {scene.body_label(body)} (mass {mb:.3g} kg, stiffest "
                f"contact {stiffest:.3g} N/m) is {p_s:.3g} s, so no time step can be derived; check the "
                "materials' density and k",
                "simulation.dt",
            )
        if p_s < period:
            period, light, k_n = p_s, body, kn_s
        # A body resting flat under its own weight sits far shallower than the reference overlap,
        # where the hertz and power laws are far stiffer: with a step above about 2 / omega there
        # (symplectic Euler's limit, and the unloading branch is 1/e stiffer in frequency) the body
        # never comes to rest but hops by nanometres, in contact a fraction of the time. Where the
        # simulator's toe bounds that stiffness (has_toe) the face of area V^(2/3) is kept: the toe
        # resolves a larger face at any step, which would otherwise ask a plate for a step 100 times
        # shorter (the hertz step goes like A^-1.5 at rest); a stiffening law has no toe.
        weight = mb * gravity
        if weight > 0.0:
            with np.errstate(all="ignore"):
                stiff = np.asarray(resting_stiffness(law, k, m, shape.volume, weight, None if toe else area))
                # (the linear law has none: all NaN, and nanmax would warn)
                k_rest = float(np.nanmax(stiff)) if np.isfinite(stiff).any() else math.nan
                if math.isfinite(k_rest) and k_rest > 0.0:
                    resting = min(resting, min(1.0, 2.0 * e_min) / math.sqrt(k_rest / mb))
    kt = np.where(np.isnan(kt), kt_derived, kt)
    recommended = min(period / STEPS_PER_CONTACT_PERIOD, resting)
    limit = period * MAX_DT_FRACTION
    if scene.dt == "auto":
        dt = recommended
    else:
        dt = float(scene.dt)
        if dt > limit:
            shape = shapes[int(scene.body_shape[light])]
            area, width = face_contact_size(shape)
            raise scene.error(
                f"time step {dt:.3g} s is above the stable limit {limit:.3g} s, 1/8 of the period of the stiffest "
                f"contact of {scene.body_label(light)} (mass {mass[light]:.3g} kg, a face of {area:.3g} m^2, "
                f"{width:.3g} m thin, {float(np.max(k_n)):.3g} N/m at an overlap of {REFERENCE_DEPTH:g} of that "
                f'width; recommended {recommended:.3g} s); use dt = "auto" or a value of at most {limit:.3g} s',
                "simulation.dt",
            )
    return TimeStep(
        dt=dt,
        recommended=recommended,
        limit=limit,
        period=period,
        lightest=light,
        tangential_stiffness=kt,
        resting=resting,
    )


def check_float32(scene, a):
    """Shapes, masses, inertias, stiffnesses and the power law within float32 (see F32_LOW)."""
    lo, hi = F32_LOW, F32_HIGH
    shapes = list(scene.shapes.values())
    names = scene.shape_names
    r_lo, r_hi = RADIUS_LOW, RADIUS_HIGH
    for s in distinct_codes(a["shape"], len(shapes)):
        sh = shapes[int(s)]
        if not r_lo <= sh.radius <= r_hi:
            i = int(np.flatnonzero(a["shape"] == s)[0])
            raise scene.error(
                f"shape {names[s]!r} (used by body {i}) has a bounding radius of {sh.radius:.3g} m: too "
                f"{'small' if sh.radius < 1.0 else 'large'} for the simulator's float32 arithmetic, whose overlap "
                f"volumes and their moments (~ radius^4) must stay between {lo:.2g} and {hi:.2g}; give the shape a "
                f"bounding radius between {r_lo:.2g} m and {r_hi:.2g} m",
                f"shapes.{names[s]}",
            )
    mats = list(scene.materials.values())
    for mat in mats:
        for attr in ("k", "tangential_stiffness"):
            value = getattr(mat, attr)
            if value is not None and not lo <= value <= hi:
                raise scene.error(
                    f"{value:g} is outside the range the simulator's float32 arithmetic can use ({lo:.2g} to "
                    f"{hi:.2g}, float32's normal range with a margin of {F32_MARGIN:g} for products); give a "
                    "value in that range",
                    f"materials.{mat.name}.{attr}",
                )
    free = a["kind"] == KIND_FREE
    if not free.any():
        return
    combo = distinct_codes(a["shape"][free].astype(np.int64) * len(mats) + a["material"][free], len(shapes) * len(mats))
    for c in combo.tolist():
        sh, mat = shapes[c // len(mats)], mats[c % len(mats)]
        mass = mat.density * sh.volume
        inertia = mat.density * np.asarray(sh.inertia)
        if lo <= mass <= hi and lo <= inertia.min() and inertia.max() <= hi:
            continue
        i = int(np.flatnonzero(free & (a["shape"] == c // len(mats)) & (a["material"] == c % len(mats)))[0])
        rho_lo = max(lo / sh.volume, lo / float(np.min(sh.inertia)))
        rho_hi = min(hi / sh.volume, hi / float(np.max(sh.inertia)))
        fix = (
            f"use a density between {rho_lo:.3g} and {rho_hi:.3g} kg/m^3 for this shape"
            if rho_lo <= rho_hi
            else "no density works for this shape: make it less elongated or change its size"
        )
        raise scene.error(
            f"{scene.body_label(i)} of material {mat.name!r} would have a mass of {mass:.3g} kg and principal "
            f"moments of inertia of {inertia.min():.3g} to {inertia.max():.3g} kg m^2; the simulator stores them "
            f"in float32, which needs values between {lo:.2g} and {hi:.2g} (float32's normal range with a margin "
            f"of {F32_MARGIN:g} for products); {fix}",
            f"materials.{mat.name}.density",
        )
    law, m = mats[0].law, mats[0].exponent
    if law != "power":
        return
    # The kernels evaluate W = k V^m / m and W' = k V^(m-1) in float32; at the reference
    # overlap (0.1% of a free body's volume) V^m must stay in range, which bounds m.
    vols = np.array([sh.volume for sh in shapes])[distinct_codes(a["shape"][free], len(shapes))]
    caps = []
    v_small, v_large = REFERENCE_DEPTH * vols.min(), REFERENCE_DEPTH * vols.max()
    if v_small < 1.0:
        caps.append((_ln(lo) / _ln(v_small), v_small))
    if v_large > 1.0:
        caps.append((_ln(hi) / _ln(v_large), v_large))
    if caps:
        m_max, v_ref = min(caps)
        if m > m_max:
            raise scene.error(
                f"m = {m:g} is too large for the simulator's float32 arithmetic with these bodies: at the "
                f"reference overlap of a contact (0.1% of a free body's volume, V = {v_ref:.3g} m^3) the law's "
                f"V^m = {_fmt_exp(m * _ln(v_ref))} is outside {lo:.2g} to {hi:.2g}; use m between 1 and "
                f"{m_max:.3g} for bodies of these sizes (or law = 'hertz')",
                f"materials.{mats[0].name}.m",
            )


def check_loads(scene, a, ts: TimeStep) -> list[str]:
    """Contacts stiff enough for the bodies' weight and initial speeds; returns warnings.

    For each free (shape, material) the overlap depth d of a face contact (area A = V^(2/3),
    size L = V^(1/3)) is solved from the law W = k V^m / m (k of the softest pair it can
    meet): under the body's weight M g, where something can carry it (a plane or a fixed or
    kinematic body), W'(A d) A = M g; at the fastest initial speed v, where something can be
    hit, W(A d) = M v^2 / 2. The linear law's force k A does not grow with depth: the weight
    needs the contact area M g / k, which an edge or corner contact reaches at about
    d / L = M g / (k A). Then:

    * weight, d / L above OVERLAP_ERROR, dt = "auto": SceneError: the body sinks through what
      carries it, and the automatic time step (set at 0.1% overlap) is far longer than the
      time the body takes to fall its own size. The fix names the k that keeps d / L at
      OVERLAP_WARNING.
    * weight, m > 2 (stiffening laws): SceneError where the step is unstable at d,
      dt > 2 sqrt(M / K(d)) with the tangent stiffness K(d) = k (m - 1) (A d)^(m - 2) A^2
      (1/pi of the local period).
    * otherwise d / L above OVERLAP_WARNING (or an unstable step at the impact overlap): a
      warning. Initial speeds only warn: the bodies need not meet anything.
    * the linear law with gravity and something to carry the bodies: a warning that a face
      contact has no resting depth (its force k A is the same at any depth).

    The mesh walls are checked first (:func:`check_mesh_walls`), their warnings returned with these.
    """
    return check_mesh_walls(scene, a, ts) + _check_body_loads(scene, a, ts)


def _check_body_loads(scene, a, ts: TimeStep) -> list[str]:
    """The bodies' part of :func:`check_loads`."""
    free = a["kind"] == KIND_FREE
    if not free.any():
        return []
    table = scene.pair_table()
    mats = list(scene.materials.values())
    law, m = table["law"], float(table["exponent"])
    k_pair = np.asarray(table["k"], dtype=np.float64)
    present = set(distinct_codes(a["material"], len(mats)).tolist())
    planes = [*scene.planes, *scene.mesh_walls]
    present.update(scene.material_index(p.material) for p in planes)
    present = np.array(sorted(present))
    support = bool(planes) or bool((a["kind"] != KIND_FREE).any())
    partners = bool(planes) or scene.num_bodies >= 2
    g = float(np.linalg.norm(scene.gravity))
    v_hit = 0.0
    if partners and a["velocity"].any():  # (bodies at rest need no norms)
        speeds = row_norms(a["velocity"][a["kind"] != KIND_FIXED])
        v_hit = float(speeds.max()) if speeds.size else 0.0
    if not ((support and g > 0.0) or v_hit > 0.0):
        return []
    shapes = list(scene.shapes.values())
    dt = ts.dt
    out = []
    rest = []
    if law == "linear" and support and g > 0.0:
        rest.append(
            "law = 'linear' cannot bring a body to rest on a face: its force k A (A the contact area) does not "
            "grow with the overlap depth, so a face that carries a body's weight is either pushed off (k A above "
            "the weight) or sinks until the area changes, and the body chatters or sinks instead of resting; use "
            "law = 'hertz' or law = 'power' (with m > 1) for bodies that rest under gravity "
            f"(materials.{mats[0].name}.law)"
        )
    n_code = len(shapes) * len(mats)
    free_code = np.where(free, body_codes(a["shape"], a["material"], len(shapes), len(mats)), n_code)
    combo = distinct_codes(free_code, n_code + 1)
    combo = combo[combo < n_code]
    for c in combo.tolist():
        sh, mi = shapes[c // len(mats)], c % len(mats)
        mat = mats[mi]
        i = first_with_code(free_code, [c], n_code)
        mass = mat.density * sh.volume
        ln_a, ln_l = (2.0 / 3.0) * _ln(sh.volume), _ln(sh.volume) / 3.0
        j = int(present[np.argmin(k_pair[mi, present])])
        k = float(k_pair[mi, j])
        soft = min((mats[mi], mats[j]), key=lambda x: x.k).name
        label = f"{scene.body_label(i)} of material {mat.name!r}"
        label += f" against {mats[j].name!r}" if j != mi else ""
        for case in _loads(mass, ln_l, g if support else 0.0, v_hit):
            found = _judge_load(scene, case, m, law, k, soft, mass, ln_a, ln_l, dt, label)
            if found is not None:
                out.append(found)
    if not out:
        return rest
    # One line for the scene: the softest case, and how many more there are.
    out.sort(key=lambda x: -x[0])
    more = f" ({len(out) - 1} more shapes or materials are soft too)" if len(out) > 1 else ""
    return rest + [out[0][1] + more]


def _judge_load(scene, case, m, law, k, soft, mass, ln_a, ln_l, dt, label):
    """One load of :func:`_loads` on a face contact of stiffness ``k``: raise a SceneError where it
    fails (see :func:`check_loads`), return ``(relative depth, warning)`` where it is soft, else None."""
    load, cause, into, scale, t_scale = case
    ln_ad = _face_overlap(load, m, _ln(k), ln_a, ln_l)
    rel = _exp(ln_ad - ln_a - ln_l)
    ln_target = _ln(OVERLAP_WARNING) + ln_a + ln_l
    unstable = False
    if m > 2.0:
        ln_kt = _ln(k) + _ln(m - 1.0) + (m - 2.0) * ln_ad + 2.0 * ln_a
        unstable = ln_kt > _ln(4.0 * mass) - 2.0 * _ln(dt)
        if scene.dt == "auto":
            # The auto step goes like 1/sqrt(k), so K(d) dt^2 / k depends on d only: the fix
            # keeps d where dt is at most 1/8 of the local period, K dt^2 <= M (pi / 4)^2.
            ln_bound = 2.0 * _ln(math.pi / 4.0) + _ln(mass) - 2.0 * _ln(dt) - _ln(k) - _ln(m - 1.0)
            ln_target = min(ln_target, (ln_bound - 2.0 * ln_a) / (m - 2.0))
    depth = f"{cause} about {_fmt_exp(ln_ad - ln_a - ln_l)} times its size ({_exp(ln_l):.3g} m) {into}"
    if not unstable and rel <= OVERLAP_WARNING:
        return None
    ln_need = _stiffness_for(load, m, ln_target, ln_a, ln_l)
    weight = load > 0.0
    if unstable:
        k_tan = _exp(_ln(k) + _ln(m - 1.0) + (m - 2.0) * ln_ad + 2.0 * ln_a)
        depth += (
            f", where the law (m = {m:g} > 2 stiffens with depth) has a stiffness of {k_tan:.3g} N/m "
            f"and the time step {dt:.3g} s is above the stable {2.0 * math.sqrt(mass / k_tan):.3g} s"
        )
    key = f"materials.{soft}.k"
    g_max = _gravity_beyond_any_k(scene, mass, m, ln_target, ln_a, ln_l) if weight and ln_need > _ln(F32_HIGH) else None
    if g_max is not None:
        g = float(np.linalg.norm(scene.gravity))
        fix = (
            f"no k within float32's range (up to {F32_HIGH:.2g}) carries that weight: the gravity "
            f"{list(scene.gravity)!r} ({g / STANDARD_GRAVITY:.3g} times standard gravity) is too strong for these "
            f"bodies; use a gravity of at most {g_max:.3g} m/s^2"
        )
        key = "simulation.gravity"
    elif ln_need > _ln(F32_HIGH):
        fix = f"no k within float32's range (up to {F32_HIGH:.2g}) is stiff enough: " + (
            "use a smaller m (W = k V^m / m gives almost no force at small overlaps when m is large)"
            if law == "power"
            else "use smaller densities or larger bodies"
        )
    elif unstable and scene.dt != "auto":
        fix = 'lower dt (or use dt = "auto" with a larger k)'
    else:
        fix = f"raise k of {soft!r} to at least {_exp(ln_need):.3g} {LAW_UNITS[law]}"
    if weight and (unstable or (rel > OVERLAP_ERROR and scene.dt == "auto")):
        why = (
            f" (the automatic time step, {dt:.3g} s, is {dt / t_scale:.3g} times {scale})"
            if scene.dt == "auto" and not unstable
            else ""
        )
        head = "too soft" if rel > OVERLAP_ERROR else "unstable at this time step"
        raise scene.error(
            f"the contacts of {label} are {head}: {depth}{why}; {fix}"
            + (" (a pair's k is the harmonic mean of its materials' k)" if fix.startswith("raise") else ""),
            "simulation.dt" if fix.startswith("lower") else key,
        )
    return rel, f"the contacts of {label} are soft: {depth}; {fix} ({key})"


def tunnelling_limits(scene, a, dt: float) -> TunnelLimits:
    """Per body, the speed of its fastest point (``|v| + |w| r``, r its bounding radius) above which
    it may tunnel at time step ``dt`` [s]; host-only (the simulator checks it once per chunk).

    Two bounds, with h the smallest half-thickness of any body (its hull's smallest width over
    its face normals, halved) and k the softest pair the body can meet:

    * step: ``v dt <= TUNNEL_STEP_FRACTION h``;
    * energy: a body of volume V and width w meets the thin one with its mean cross-section A = V / w
      (a cube's face, a plate lying flat); the overlap stops growing once it has crossed the
      thinnest thickness, or its own (a plane wall), at ``V_c = A min(w, 2 h)``, so
      ``m v^2 / 2 <= TUNNEL_ENERGY_FRACTION W(V_c)`` with the law ``W = k V^m / m``.
    """
    shapes = list(scene.shapes.values())
    shape_widths = np.array([shape_width(sh) for sh in shapes])
    n_mat = len(scene.material_names)
    # The limits depend on a body's shape and material alone: worked out per (shape, material) pair present
    # (the same operations on the same numbers), then given to the bodies.
    code = body_codes(a["shape"], a["material"], len(shapes), n_mat)
    n_code = len(shapes) * n_mat
    present = np.bincount(code, minlength=n_code) > 0 if len(code) else np.zeros(0, dtype=bool)
    pairs = np.flatnonzero(present)
    used = distinct_codes(pairs // n_mat, len(shapes))
    used_width = shape_widths[used]
    if used_width.size and not np.isnan(used_width).any():
        # the first body that thin
        thinnest = first_with_code(a["shape"], used[used_width == used_width.min()], len(shapes))
    else:
        thinnest = int(np.argmin(shape_widths[a["shape"]]))
    h = 0.5 * float(shape_widths[a["shape"][thinnest]])
    table = scene.pair_table()
    m = float(table["exponent"])
    k_pair = np.asarray(table["k"], dtype=np.float64)
    materials = set(np.flatnonzero(np.bincount(a["material"], minlength=n_mat)).tolist())
    materials.update(scene.material_index(p.material) for p in [*scene.planes, *scene.mesh_walls])
    materials = np.array(sorted(materials))
    shape_of, material_of = pairs // n_mat, pairs % n_mat
    width = shape_widths[shape_of]
    volume = np.array([sh.volume for sh in shapes], dtype=np.float64)[shape_of]
    k = k_pair[:, materials].min(axis=1)[material_of]
    density = np.array([mat.density for mat in scene.materials.values()])
    mass = np.asarray(density[material_of] * np.array([sh.volume for sh in shapes])[shape_of], dtype=np.float64)
    with np.errstate(all="ignore"):
        v_cross = volume / width * np.minimum(width, 2.0 * h)
        ln_w = np.log(k) + m * np.log(v_cross) - math.log(m)
        v_energy = np.exp(0.5 * (math.log(2.0 * TUNNEL_ENERGY_FRACTION) + ln_w - np.log(mass)))
    v_energy = np.where(mass > 0.0, v_energy, np.inf)
    v_step = TUNNEL_STEP_FRACTION * h / dt
    # per code (absent codes never read), then given to the bodies: one gather, or one fill where one code is used
    code_limit = np.full(n_code, np.inf)
    code_limit[pairs] = np.minimum(v_step, v_energy)
    code_step = np.zeros(n_code, dtype=bool)
    code_step[pairs] = v_step <= v_energy
    if pairs.size == 1:
        limit = np.full(len(code), code_limit[pairs[0]])
        step_bound = np.full(len(code), code_step[pairs[0]])
    else:
        limit = code_limit[code]
        step_bound = code_step[code]
    if scene.num_bodies < 2 and not scene.planes and not scene.mesh_walls:
        limit = np.full(scene.num_bodies, np.inf)  # nothing to pass through
    return TunnelLimits(
        body_speed_limit=limit,
        body_step_bound=step_bound,
        half_thickness=h,
        thinnest=thinnest,
    )


def check_tunnelling(scene, a, dt: float, limits: TunnelLimits | None = None) -> list[str]:
    """A warning when a body's initial speed (of its fastest point) is above its
    :func:`tunnelling_limits` (``limits``, where they are at hand); the run still starts (the body may slow
    down before it meets anything)."""
    moving = a["kind"] != KIND_FIXED
    if not moving.any() or not (a["velocity"].any() or a["angular_velocity"].any()):
        return []  # (every body at rest: no speed is above a limit, and none need be worked out)
    shapes = list(scene.shapes.values())
    radius = np.array([sh.radius for sh in shapes])[a["shape"]]
    speed = row_norms(a["velocity"]) + row_norms(a["angular_velocity"]) * radius
    limits = tunnelling_limits(scene, a, dt) if limits is None else limits
    ratio = np.where(moving, speed / limits.body_speed_limit, 0.0)
    i = int(np.argmax(ratio))
    if not ratio[i] > 1.0:
        return []
    more = int(np.count_nonzero(ratio > 1.0)) - 1
    return [
        f"{scene.body_label(i)} starts at {limits.describe(i, float(speed[i]), dt)}"
        + (f" ({more} more bodies are that fast)" if more else "")
    ]


def check_motion_speeds(scene, a, dt: float) -> list[str]:
    """A warning per motion that moves what follows it (box walls, kinematic bodies, plane and mesh walls) faster
    than the slowest :func:`tunnelling_limits` of the free bodies: they may pass through it, or be thrown out."""
    free = a["kind"] == KIND_FREE
    followers: dict[str, list[str]] = {}
    for i, name in sorted(scene.body_motion.items()):
        followers.setdefault(name, []).append(f"body {i}")
    walls = [
        *zip(scene.planes, scene.plane_keys, strict=True),
        *zip(scene.mesh_walls, scene.mesh_wall_keys, strict=True),
    ]
    for wall, key in walls:
        if wall.motion is not None:
            followers.setdefault(wall.motion, []).append(key)
    if not followers or not free.any():
        return []
    limits = tunnelling_limits(scene, a, dt)
    i = int(np.flatnonzero(free)[np.argmin(limits.body_speed_limit[free])])
    limit = float(limits.body_speed_limit[i])
    out = []
    for name, what in followers.items():
        motion = scene.motions[name]
        speed = motion.peak_speed(scene.gravity)
        if not speed > limit:
            continue
        fix = {"cycle": "its amplitude or gamma, or its frequency", "ramp": "its speed", "servo": "its max_speed"}
        names = ", ".join(what[:3]) + (f" and {len(what) - 3} more" if len(what) > 3 else "")
        out.append(
            f"motion {name!r} moves {names} at up to {speed:.3g} m/s, above the {limit:.3g} m/s at which "
            f"{scene.body_label(i)}, hit at that speed, may pass through what it hits or be thrown out: lower "
            f"{fix[motion.kind]} (motions.{name}) or raise k"
        )
    return out


def check_steps(scene, ts: TimeStep):
    """The steps of the run (``duration / dt``) at most MAX_STEPS."""
    if scene.duration is not None:
        steps, key = math.ceil(scene.duration / ts.dt - 1e-9), "simulation.duration"
    elif scene.steps is not None:
        steps, key = scene.steps, "simulation.steps"
    else:
        return
    if steps > MAX_STEPS:
        raise scene.error(
            f"a run of {steps:.3g} steps of {ts.dt:.3g} s is more than the simulator counts ({MAX_STEPS}, a "
            "32-bit step counter); shorten the run"
            + (" or use a larger time step (a softer k gives a longer automatic one)" if scene.duration else ""),
            key,
        )


# ------------------------------------------------------------------ scales a run cannot resolve


def _gravity_beyond_any_k(scene, mass, m, ln_target, ln_a, ln_l) -> float | None:
    """The largest gravity [m/s^2] whose weight of a body of ``mass`` the stiffest k within float32's range
    holds at the overlap ``ln_target`` (ln(A d), :func:`_face_overlap`), where standard gravity's weight
    would be held: the scene's gravity, not its materials, is then what no k can carry. Else None."""
    # _stiffness_for solved for the force at k = F32_HIGH.
    if m == 1.0:
        ln_load = _ln(F32_HIGH) + ln_a + (ln_target - ln_a - ln_l)
    else:
        ln_load = _ln(F32_HIGH) + ln_a + (m - 1.0) * ln_target
    g_max = _exp(ln_load) / mass
    return g_max if g_max >= STANDARD_GRAVITY else None


def check_position_spacing(scene, a) -> None:
    """SceneError where a body lies so far from the origin that float64 positions cannot resolve a contact
    there.

    The time step resolves a contact at an overlap of REFERENCE_DEPTH of a body's width (see
    :func:`time_step`); where the spacing of float64 numbers is larger than that for the thinnest body, an
    overlap is a few spacings deep at most, its force jumps between a few values and a body neither moves
    smoothly nor comes to rest (one at rest under gravity may never move at all). Closer in, the mixed
    precision moves a far body as it would at the origin (tests/test_precision.py). (The float32 positions
    of precision = "float32" resolve far less; ``polydem validate`` warns of those.)
    """
    shapes = list(scene.shapes.values())
    free = a["kind"] == KIND_FREE
    used = distinct_codes(a["shape"][free] if free.any() else a["shape"], len(shapes))
    thinnest = min(shape_width(shapes[int(s)]) for s in used)
    resolve = REFERENCE_DEPTH * thinnest
    if not (math.isfinite(resolve) and resolve > 0.0):
        return
    position = np.asarray(a["position"], dtype=np.float64)
    # The body farthest out along an axis sets the spacing: its coordinate is the largest of all.
    if not float(np.spacing(np.abs(position).max())) > resolve:
        return
    far = np.abs(position).max(axis=1)
    i = int(np.argmax(far))
    spacing = float(np.spacing(far[i]))
    # The largest distance whose float64 spacing (2^(e - 52) in [2^e, 2^(e+1))) is at most `resolve`.
    limit = 2.0 ** (math.floor(math.log2(resolve)) + 53)
    where = next((e["key"] for e in scene.emitters if e["first"] <= i <= e["last"]), None)
    raise scene.error(
        f"{scene.body_label(i)} is at {a['position'][i].tolist()!r} m, where float64 numbers are {spacing:.3g} m "
        f"apart: more than {REFERENCE_DEPTH:g} of the thinnest body's width ({thinnest:.3g} m), the overlap at "
        f"which the time step resolves a contact, so no contact can be resolved there; place the bodies within "
        f"{limit:.3g} m of the origin (move the whole scene: only relative positions matter)",
        f"{where}.region" if where is not None else f"bodies[{i}].position",
    )


def check_toe_step(scene, ts) -> list[str]:
    """A warning where the scene gives a dt above TOE_STEP_WARNING recommended steps under a law with the
    resolved toe (:func:`has_toe`): the toe is the run's step's there (``Model.toe_dt``), and its V_c grows as
    dt^(2 / (2 - m)), so overlaps below it follow a stiffness set by dt instead of k, and a pile comes out
    otherwise than at the recommended step (BENCHMARKS.md sections 24-25)."""
    if scene.dt == "auto" or not (ts.recommended > 0.0 and ts.dt > TOE_STEP_WARNING * ts.recommended):
        return []
    table = scene.pair_table()
    law, m = table["law"], float(table["exponent"])
    if not has_toe(law, m):
        return []
    ratio = ts.dt / ts.recommended
    power = 2.0 / (2.0 - m)
    return [
        f"simulation.dt = {ts.dt:.3g} s is {ratio:.3g} times the recommended step {ts.recommended:.3g} s: under the "
        f"{law} law the resolved toe (the law below a volume V_c, which keeps a face at rest resolved) follows the "
        f"step above the recommended one, V_c ~ dt^{power:.3g}, here {ratio**power:.3g} times larger, and overlaps "
        "below it follow a stiffness set by dt instead of k, so a pile settles otherwise than at the recommended "
        f'step; for results that hold as dt is refined use dt = "auto" or at most {TOE_STEP_WARNING:g} times it '
        f"({TOE_STEP_WARNING * ts.recommended:.3g} s)"
    ]


def check_resting_ringing(scene) -> list[str]:
    """A warning where a power law without the resolved toe (m >= 2) meets a restitution below
    RINGING_RESTITUTION under gravity: the hysteresis branches do not damp an oscillation about the unloading
    branch (1/e^2 stiffer than loading), so a face that comes to rest after an impact swings for many of its
    periods (BENCHMARKS.md section 26e). Hertz and power m < 2 rest on their toe."""
    table = scene.pair_table()
    law, m = table["law"], float(table["exponent"])
    # (m < 2 with m > 1 rests on the toe; m = 1 is the linear law's force, which has no resting depth at all)
    if law != "power" or m < 2.0 or not np.any(np.asarray(scene.gravity, dtype=np.float64) != 0.0):
        return []
    e = np.asarray(table["restitution"], dtype=np.float64)
    low = float(np.min(e))
    if not low < RINGING_RESTITUTION:
        return []
    names = list(scene.materials)
    i, j = np.unravel_index(int(np.argmin(e)), e.shape)
    pair = f"{names[i]!r}" if i == j else f"{names[i]!r} and {names[j]!r}"
    return [
        f"restitution {low:g} between {pair} under the power law with m = {m:g} (no resolved toe): a contact that "
        "comes to rest after an impact rings, its force swinging from step to step (a cube set down on a floor at "
        "e = 0.1 still reports 0.8 to 1.2 times its weight 0.3 s later and rests after about 1 s); for resting "
        f'contacts give restitution >= {RINGING_RESTITUTION:g} or use law = "hertz"'
    ]


def check_run_span(scene, dt: float, steps: int, source: str, default: bool = False) -> list[str]:
    """Warnings about the simulated time a run of ``steps`` steps of ``dt`` [s] covers (``source``: where the
    steps come from, for the message; ``default``: they are the command's default, nothing asked for them).

    * No body moves: over the run, gravity and the initial velocities move no free or kinematic body by
      the spacing of its position numbers (float64, or float32 for precision = "float32"), so the run
      ends where it started: a time step far too short (an extreme k or density, a dt in the wrong
      unit) or a run of a few steps of a fine one.
    * Else, a run of the default length covering less than DEFAULT_RUN_MIN_TIME.
    """
    a = scene.body_arrays()
    moving = a["kind"] != KIND_FIXED
    if not moving.any() or not (dt > 0.0 and steps > 0):
        return []
    span = steps * dt
    shapes = list(scene.shapes.values())
    radius = np.array([sh.radius for sh in shapes], dtype=np.float64)[a["shape"]]
    g = float(np.linalg.norm(np.asarray(scene.gravity, dtype=np.float64)))
    driven = g > 0.0 or np.any(a["velocity"][moving] != 0.0) or np.any(a["angular_velocity"][moving] != 0.0)
    with np.errstate(all="ignore"):
        # Symplectic Euler from rest: g t (t + dt) / 2 after t.
        fall = np.where(a["kind"] == KIND_FREE, 0.5 * g * span * (span + dt), 0.0)
        reach = row_norms(a["velocity"]) * span + row_norms(a["angular_velocity"]) * radius * span + fall
        dtype = np.float32 if scene.precision == "float32" else np.float64
        far = np.abs(np.asarray(a["position"], dtype=np.float64)).max(axis=1) + radius
        spacing = np.spacing(far.astype(dtype)).astype(np.float64)
    run = f"{steps} steps of {dt:.3g} s ({source}) cover {span:.3g} s"
    # Without gravity or initial velocities only contacts (initial overlaps) move bodies: nothing to estimate.
    if driven and not np.any(reach[moving] >= spacing[moving]):
        i = int(np.flatnonzero(moving)[np.argmax(reach[moving] / spacing[moving])])
        return [
            f"{run}, in which gravity and the initial velocities move no body as far as the spacing of its "
            f"position numbers ({scene.body_label(i)} the furthest: {reach[i]:.3g} m against {spacing[i]:.3g} m): "
            f"unless contacts push them, the run leaves every body where it is; {_time_step_cause(scene)}"
        ]
    if default and span < DEFAULT_RUN_MIN_TIME:
        return [
            f"{run}, less than {DEFAULT_RUN_MIN_TIME:g} s; {_time_step_cause(scene)}, or give the run's length "
            "(simulation.duration or --duration)"
        ]
    return []


def _time_step_cause(scene) -> str:
    """What sets the time step of a run, and what to check, for :func:`check_run_span`."""
    if scene.dt != "auto":
        return f'simulation.dt = {scene.dt!r} s sets it: check its unit (seconds) or use dt = "auto"'
    try:
        ts = time_step(scene)
    except Exception:  # validate() reports the scene's own problems; only the cause is wanted here
        return "check the materials' k and density"
    i = ts.lightest
    mat = list(scene.materials.values())[int(np.asarray(scene.body_material)[i])]
    return (
        f'dt = "auto" takes it from the stiffest contact of {scene.body_label(i)}: check k = {mat.k!r} and '
        f"density = {mat.density!r} of materials.{mat.name}"
    )


# ------------------------------------------------------------------ mesh walls


def check_mesh_walls(scene, a, ts: TimeStep) -> list[str]:
    """Mesh walls: a thickness their cells resolve (SceneError), free bodies that start in their solid
    (as plane walls: a SceneError beyond INITIAL_OVERLAP_ERROR of the body's thickness, a warning beyond
    INITIAL_OVERLAP_WARNING), triangles that fold back onto their neighbours (warning), a thickness above
    half the thinnest part of a closed wall (warning) and a wall that moves faster than the bodies it meets
    can take (warning, as :func:`check_tunnelling` warns of a drum's parts). Returns the warnings."""
    walls = list(zip(scene.mesh_walls, scene.mesh_wall_keys, strict=True))
    if not walls:
        return []
    for wall, key in walls:
        _check_mesh_thickness(scene, wall, key)
    found = _mesh_wall_speeds(scene, a, ts.dt)
    records = []
    for wall, key in walls:
        records += _mesh_overlaps(scene, wall, key, a)
    found += _report_mesh_overlaps(scene, records)
    for wall, key in walls:
        found += _mesh_folds(scene, wall, key)
        found += _mesh_thickness_rule(scene, wall, key)
    return found


# Neighbouring triangles whose normals are this close to opposite (1 - cos of the angle between the
# faces, 0.8 degrees) fold back onto each other.
FOLD = 1e-4


def _mesh_folds(scene, wall, key) -> list[str]:
    """A warning where two triangles sharing an edge fold back onto each other (their normals opposite):
    one of them is turned over, and the solid behind it lies on the grains' side. Kept with the cells."""
    memo = mesh_wall_memo(scene, wall, scene.mesh_wall_thickness(wall))
    if "folds" not in memo:
        memo["folds"] = _folds(wall, key)
    return memo["folds"]


def _folds(wall, key) -> list[str]:
    from polydem.meshwall import edge_pairs, triangle_normals

    f = np.asarray(wall.triangles, dtype=np.int64)
    normals, _ = triangle_normals(np.asarray(wall.vertices, dtype=np.float64), f)
    f1, _, f2, _, _ = edge_pairs(f, f"mesh wall {key}")
    folded = np.einsum("ek,ek->e", normals[f1], normals[f2]) < FOLD - 1.0
    if not folded.any():
        return []
    k = int(np.flatnonzero(folded)[0])
    return [
        f"mesh wall {key}: triangles {int(f1[k])} and {int(f2[k])} share an edge but fold back onto each other "
        f"(their normals are opposite; {int(folded.sum())} such edge(s)): one is turned over, a sliver whose solid "
        "lies on the grains' side, and grains that reach it are pushed the wrong way; remesh the surface there "
        "(e.g. trimesh's remove of degenerate and duplicate faces, or a smaller jitter of its vertices)"
    ]


def _check_mesh_thickness(scene, wall, key):
    """A SceneError where the wall's thickness and its triangles are too far apart for its cells."""
    from polydem.meshwall import MAX_SIZE_RATIO, thickness_problem, thickness_range, triangle_sizes

    h = scene.mesh_wall_thickness(wall)
    low, high = thickness_range(wall.vertices, wall.triangles)
    if low <= h <= high:
        return
    default = wall.thickness is None
    why = thickness_problem(
        wall.vertices, wall.triangles, h, " (the default: the free bodies' largest diameter)" if default else ""
    )
    if h < low and low <= high and not np.allclose(wall.scale, 1.0):
        # Triangles too large for the bodies: most likely the file's units.
        sizes = triangle_sizes(wall.vertices, wall.triangles)
        s = float(np.max(np.abs(wall.scale)))
        s_hi = s * MAX_SIZE_RATIO * h / float(sizes.max())
        s_lo = s * h / (MAX_SIZE_RATIO * float(sizes.min()))
        raise scene.error(
            f"with scale {s:g}, {why}; or, with this thickness, a scale from {s_lo:.3g} to {s_hi:.3g} (the mesh "
            "file's unit in m: 0.001 for mm)",
            f"{key}.scale",
        )
    raise scene.error(why + (f" ({key}.thickness)" if default else ""), f"{key}.thickness")


def _mesh_wall_speeds(scene, a, dt: float) -> list[str]:
    """A warning per mesh wall whose fastest point (``|v| + |w| r``, r its farthest vertex from the
    pivot) moves faster than the slowest :func:`tunnelling_limits` of the free bodies it may meet."""
    free = a["kind"] == KIND_FREE
    moving = [(w, k) for w, k in zip(scene.mesh_walls, scene.mesh_wall_keys, strict=True) if w.moving]
    if not moving or not free.any():
        return []
    limits = tunnelling_limits(scene, a, dt)
    i = int(np.flatnonzero(free)[np.argmin(limits.body_speed_limit[free])])
    limit = float(limits.body_speed_limit[i])
    out = []
    for wall, key in moving:
        reach = float(np.linalg.norm(wall.vertices - np.asarray(wall.pivot), axis=1).max())
        slide = float(np.linalg.norm(wall.velocity))
        turn = float(np.linalg.norm(wall.angular_velocity)) * reach
        speed = slide + turn
        if not speed > limit:
            continue
        if limits.body_step_bound[i]:
            why = (
                f"a step of {dt:.3g} s moves it {TUNNEL_STEP_FRACTION:g} times the smallest half-thickness of a "
                f"body ({limits.half_thickness:.3g} m)"
            )
            fix = "or dt"
        else:
            why = (
                f"{scene.body_label(i)}, hit at that speed, would carry {1.0 / TUNNEL_ENERGY_FRACTION:g} times the "
                "energy its contact stores before the body is through"
            )
            fix = "or raise k"
        field = "angular_velocity" if turn >= slide else "velocity"
        out.append(
            f"mesh wall {key} moves its farthest point ({reach:.3g} m from the pivot) at {speed:.3g} m/s, above "
            f"the {limit:.3g} m/s at which {why}: the bodies it hits may pass through it or be thrown out at that "
            f"speed; lower its {field} ({key}.{field}) {fix}"
        )
    return out


def _mesh_overlaps(scene, wall, key, a) -> list[tuple]:
    """(relative depth, depth, body, where, of what, fix) of the free bodies (compound grains part by
    part) in the solid of ``wall`` at t = 0: a body vertex in a cell (its depth behind the triangle,
    over the body's thickness along the triangle's normal; behind a concave edge or corner, its
    distance from it over the body's width), a mesh vertex in a body (its depth in it over the body's
    width), and, in a closed wall, a body whose centre is inside the surface."""
    from polydem.compound import expand_bodies
    from polydem.meshwall import EDGE, TRIANGLE, cell_reach, is_closed, near_pairs, winding

    free = np.flatnonzero(a["kind"] == KIND_FREE)
    if not free.size:
        return []
    h = scene.mesh_wall_thickness(wall)
    cells = scene.mesh_wall_cells(wall, h)
    shapes = list(scene.shapes.values())
    convex, part, pos, quat, owner = expand_bodies(
        shapes, a["shape"][free], a["position"][free], a["orientation"][free]
    )
    owner = free[owner]
    pos = pos - np.asarray(wall.pivot, dtype=np.float64)  # into the cells' frame
    radius = np.array([s.radius for s in convex])[part]
    pi, ci = near_pairs(pos, radius, cells.cell_center, cells.cell_radius)
    best = {}  # body -> the deepest record

    def keep(rec):
        if rec[0] > INITIAL_OVERLAP_WARNING and (rec[2] not in best or rec[0] > best[rec[2]][0]):
            best[rec[2]] = rec

    rot = quat_to_matrix(quat)
    tol = 1e-9 * max(h, float(np.linalg.norm(np.ptp(wall.vertices, axis=0))))
    v, f = cells.vertices, cells.faces
    for s in np.unique(part[pi]).tolist():
        shape = convex[s]
        width = shape_width(shape)
        rows = np.flatnonzero(part[pi] == s)
        for lo in range(0, len(rows), 4096):
            sel = rows[lo : lo + 4096]
            p, c = pi[sel], ci[sel]
            pts = np.einsum("pij,vj->pvi", rot[p], shape.vertices) + pos[p][:, None, :]
            inside = cell_reach(cells, c, pts) <= tol
            kind = cells.cell_kind[c]
            src = cells.cell_source[c]
            front = cells.cell_front[c]
            depth = np.einsum("pvk,pk->pv", pts, front[:, :3]) * -1.0 + front[:, 3, None]
            along = np.einsum("pvk,pk->pv", pts, front[:, :3])
            thick = along.max(axis=1) - along.min(axis=1)
            # Behind a concave edge (src: its two vertices) or corner (its vertex): the distance from it.
            a_pt = v[np.where(kind == TRIANGLE, 0, src[:, 0])]
            b_pt = v[np.where(kind == EDGE, src[:, 1], 0)]
            axis = b_pt - a_pt
            axis /= np.maximum(np.linalg.norm(axis, axis=1, keepdims=True), 1e-300)
            off = pts - a_pt[:, None, :]
            off_line = off - np.einsum("pvk,pk->pv", off, axis)[..., None] * axis[:, None, :]
            dist = np.where((kind == EDGE)[:, None], np.linalg.norm(off_line, axis=2), np.linalg.norm(off, axis=2))
            depth = np.where((kind == TRIANGLE)[:, None], depth, dist)
            depth = np.where(inside, depth, -np.inf)
            deepest = np.argmax(depth, axis=1)
            d = depth[np.arange(len(p)), deepest]
            rel = d / np.where(kind == TRIANGLE, thick, width)
            for j in np.flatnonzero(rel > INITIAL_OVERLAP_WARNING).tolist():
                keep(_mesh_record(key, int(owner[p[j]]), float(rel[j]), float(d[j]), kind[j], src[j],
                                  front[j], pos[p[j]]))  # fmt: skip
            # Mesh vertices (the corners of the cells' triangles) inside the body.
            tri = kind == TRIANGLE
            if tri.any():
                corners = v[f[src[tri, 0]]]
                local = np.einsum("pji,pvj->pvi", rot[p[tri]], corners - pos[p[tri]][:, None, :])
                gap = shape.face_offsets - np.einsum("pvk,fk->pvf", local, shape.face_normals)
                inner = gap.min(axis=2)
                which = np.argmax(inner, axis=1)
                dd = inner[np.arange(len(which)), which]
                for j in np.flatnonzero(dd > INITIAL_OVERLAP_WARNING * width).tolist():
                    vi = int(f[src[tri][j, 0], which[j]])
                    keep(
                        (
                            float(dd[j] / width),
                            float(dd[j]),
                            int(owner[p[tri][j]]),
                            f"onto vertex {vi} of the mesh wall {key}, which pokes into it",
                            "its width",
                            f"move it off the wall by at least {dd[j]:.3g} m, or move the wall",
                        )
                    )
    # A body whose centre is inside a closed surface facing out lies in its solid, however deep.
    if is_closed(wall.triangles):
        bodies = np.setdiff1d(free, np.fromiter(best, dtype=np.int64, count=len(best)))
        wn = winding(a["position"][bodies], wall.vertices, wall.triangles)
        for i in bodies[wn > 0].tolist():
            best[i] = (
                1.0,
                h,
                i,
                f"or more inside the closed mesh wall {key} (past its thickness, where its cells end)",
                "its thickness",
                "move it out of the wall; if the bodies belong inside, the triangles face the wrong way: set "
                f"flip_normals = true ({key}.flip_normals)",
            )
    return list(best.values())


def _mesh_record(key, body, rel, depth, kind, src, front, centre):
    """The overlap record of a body vertex ``depth`` [m] in a cell of kind ``kind`` behind ``src``."""
    from polydem.meshwall import EDGE, TRIANGLE

    if kind == TRIANGLE:
        n = ", ".join(f"{x:.3g}" for x in front[:3])
        where = f"behind triangle {int(src[0])} of the mesh wall {key}"
        fix = (
            f"move it by at least {depth:.3g} m along the triangle's normal [{n}], to the side it faces, or move "
            "the wall"
        )
        if float(np.dot(front[:3], centre) - front[3]) < 0.0:
            fix += (
                "; if the bodies belong on the other side, the triangles face the wrong way: set flip_normals = "
                f"true ({key}.flip_normals)"
            )
        return rel, depth, body, where, "its thickness along the triangle's normal", fix
    what = (
        f"the concave edge between vertices {int(src[0])} and {int(src[1])}"
        if kind == EDGE
        else f"the concave corner at vertex {int(src[0])}"
    )
    return (
        rel,
        depth,
        body,
        f"behind {what} of the mesh wall {key}",
        "its width",
        f"move it out of the corner by at least {depth:.3g} m, or move the wall",
    )


def _report_mesh_overlaps(scene, records) -> list[str]:
    return report_overlaps(
        scene,
        records,
        f"bodies start in the solid of a mesh wall by more than {INITIAL_OVERLAP_WARNING:.0%} of their "
        "thickness, pushed out at the start",
        "move them out",
    )


def _mesh_thickness_rule(scene, wall, key) -> list[str]:
    """A warning where the cells behind two sides of the wall overlap: along the ray back from each
    triangle's centroid, the first triangle it leaves the solid through (one that shares no vertex
    with it) lies nearer than the two cells reach into the solid between them (twice the thickness
    where the two sides are parallel). Kept with the cells: it depends on nothing else."""
    from polydem.meshwall import near_pairs, ray_exit, ray_hits, triangle_normals, triangle_sizes

    h = scene.mesh_wall_thickness(wall)
    memo = mesh_wall_memo(scene, wall, h)
    if "rule" in memo:
        return memo["rule"]
    cells = scene.mesh_wall_cells(wall, h)
    v, f = cells.vertices, cells.faces
    normals, _ = triangle_normals(v, f)
    centroid = v[f].mean(axis=1)
    mid = centroid - h * normals
    ri, tj = near_pairs(mid, np.full(len(f), h), centroid, triangle_sizes(v, f))
    shares = (f[ri][:, :, None] == f[tj][:, None, :]).any(axis=(1, 2))
    ri, tj = ri[~shares], tj[~shares]
    t = ray_hits(centroid[ri], -normals[ri], v[f[tj]])
    ok = (t > 0.0) & (t <= 2.0 * h)
    ri, tj, t = ri[ok], tj[ok], t[ok]
    found = []
    if len(ri):
        # The nearest crossing of each ray, if it leaves the solid there.
        order = np.lexsort((t, ri))
        ri, tj, t = ri[order], tj[order], t[order]
        first = np.r_[True, ri[1:] != ri[:-1]]
        ri, tj, t = ri[first], tj[first], t[first]
        leaves = np.einsum("pk,pk->p", -normals[ri], normals[tj]) > 0.0
        ri, tj, t = ri[leaves], tj[leaves], t[leaves]
        here = ray_exit(cells, ri, centroid[ri], -normals[ri])
        there = ray_exit(cells, tj, centroid[ri] - t[:, None] * normals[ri], normals[ri])
        over = here + there > t * (1.0 + 1e-9)
        if over.any():
            k = int(np.argmin(np.where(over, t, np.inf)))
            default = " (the default: the free bodies' largest diameter)" if wall.thickness is None else ""
            found.append(
                f"mesh wall {key}: its thickness {h:.3g} m{default} is more than half the thickness of the wall "
                f"the mesh makes at triangle {int(ri[k])}, {t[k]:.3g} m through to triangle {int(tj[k])} "
                f"({int(over.sum())} triangles are that close to another side): the cells behind one side "
                "reach into those behind the other, and a body pressed in there meets the solid twice; give a "
                f"thickness below {0.5 * t[k]:.3g} m ({key}.thickness)"
            )
    memo["rule"] = found
    return found
