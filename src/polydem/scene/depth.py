"""Resting depth of a contact: how deep a face, an edge or a corner sinks under a load, and the k for a depth.

Host-only (numpy; no Warp): ``polydem validate`` prints these depths, and the benchmarks choose k with them.

The force of the volume model on a body pressed into a flat face (a plane wall, or a face of a larger body)
is ``F = W'(V) |S|``, with V the overlap volume and S the area vector of the body's faces inside the other,
whose length is the area of the cut: ``|S| = dV/dd`` for a press of depth d along a fixed direction. So
``F = d W(V(d)) / dd``: the force is the derivative of the energy with respect to the depth, and a body
under a load F rests where ``W'(V(d)) |S(d)| = F`` (on the loading branch: a contact left by an impact rests
on its unloading branch, a dent deeper).

Closed forms. Near a feature, ``V(d) = c d^j`` with j = 1 for a face (c its area A), 2 for an edge and 3
for a corner, and ``|S| = j c d^(j-1)``. Under ``W = k V^m / m`` (linear m = 1, hertz m = 1.5, power m):

    F = j k c^m d^(j m - 1),      d = (F / (j k c^m))^(1 / (j m - 1)),      k = F / (j c^m d^(j m - 1))

so the depth goes as (F / k) to the power 1 / (j m - 1):

    law       face (j = 1)        edge (j = 2)         corner (j = 3)
    linear    none (see below)    F / k                (F / k)^(1/2)
    hertz     (F / k)^2           (F / k)^(1/2)        (F / k)^(2/7)
    power m   (F / k)^(1/(m-1))   (F / k)^(1/(2m-1))   (F / k)^(1/(3m-1))

A face is stiff and a corner soft: under hertz, a hundredfold load takes a face 10^4 times deeper but a
corner only 3.7 times; and raising k a hundredfold leaves a corner 27% of its depth, a face 1e-4. A
corner's force grows as d^3.5 (V ~ d^3, |S| ~ d^2), so the corner, not the face, sets how far a pile is
from the rigid limit. Under the linear law a face's force k A does not depend on the depth: a face lighter
than that floats on the surface (depth 0), a heavier one sinks. For a cube of edge a, pressed face first
(c = a^2), edge first with both faces at 45 degrees (c = a, exact for d <= a / sqrt 2) and corner first
along a body diagonal (c = sqrt(3) / 2: the cap is the corner tetrahedron of legs sqrt(3) d, exact for
d <= a / sqrt 3); see :func:`cube_cap`.

Any convex shape (:class:`Cut`): the cap of the hull beyond a plane at depth d below its lowest vertex
along a direction, whose cross-section area A(t) is a quadratic in t between consecutive vertex depths, so
V(d) is exact by Simpson's rule on each interval. :func:`resting_depth` solves ``W'(V(d)) A(d) = F`` (a
bracket, then regula falsi in log-log) for each face (pressed along its normal), edge (along the sum of its
two faces' normals) and corner (along the sum of its faces' normals) and returns the deepest;
:func:`stiffness_for_depth` is the inverse, the k that keeps every corner (or edge, or face) at most a given
depth under a load.

The resolved toe (:mod:`polydem.kernels.response`, ``toe_volume``). Under laws stiffer than linear at
V = 0 (hertz, power with m < 2) the simulator continues the law below a toe volume V_c with
``W'(V) = a V + b V^2``, ``a = (3 - m) k V_c^(m-2)``, ``b = (m - 2) k V_c^(m-3)`` (W' and W'' continuous
at V_c). V_c is set per pair so that a face of area ``A_toe`` (the smaller of the two bodies' largest face
areas) on the unloading branch (1/e^2 stiffer) has omega dt = TOE_OMEGA_DT against the pair's translational
mass, dt the larger of the run's step and the scene's recommended one (``Model.toe_dt``), so that a shorter
step integrates the same law:
``a A_toe^2 inv_mass / e^2 = (TOE_OMEGA_DT / dt)^2``, so ``a = (TOE_OMEGA_DT e / dt)^2 / (inv_mass A_toe^2)``
whatever k is. A lightly loaded face (A d << V_c) therefore rests on a linear spring of stiffness a A^2:

    d = F / (a A^2) = F inv_mass (A_toe / A)^2 (dt / (TOE_OMEGA_DT e))^2

(deeper by about a third of A d / V_c, the b V^2 term), set by that step and the pair's mass, not by k.
A body resting on its largest face on a wall under its own weight (F inv_mass = g, A = A_toe) sits
``g (dt / (TOE_OMEGA_DT e))^2`` deep: 1.4e-9 m at dt = 6e-6 s, e = 0.5. Loads above
the toe's ``F_c = k V_c^(m-1) A`` follow the law. Edges and corners below V_c rest on the toe too, where
their force ``j a c^2 d^(2j-1)`` (a corner's d^5) is softer than the law's. Where the reference contact
sets the recommended step (dt^2 ~ 1/k) V_c is a fixed share of the grain's volume, 4e-5 for a pair of 1 cm cubes
with e = 0.5 (so corners up to 3.5% of the edge deep), growing as 1/e^4; where the resting rule sets it
(dt ~ 1/k, at stiffer k) V_c shrinks as 1/k^2. Give :class:`Toe` to include it; :func:`stiffness_for_depth`
takes a function of k for it (:func:`auto_dt`), and :func:`pile_depths` says where a depth is the toe's.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from polydem.kernels.laws import LAW_SPECS, LAWS, TOE_MIN_RESTITUTION, TOE_OMEGA_DT
from polydem.scene.bodies import BodyKind
from polydem.shapes import largest_face_area

__all__ = [
    "FEATURES",
    "Law",
    "Toe",
    "Cut",
    "Rest",
    "PileDepth",
    "toe_volume",
    "cube_cap",
    "power_law_depth",
    "shape_cuts",
    "resting_contact",
    "resting_depth",
    "stiffness_for_depth",
    "auto_dt",
    "pile_depths",
]

FEATURES = ("face", "edge", "corner")
"""What of a body presses into a flat face: j = 1, 2, 3 in ``V = c d^j``."""

# Most steps of the root finder within one piece of V(d) (it takes about ten).
_STEPS = 110
# Where a piece is searched for the load, as fractions of it, in order: the first that carries it and the
# one before bracket the depth.
_SAMPLES = np.linspace(0.0, 1.0, 33)[1:]


def _exponent(law: str, m: float | None) -> float:
    if law not in LAWS:
        raise ValueError(f"law must be one of {', '.join(LAWS)}, got {law!r}")
    spec = LAW_SPECS[law]
    if spec.fixed_exponent is not None:
        return spec.fixed_exponent
    if m is None or not math.isfinite(m) or m < 1.0:
        raise ValueError(f"the {law} law needs an exponent m >= 1 ({spec.formula}), got m = {m!r}")
    return float(m)


def toe_volume(
    law: str, k: float, m: float | None, e: float, dt: float, area: float, r_min: float, inv_mass: float
) -> float:
    """V_c [m^3] of the resolved toe, as the simulator's ``toe_volume`` computes it (module docstring).

    ``k`` in the law's units, ``e`` the restitution, ``dt`` [s], ``area`` the smaller of the pair's largest
    face areas [m^2], ``r_min`` the smaller bounding radius of the pair [m], ``inv_mass`` 1/m_a + 1/m_b
    [1/kg] (1/m against a wall or a fixed body). 0 (no toe) for the linear law, m >= 2, no step or no mass;
    never above r_min^3.
    """
    mm = _exponent(law, m)
    if not LAW_SPECS[law].toe or not (mm < 2.0 and dt > 0.0 and inv_mass > 0.0 and k > 0.0 and area > 0.0):
        return 0.0
    ln_x = (
        math.log((3.0 - mm) * k)
        + 2.0 * math.log(area * dt)
        + math.log(inv_mass)
        - 2.0 * math.log(max(e, TOE_MIN_RESTITUTION) * TOE_OMEGA_DT)
    )
    return math.exp(min(ln_x / (2.0 - mm), 3.0 * math.log(r_min)))


@dataclass(frozen=True)
class Toe:
    """What sets a pair's toe volume: restitution ``e``, time step ``dt`` [s], ``inv_mass`` = 1/m_a + 1/m_b
    [1/kg], ``r_min``, the pair's smaller bounding radius [m], and ``area``, the smaller of the pair's largest
    face areas [m^2] (None: the pressed shape's)."""

    e: float
    dt: float
    inv_mass: float
    r_min: float | None = None
    area: float | None = None


@dataclass(frozen=True)
class Law:
    """A contact law W(V) with the simulator's toe below ``vc`` [m^3] (0: none).

    ``kind`` a name of :data:`polydem.kernels.laws.LAWS`: "linear" (W = k V), "hertz" (W = 2/3 k V^1.5)
    or "power" (W = k V^m / m, ``m`` >= 1).
    """

    kind: str
    k: float
    m: float | None = None
    vc: float = 0.0
    exponent: float = field(init=False)  # the m of W = k V^m / m: 1 linear, 1.5 hertz

    def __post_init__(self):
        object.__setattr__(self, "exponent", _exponent(self.kind, self.m))
        if not (math.isfinite(self.k) and self.k > 0.0):
            raise ValueError(f"k must be a positive finite number, got {self.k!r}")

    @classmethod
    def with_toe(cls, kind: str, k: float, m: float | None, toe: Toe | None, shape) -> Law:
        """The law with the toe of ``toe`` (None: none); the pressed ``shape`` stands in for a missing
        ``toe.r_min`` or ``toe.area``."""
        if toe is None:
            return cls(kind, k, m)
        r_min = float(shape.radius) if toe.r_min is None else toe.r_min
        area = largest_face_area(shape) if toe.area is None else toe.area
        return cls(kind, k, m, toe_volume(kind, k, m, toe.e, toe.dt, area, r_min, toe.inv_mass))

    def derivative(self, volume: float) -> float:
        """W'(V) [Pa] at an overlap volume V >= 0 [m^3]: the toe's below ``vc``, else the law's."""
        m = self.exponent
        if volume < self.vc:
            x = volume / self.vc
            return self.k * self.vc ** (m - 1.0) * x * ((3.0 - m) + (m - 2.0) * x)
        if volume <= 0.0:
            return self.k if m == 1.0 else 0.0
        return float(LAW_SPECS[self.kind].derivative(volume, self.k, m))


def cube_cap(edge: float, feature: str) -> tuple[float, int, float]:
    """``(c, j, d_max)`` of a cube of edge ``edge`` [m] pressed ``feature`` first into a half space:
    ``V = c d^j``, ``|S| = j c d^(j-1)``, exact for depths up to d_max [m] (module docstring)."""
    if feature == "face":
        return edge * edge, 1, edge
    if feature == "edge":
        return edge, 2, edge / math.sqrt(2.0)
    if feature == "corner":
        return math.sqrt(3.0) / 2.0, 3, edge / math.sqrt(3.0)
    raise ValueError(f"feature must be one of {', '.join(FEATURES)}, got {feature!r}")


def power_law_depth(load: float, k: float, m: float, c: float, j: int) -> float:
    """``d = (F / (j k c^m))^(1 / (j m - 1))`` [m]: the depth of a cap ``V = c d^j`` under ``load`` F [N]
    and W = k V^m / m, without the toe. For j m = 1 (a face under the linear law) the force k c does not
    depend on the depth: 0 where it carries the load, inf where not."""
    p = j * m - 1.0
    if p <= 0.0:
        return 0.0 if k * c >= load else math.inf
    return (load / (j * k * c**m)) ** (1.0 / p)


def _cross(a, b) -> np.ndarray:
    # np.cross costs tens of microseconds on 3-vectors; a Cut is built per face, edge and corner.
    return np.array([a[1] * b[2] - a[2] * b[1], a[2] * b[0] - a[0] * b[2], a[0] * b[1] - a[1] * b[0]])


def _plane_basis(u: np.ndarray) -> np.ndarray:
    """(2, 3): two unit vectors normal to the unit vector u and to each other."""
    a = (1.0, 0.0, 0.0) if abs(u[0]) < 0.9 else (0.0, 1.0, 0.0)
    e1 = _cross(u, a)
    e1 /= math.sqrt(float(e1 @ e1))
    return np.array([e1, _cross(u, e1)])


class Cut:
    """The cap of a convex hull (vertices [m], edges as vertex index pairs) beyond a plane normal to
    ``direction`` (the direction it is pressed in, body frame), at depth t below its lowest vertex.

    ``area(t)`` is the cap's cross-section at the plane [m^2], which is |S| of the body against a flat
    face; ``volume(t)`` [m^3] its integral from 0. Between consecutive vertex depths the section's
    corners move linearly with t, so its area is a quadratic and Simpson's rule is exact: each such piece
    is evaluated once, when a depth first reaches it.
    """

    def __init__(self, vertices, edges, direction, label: str = ""):
        v = np.asarray(vertices, dtype=np.float64)
        u = np.asarray(direction, dtype=np.float64)
        u = u / np.linalg.norm(u)
        self.direction = u
        self.label = label
        h = v @ u
        self.depths = h.max() - h
        self.extent = float(self.depths.max())
        self._tol = 1e-12 * float(np.ptp(v, axis=0).max())
        self._xy = v @ _plane_basis(u).T
        edges = np.asarray(edges, dtype=np.int64).reshape(-1, 2)
        self._i, self._j = edges[:, 0], edges[:, 1]
        breaks = [0.0]
        for b in np.sort(self.depths):
            if b > breaks[-1] + self._tol:
                breaks.append(float(b))
        self._breaks = breaks
        # One row per piece: t0, t1, V(t0), and A(t0 + s (t1 - t0)) = c0 + c1 s + c2 s^2.
        self._pieces: list[tuple[float, float, float, float, float, float]] = []

    def area(self, t: float) -> float:
        """Area of the hull's section by the plane t below its lowest vertex [m^2] (by the vertices and
        edge crossings there, in angular order)."""
        d = self.depths
        on = np.abs(d - t) <= self._tol
        di, dj = d[self._i], d[self._j]
        cross = ((di - t) * (dj - t) < 0.0) & ~on[self._i] & ~on[self._j]
        i, j = self._i[cross], self._j[cross]
        w = (t - di[cross]) / (dj[cross] - di[cross])
        pts = np.concatenate([self._xy[on], self._xy[i] + w[:, None] * (self._xy[j] - self._xy[i])])
        if len(pts) < 3:
            return 0.0
        q = pts - pts.mean(axis=0)
        q = q[np.argsort(np.arctan2(q[:, 1], q[:, 0]))]
        return 0.5 * abs(float(np.sum(q[:, 0] * np.roll(q[:, 1], -1) - np.roll(q[:, 0], -1) * q[:, 1])))

    def _piece(self, n: int):
        while len(self._pieces) <= n:
            k = len(self._pieces)
            t0, t1 = self._breaks[k], self._breaks[k + 1]
            v0 = 0.0
            if k:
                p = self._pieces[-1]
                v0 = p[2] + (p[1] - p[0]) * (p[3] + p[4] / 2.0 + p[5] / 3.0)
            a0, am, a1 = self.area(t0), self.area(0.5 * (t0 + t1)), self.area(t1)
            self._pieces.append((t0, t1, v0, a0, -3.0 * a0 + 4.0 * am - a1, 2.0 * a0 - 4.0 * am + 2.0 * a1))
        return self._pieces[n]

    @property
    def num_pieces(self) -> int:
        return len(self._breaks) - 1

    def _at(self, n: int, t: float) -> tuple[float, float]:
        t0, t1, v0, c0, c1, c2 = self._piece(n)
        h = t1 - t0
        s = (t - t0) / h
        return v0 + h * s * (c0 + s * (c1 / 2.0 + s * c2 / 3.0)), c0 + s * (c1 + s * c2)

    def _index(self, t: float) -> int:
        n = int(np.searchsorted(self._breaks, t, side="right")) - 1
        return min(max(n, 0), self.num_pieces - 1)

    def volume(self, t: float) -> float:
        """V(t) [m^3] of the cap t [m] deep (the whole hull beyond its extent)."""
        t = min(max(float(t), 0.0), self.extent)
        return self._at(self._index(t), t)[0]

    def cap(self, t: float) -> tuple[float, float]:
        """(V, |S|) of the cap t [m] deep (|S| = 0 beyond the extent: the body is through)."""
        if t >= self.extent:
            return self.volume(self.extent), 0.0
        t = max(float(t), 0.0)
        return self._at(self._index(t), t)

    def force(self, law: Law, t: float) -> float:
        """W'(V(t)) |S(t)| [N]."""
        v, a = self.cap(t)
        return law.derivative(v) * a

    def depth(self, law: Law, load: float) -> float:
        """The depth t [m] at which ``W'(V) |S| = load`` [N] (the first, going down); 0 where the force at
        first touch already carries it (a face under the linear law), inf where the body would go through."""
        if not load > 0.0:
            return 0.0
        for n in range(self.num_pieces):
            t0, t1 = self._piece(n)[:2]
            if self.force(law, t0) >= load:
                return t0
            # Past the widest section |S| shrinks, and the force may peak inside a piece: the first
            # sample that carries the load and the one before bracket the depth.
            lo = t0
            for hi in t0 + (t1 - t0) * _SAMPLES:
                if self._at_force(law, n, hi) >= load:
                    return self._solve(law, n, load, lo, hi)
                lo = hi
        return math.inf

    def _solve(self, law: Law, n: int, load: float, lo: float, hi: float) -> float:
        """The depth in (lo, hi] where the force of piece n reaches ``load`` (below it at lo, not below at hi).
        Near a feature the force is about a power of the depth, a line in (log t, log F): regula falsi there
        (Illinois, which keeps the bracket) takes a few steps where bisection takes a hundred."""
        if lo <= 0.0:
            lo = hi
            while self._at_force(law, n, lo) >= load:
                hi, lo = lo, lo / 16.0
                if lo < 1e-30 * self.extent:
                    return hi
        ln_load = math.log(load)
        x0, x1 = math.log(lo), math.log(hi)
        y0, y1 = self._ln_excess(law, n, lo, ln_load), self._ln_excess(law, n, hi, ln_load)
        side = 0
        for _ in range(_STEPS):
            if x1 - x0 <= 1e-13:
                break
            x = 0.5 * (x0 + x1)
            if math.isfinite(y0) and y1 > y0:
                x = x1 - y1 * (x1 - x0) / (y1 - y0)
                if not x0 < x < x1:
                    x = 0.5 * (x0 + x1)
            y = self._ln_excess(law, n, math.exp(x), ln_load)
            if y >= 0.0:
                x1, y1 = x, y
                if side == 1:
                    y0 *= 0.5
                side = 1
            else:
                x0, y0 = x, y
                if side == -1:
                    y1 *= 0.5
                side = -1
        return math.exp(x1)

    def _ln_excess(self, law: Law, n: int, t: float, ln_load: float) -> float:
        f = self._at_force(law, n, t)
        return math.log(f) - ln_load if f > 0.0 else -math.inf

    def _at_force(self, law: Law, n: int, t: float) -> float:
        v, a = self._at(n, t)
        return law.derivative(v) * a


def _hull(shape):
    """(vertices, faces, face normals) of a shape's convex hull (a compound grain's: its parts' hull)."""
    if getattr(shape, "is_compound", False):
        from polydem.shapes import ConvexShape

        shape = ConvexShape.from_points(np.asarray(shape.vertices))
    return np.asarray(shape.vertices, dtype=np.float64), list(shape.faces), np.asarray(shape.face_normals)


def shape_cuts(shape, feature: str) -> list[Cut]:
    """One :class:`Cut` per face (pressed along its outward normal), edge (along the sum of its two faces'
    normals) or corner (along the sum of its faces' normals) of a shape (a ConvexShape, or a compound one's
    hull). These directions lie inside the feature's normal cone, so the feature is what touches first; for
    the cube they are the symmetric ones of :func:`cube_cap`."""
    if feature not in FEATURES:
        raise ValueError(f"feature must be one of {', '.join(FEATURES)}, got {feature!r}")
    vertices, faces, normals = _hull(shape)
    owners: dict[tuple[int, int], list[int]] = {}
    for f, loop in enumerate(faces):
        loop = [int(x) for x in loop]
        for a, b in zip(loop, loop[1:] + loop[:1], strict=True):
            owners.setdefault((min(a, b), max(a, b)), []).append(f)
    edges = np.array(sorted(owners), dtype=np.int64)
    if feature == "face":
        return [Cut(vertices, edges, n, f"face {f}") for f, n in enumerate(normals)]
    if feature == "edge":
        return [Cut(vertices, edges, normals[fs].sum(axis=0), f"edge {e}") for e, fs in owners.items()]
    around = np.zeros_like(vertices)
    for f, loop in enumerate(faces):
        around[np.asarray(loop, dtype=np.int64)] += normals[f]
    return [Cut(vertices, edges, around[v], f"corner {v}") for v in range(len(vertices))]


@dataclass(frozen=True)
class Rest:
    """A resting contact (:func:`resting_contact`): ``depth`` [m], overlap ``volume`` [m^3] and ``area``
    |S| [m^2] there, the body-frame ``direction`` it is pressed in, the ``feature`` and its ``label``,
    the toe volume ``vc`` [m^3] and whether the contact is in the toe (V < vc)."""

    depth: float
    volume: float
    area: float
    direction: np.ndarray
    feature: str
    label: str
    vc: float

    @property
    def in_toe(self) -> bool:
        return self.volume < self.vc


def resting_contact(
    shape, law: str, k: float, load: float, feature: str = "corner", *, m: float | None = None, toe: Toe | None = None,
    cuts: list[Cut] | None = None, shallowest: bool = False,
) -> Rest:  # fmt: skip
    """The deepest (``shallowest``: the shallowest) of a shape's faces, edges or corners (``feature``)
    resting on a flat face under ``load`` [N] with the law ``law`` ("linear", "hertz", "power" with ``m``)
    of stiffness ``k``; with ``toe``, the simulator's resolved toe of that pair (module docstring). ``cuts``
    reuses :func:`shape_cuts`."""
    if not (math.isfinite(load) and load >= 0.0):
        raise ValueError(f"load must be a finite force >= 0 [N], got {load!r}")
    w = Law.with_toe(law, k, m, toe, shape)
    best = None
    for cut in shape_cuts(shape, feature) if cuts is None else cuts:
        d = cut.depth(w, load)
        if best is None or (d < best[0] if shallowest else d > best[0]):
            best = (d, cut)
    d, cut = best
    v, a = cut.cap(d) if math.isfinite(d) else (math.inf, 0.0)
    return Rest(d, v, a, cut.direction, feature, cut.label, w.vc)


def resting_depth(
    shape, law: str, k: float, load: float, feature: str = "corner", *, m: float | None = None, toe: Toe | None = None
) -> float:
    """Depth [m] of the deepest ``feature`` ("face", "edge" or "corner") of ``shape`` resting on a flat
    face under ``load`` [N] (see :func:`resting_contact`); inf where it would go through."""
    return resting_contact(shape, law, k, load, feature, m=m, toe=toe).depth


def stiffness_for_depth(
    shape, law: str, depth: float, load: float, feature: str = "corner", *, m: float | None = None, toe=None,
    cuts: list[Cut] | None = None,
) -> float:  # fmt: skip
    """The k (in the law's units) that keeps every ``feature`` of ``shape`` at most ``depth`` [m] deep
    under ``load`` [N].

    ``toe`` None: the law alone, the largest over the features of ``F / (W'_1(V(d)) |S(d)|)``, W'_1 the law
    with k = 1 (the force is proportional to k); for a cube's corner under hertz ``F / (3 (sqrt(3)/2)^1.5
    d^3.5)``. Else a function of k giving the :class:`Toe` of a scene at that k (:func:`auto_dt`: the
    recommended step, and with it the toe, follows k): the toe is softer than the law below V_c, so the k is
    found by bisection above the law's; inf where no k reaches the depth (a given dt above the recommended
    step gives the toe a slope that does not grow with k: lower dt).
    """
    if not (math.isfinite(depth) and depth > 0.0):
        raise ValueError(f"depth must be a positive length [m], got {depth!r}")
    if not (math.isfinite(load) and load > 0.0):
        raise ValueError(f"load must be a positive force [N], got {load!r}")
    cuts = shape_cuts(shape, feature) if cuts is None else cuts
    unit = Law(law, 1.0, m)
    k_law = 0.0
    for cut in cuts:
        if depth >= cut.extent:
            raise ValueError(f"depth {depth:g} m is beyond the shape's extent {cut.extent:g} m along {cut.label}")
        f1 = cut.force(unit, depth)
        if f1 > 0.0:
            k_law = max(k_law, load / f1)
    if toe is None or k_law == 0.0:
        return k_law

    def deepest(k, among):
        w = Law.with_toe(law, k, m, toe(k), shape)
        return max((cut.depth(w, load), i) for i, cut in enumerate(among))

    # Bisect on the cut that is deepest at the k found, over again while another one is deeper there.
    k, cut = k_law, None
    for _ in range(len(cuts)):
        d, i = deepest(k, cuts)
        if d <= depth * (1.0 + 1e-9) or cuts[i] is cut:
            return k
        cut = cuts[i]
        lo, hi = k, k
        while deepest(hi, [cut])[0] > depth:
            lo, hi = hi, 4.0 * hi
            if hi > 1e30 * k_law:
                return math.inf
        while hi > lo * (1.0 + 1e-9):
            mid = math.sqrt(lo * hi)
            if deepest(mid, [cut])[0] > depth:
                lo = mid
            else:
                hi = mid
        k = hi
    return k


def auto_dt(ts, law: str, m: float | None, scale: float) -> float:
    """The step [s] that dt = "auto" takes when every k of a scene is ``scale`` times what it is, from the
    scene's :class:`~polydem.scene.checks.TimeStep` ``ts``: 1/STEPS_PER_CONTACT_PERIOD of the reference
    contact's period, which goes as k^(-1/2) (with the derived tangential spring), or the resting rule's
    step (``ts.resting``), which goes as 1/k under hertz and k^(-1/(2(m-1))) under a power law."""
    from polydem.scene.checks import STEPS_PER_CONTACT_PERIOD

    dt = ts.period / STEPS_PER_CONTACT_PERIOD / math.sqrt(scale)
    mm = _exponent(law, m)
    if math.isfinite(ts.resting) and mm > 1.0:
        dt = min(dt, ts.resting * scale ** (-1.0 / (2.0 * (mm - 1.0))))
    return dt


@dataclass(frozen=True)
class PileDepth:
    """Expected resting depths of one free (shape, material) of a scene (:func:`pile_depths`).

    ``shape``, ``material``: names; ``size``: V^(1/3) [m]; ``k``: the softest pair it meets; ``weight``:
    its own [N]; ``column``: grains in a column ``height`` [m] tall (at least 1; see :func:`pile_depths`);
    ``depth_weight`` and ``depth_column``: feature -> :class:`Rest` under one weight and under the
    column's; ``allowed``: a corner depth as a share of the size, and the k that keeps every corner at most
    that deep under the column: ``k_corner`` with the toe of the scene's step (inf where its dt is given and
    too long), ``k_corner_law`` by the law alone; ``partner``: what the toe's pair mass takes the
    grain to rest on ("a like grain", or "a wall" for a lone body); ``shallowest_face``: the
    :class:`Rest` of its shallowest face (its largest, as a rule) under its own weight.
    """

    shape: str
    material: str
    size: float
    k: float
    weight: float
    column: float
    height: float
    depth_weight: dict
    depth_column: dict
    allowed: float
    k_corner: float
    k_corner_law: float
    partner: str
    shallowest_face: Rest


BED_PACKING = 0.6
"""Solid fraction of the settled bed whose depth :func:`pile_depths` takes for the column (when less than
the free bodies' vertical extent)."""

ALLOWED_CORNER_DEPTH = 0.01
"""The corner depth, as a share of a grain's size, for which :func:`pile_depths` names a k."""


def pile_depths(scene, ts=None, allowed: float = ALLOWED_CORNER_DEPTH) -> list[PileDepth]:
    """Resting depths to expect in a scene's pile, per free (shape, material): the deepest face, edge and
    corner under the weight of one grain and of a column of grains as tall as the free bodies' vertical
    extent (their span along gravity plus a bounding diameter) or, where less, the bed they settle into
    (their volume at a solid fraction of BED_PACKING over their horizontal span), against the softest pair
    the grain can meet, with the toe of a pair of two such grains (of the grain and a wall where it is the
    only free body) of the scene's step, at least the recommended one (``ts``, its
    :class:`~polydem.scene.checks.TimeStep`; None: no toe); and the k for a corner ``allowed`` of the size deep
    under the column (the recommended step, and with it the toe, follows k: :func:`auto_dt`). Empty without
    gravity or free bodies."""
    a = scene.body_arrays()
    free = a["kind"] == BodyKind.FREE
    g = float(np.linalg.norm(scene.gravity))
    if not free.any() or g <= 0.0:
        return []
    up = -np.asarray(scene.gravity, dtype=np.float64) / g
    shapes = list(scene.shapes.values())
    names = scene.shape_names
    mats = list(scene.materials.values())
    radius = np.array([s.radius for s in shapes])[a["shape"][free]]
    pos = a["position"][free]
    span = np.ptp(pos @ np.vstack([up, _plane_basis(up)]).T, axis=0) + 2.0 * radius.max()
    # A pour starts spread out and settles into a bed: at most as deep as its solids packed at BED_PACKING
    # over the footprint.
    solid = float(np.sum(np.array([s.volume for s in shapes])[a["shape"][free]]))
    height = float(min(span[0], solid / (BED_PACKING * span[1] * span[2])))
    table = scene.pair_table()
    law, m = table["law"], float(table["exponent"])
    m_law = m if LAW_SPECS[law].fixed_exponent is None else None
    k_pair = np.asarray(table["k"], dtype=np.float64)
    e_pair = np.asarray(table["restitution"], dtype=np.float64)
    present = set(np.unique(a["material"]).tolist())
    present.update(scene.material_index(p.material) for p in [*scene.planes, *scene.mesh_walls])
    present = np.array(sorted(present))
    # A grain of a pile rests on others like it; a lone one on a wall or a fixed body (the toe's pair mass).
    pair_bodies = 2.0 if np.count_nonzero(free) > 1 else 1.0
    partner = "a like grain" if pair_bodies == 2.0 else "a wall"
    rows = []
    combo = np.unique(a["shape"][free].astype(np.int64) * len(mats) + a["material"][free])
    for c in combo.tolist():
        si, mi = c // len(mats), c % len(mats)
        shape, mat = shapes[si], mats[mi]
        j = int(present[np.argmin(k_pair[mi, present])])
        k, e = float(k_pair[mi, j]), float(e_pair[mi, j])
        mass = mat.density * shape.volume
        size = shape.volume ** (1.0 / 3.0)
        weight = mass * g
        column = max(1.0, height / size)
        cuts = {f: shape_cuts(shape, f) for f in FEATURES}
        toe = None
        if ts is not None:
            from polydem.scene.checks import toe_step

            toe = Toe(e, ts.toe_dt, pair_bodies / mass, shape.radius, largest_face_area(shape))

            def toe_at(kk, e=e, mass=mass, shape=shape, k0=k):
                # The recommended step follows k; a given dt does not (dt = "auto": the recommended step).
                rec = auto_dt(ts, law, m_law, kk / k0)
                dt = toe_step(rec if scene.dt == "auto" else ts.dt, rec)
                return Toe(e, dt, pair_bodies / mass, shape.radius, largest_face_area(shape))

        under = [
            {f: resting_contact(shape, law, k, load, f, m=m_law, toe=toe, cuts=cuts[f]) for f in FEATURES}
            for load in (weight, column * weight)
        ]
        shallow = resting_contact(shape, law, k, weight, "face", m=m_law, toe=toe, cuts=cuts["face"], shallowest=True)
        corner = (shape, law, allowed * size, column * weight, "corner")
        k_law = stiffness_for_depth(*corner, m=m_law, cuts=cuts["corner"])
        k_toe = k_law if toe is None else stiffness_for_depth(*corner, m=m_law, toe=toe_at, cuts=cuts["corner"])
        rows.append(
            PileDepth(
                names[si],
                mat.name,
                size,
                k,
                weight,
                column,
                height,
                under[0],
                under[1],
                allowed,
                k_toe,
                k_law,
                partner,
                shallow,
            )  # fmt: skip
        )
    return rows
