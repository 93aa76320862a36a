"""Measures of granular packings (issue 26): exact local packing fraction and its profiles, contact
types and coordination number without rattlers, fabric tensor, Love-Weber stress and its profiles,
the distribution of contact forces and of contact normal orientations.

Every measure works on a :class:`polydem.Simulation` (its current state, its scene's shapes and
walls, and :meth:`~polydem.Simulation.contacts`) or on plain arrays: a :class:`Grains` built from
shapes, shape indices and body-frame poses, and a contacts dict with the keys of
``Simulation.contacts()`` (``contact_average()`` also serves the force-based measures). Host-side
numpy and scipy, in float64; nothing here steps or changes a simulation.

Packing fraction. The volume of each grain inside an axis-aligned :class:`Box` is exact: the
grain's surface is clipped by the box's planes (Sutherland-Hodgman on every face loop, the cut
closed on each plane), and the volume follows from the divergence theorem,
``V = 1/3 sum_f d_f A_f`` over the faces of the clipped solid. Grains are never counted by their
centres. A compound grain (:class:`polydem.CompoundShape`) is clipped part by part; where its parts
overlap each other, their common pieces (convex: the intersection of the parts' half-spaces) are
clipped too and subtracted and added back by inclusion-exclusion, so the union is counted once, as
its mass properties are.

Contact types. A contact's overlap has one flat side where one body presents a face (the other
body's edge, corner or face dips into it), and its shape tells the feature that dips in: with V the
overlap volume, S = |S_A| the area of that flat side (the area vector of the overlap's surface on
A, :func:`polydem.overlap`) and d the penetration depth, a face (a slab) gives V = S d, a straight
edge (a wedge) V = S d / 2, a corner (a pyramid) V = S d / 3, whatever the angles. The ratio
``r = V / (S d)`` is therefore 1, 1/2 or 1/3, and a feature tilted between two of these gives a
value between them. The thresholds lie half-way: :data:`FACE_RATIO` = 3/4 (a whole face tilted, its
sides sunk by d and d_s, gives r = (1 + d_s/d) / 2: it counts as a face while d_s >= d/2),
:data:`VERTEX_RATIO` = 5/12 (a whole edge tilted gives r = (d^2 + d d_s + d_s^2) / (3 d (d + d_s)):
an edge while d_s >= 0.64 d; a corner gives 1/3 until the cut reaches the next vertex). Where two
edges cross, the overlap is a pyramid as well (two cube edges crossing square: V = 2/3 d^3, S = 2
d^2, r = 1/3), but neither body presents a face: the normal S_A/|S_A| lies along the cross product of
the edges, 45 degrees from every face normal of both cubes. A contact whose normal is more than
:data:`ALIGN_ANGLE` (10 degrees) from the nearest face normal of either body is "edge-edge", whatever
its ratio. A rounded grain (``ConvexShape.sphere``) pressed deeper than its facets are wide makes a
paraboloid cap, r = 1/2: "edge-face". The geometry is that of the current poses, in float64
(:func:`polydem.overlap` for pairs, the exact clipping for walls), where ``Simulation.contacts()``
reports the poses one step earlier: a contact that opened in the last step is left unclassified.
The overlap's shape is what the contact law acts on, at the depth the stiffness sets: faces
misaligned by more than about d / L touch by a corner, and in a settled pour of cubes nearly every
contact is then vertex-face. ``classify_contacts`` therefore classifies by default by what each body
presents within :data:`ALIGN_ANGLE` of the contact normal, whatever the stiffness (``method="features"``),
and by the overlap's shape on request (``method="overlap"``).

Stress. ``sigma = 1/V sum_c f_c (x) l_c`` (Love-Weber), compressive stress positive: f_c the force
that A exerts on B [N], l_c = x_B - x_A the branch vector between the centres [m], or for a wall
contact from the grain's centre to the contact point (B is the wall). Each contact counts by the
fraction of its branch vector inside the box, which makes it the contact part of the
coarse-grained stress with a box window (Goldhirsch 2010; Weinhart et al. 2012): no contact is
counted half by the choice of a bin edge, and in a bin that holds whole branch vectors it is the
classical sum. The kinetic part (velocity fluctuations) is left out: these are measures of packings
at rest.
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass, field, replace

import numpy as np

from polydem.compound import convex_parts, is_compound
from polydem.quaternions import quat_to_matrix
from polydem.scene.bodies import BodyKind

__all__ = [
    "ALIGN_ANGLE",
    "FACE_RATIO",
    "KINDS",
    "MIN_CONTACTS",
    "VERTEX_RATIO",
    "Box",
    "ContactTypes",
    "Coordination",
    "ForceDistribution",
    "Grains",
    "OrientationDistribution",
    "PackingProfile",
    "Rose",
    "StressProfile",
    "classify",
    "classify_contacts",
    "classify_features",
    "clipped_volumes",
    "coordination",
    "cubic_frame",
    "cubic_order",
    "fabric",
    "force_distribution",
    "normal_orientations",
    "normal_rose",
    "packing_fraction",
    "packing_profile",
    "settled_box",
    "stress",
    "stress_profile",
    "summary",
]

KINDS = ("face-face", "edge-face", "vertex-face", "edge-edge")
"""Contact types, in the order of :attr:`ContactTypes.kind` (-1: not classified)."""

FACE_RATIO = 0.75
"""``V / (S d)`` at or above which a contact is face-face (1 for a slab, 1/2 for a wedge)."""

VERTEX_RATIO = 5.0 / 12.0
"""``V / (S d)`` below which a contact is vertex-face (1/3 for a pyramid, 1/2 for a wedge)."""

ALIGN_ANGLE = 10.0
"""Largest angle [degrees] between the contact normal and a face normal of either body for a
contact to have a face; beyond it on both bodies, the contact is edge-edge."""

MIN_CONTACTS = 4
"""A grain with fewer contacts than this is a rattler (3 would be the isostatic count of frictional spheres)."""

# Segments per block of the clipping: ~100 bytes each with the temporaries, so some 50 MB a block.
_BLOCK_SEGMENTS = 1 << 19
_AXES = {"x": 0, "y": 1, "z": 2}


# ---------------------------------------------------------------------------------------------- inputs


def _axis(axis) -> int:
    if isinstance(axis, str) and axis.lower() in _AXES:
        return _AXES[axis.lower()]
    if isinstance(axis, int | np.integer) and not isinstance(axis, bool) and 0 <= int(axis) <= 2:
        return int(axis)
    raise ValueError(f"axis must be 0, 1, 2 or 'x', 'y', 'z', got {axis!r}")


def _positive(name: str, value) -> float:
    try:
        v = float(value)
    except (TypeError, ValueError):
        raise ValueError(f"{name} must be a number, got {value!r}") from None
    if isinstance(value, bool) or not math.isfinite(v) or v <= 0.0:
        raise ValueError(f"{name} must be a finite number > 0, got {value!r}")
    return v


def _rows(name: str, values, width: int, n: int | None = None) -> np.ndarray:
    a = np.asarray(values, dtype=np.float64)
    if a.ndim != 2 or a.shape[1] != width or (n is not None and len(a) != n):
        want = f"({n if n is not None else 'N'}, {width})"
        raise ValueError(f"{name} must have shape {want}, got {a.shape}")
    if not np.isfinite(a).all():
        raise ValueError(f"{name} must be finite")
    return a


@dataclass
class Grains:
    """Grains as plain arrays: what the packing measures read from a simulation.

    Attributes:
        shapes: S shapes (:class:`polydem.ConvexShape` or :class:`polydem.CompoundShape`).
        body_shape: (N,) int index into ``shapes`` of each body.
        position: (N, 3) centre of mass of each body [m] (the body frame's origin, as
            ``Simulation.state()["body_position"]``).
        orientation: (N, 4) unit quaternion xyzw from the body frame (principal axes) to the world.
        counted: (N,) bool, the bodies that are grains of the packing (those the packing fraction
            sums and the coordination number averages); default all.
        free: (N,) bool, the bodies that can be rattlers (the free ones); default all.
        plane_normal: (P, 3) unit normals of the plane walls, into the simulated side.
        plane_offset: (P,) ``normal . point`` of each plane [m]: a wall fills ``normal . x <= offset``.
    """

    shapes: list
    body_shape: np.ndarray
    position: np.ndarray
    orientation: np.ndarray
    counted: np.ndarray | None = None
    free: np.ndarray | None = None
    plane_normal: np.ndarray = field(default_factory=lambda: np.zeros((0, 3)))
    plane_offset: np.ndarray = field(default_factory=lambda: np.zeros(0))

    def __post_init__(self):
        self.shapes = list(self.shapes)
        self.body_shape = np.asarray(self.body_shape, dtype=np.int64).reshape(-1)
        n = len(self.body_shape)
        if n and (self.body_shape.min() < 0 or self.body_shape.max() >= len(self.shapes)):
            raise ValueError(f"body_shape must index the {len(self.shapes)} shapes, got {self.body_shape.max()}")
        self.position = _rows("position", self.position, 3, n)
        q = _rows("orientation", self.orientation, 4, n)
        norm = np.linalg.norm(q, axis=1)
        if n and (norm < 0.5).any():
            raise ValueError("orientation must hold unit quaternions xyzw")
        self.orientation = q / norm[:, None]
        for name in ("counted", "free"):
            mask = getattr(self, name)
            mask = np.ones(n, dtype=bool) if mask is None else _mask(name, mask, n)
            setattr(self, name, mask)
        self.plane_normal = _rows("plane_normal", self.plane_normal, 3)
        self.plane_offset = np.asarray(self.plane_offset, dtype=np.float64).reshape(-1)
        if len(self.plane_offset) != len(self.plane_normal):
            raise ValueError("plane_normal and plane_offset must have one row per plane")

    @classmethod
    def from_scene(cls, scene, state=None, bodies=None) -> Grains:
        """The grains of ``scene`` at ``state`` (a dict as ``Simulation.state()``; default the
        scene's initial poses). ``bodies``: which bodies count, an (N,) bool mask or indices
        (default the free ones)."""
        shapes = [scene.shapes[name] for name in scene.shape_names]
        if state is None:
            position, orientation = scene.body_position, scene.body_orientation
        else:
            position, orientation = state["body_position"], state["body_orientation"]
        free = np.asarray(scene.body_kind) == BodyKind.FREE
        counted = free if bodies is None else _mask("bodies", bodies, scene.num_bodies)
        planes = scene.planes
        normal = np.array([p.normal for p in planes], dtype=np.float64).reshape(-1, 3)
        offset = np.array([np.dot(p.normal, p.point) for p in planes], dtype=np.float64)
        return cls(shapes, scene.body_shape, position, orientation, counted, free, normal, offset)

    @classmethod
    def from_simulation(cls, sim, bodies=None) -> Grains:
        """The grains of a :class:`polydem.Simulation` at its current state (see :meth:`from_scene`)."""
        return cls.from_scene(sim.scene, sim.state(), bodies)

    @property
    def num_bodies(self) -> int:
        return len(self.body_shape)

    def volumes(self) -> np.ndarray:
        """(N,) volume of each body [m^3]."""
        return np.array([s.volume for s in self.shapes], dtype=np.float64)[self.body_shape]

    def radii(self) -> np.ndarray:
        """(N,) bounding radius of each body about its centre [m]."""
        return np.array([s.radius for s in self.shapes], dtype=np.float64)[self.body_shape]

    def grain_size(self) -> float:
        """Mean volume-equivalent diameter ``(6 V / pi)^(1/3)`` of the counted grains [m]."""
        v = self.volumes()[self.counted]
        if not len(v):
            raise ValueError("no grain is counted")
        return float(np.mean(np.cbrt(6.0 * v / math.pi)))


def _mask(name, mask, n) -> np.ndarray:
    m = np.asarray(mask)
    if m.dtype == bool:
        if m.shape != (n,):
            raise ValueError(f"{name} must be an ({n},) bool mask or body indices, got shape {m.shape}")
        return m.copy()
    out = np.zeros(n, dtype=bool)
    idx = m.astype(np.int64).reshape(-1)
    if len(idx) and (idx.min() < 0 or idx.max() >= n):
        raise ValueError(f"{name} holds body indices outside 0..{n - 1}")
    out[idx] = True
    return out


def _grains(source) -> Grains:
    if isinstance(source, Grains):
        return source
    if hasattr(source, "model") and hasattr(source, "state"):
        return Grains.from_simulation(source)
    raise TypeError(f"expected a polydem.Simulation or a polydem.measures.Grains, got {type(source).__name__}")


def _contacts(source, contacts) -> dict:
    if contacts is not None:
        return contacts
    if hasattr(source, "contacts"):
        return source.contacts()
    raise ValueError("give the contacts (a dict as Simulation.contacts() returns) with Grains or arrays")


def _positions(source) -> np.ndarray:
    if isinstance(source, Grains):
        return source.position
    if hasattr(source, "state"):
        return np.asarray(source.state()["body_position"], dtype=np.float64)
    return _rows("positions", source, 3)


@dataclass(frozen=True)
class Box:
    """An axis-aligned box, the region a measure is taken over.

    Attributes:
        lower, upper: (3,) corners [m], ``lower < upper`` on every axis.
    """

    lower: np.ndarray
    upper: np.ndarray

    def __post_init__(self):
        lo = np.asarray(self.lower, dtype=np.float64).reshape(-1)
        hi = np.asarray(self.upper, dtype=np.float64).reshape(-1)
        if lo.shape != (3,) or hi.shape != (3,) or not (np.isfinite(lo).all() and np.isfinite(hi).all()):
            raise ValueError(f"a box needs finite (3,) lower and upper corners, got {self.lower!r}, {self.upper!r}")
        if not np.all(hi > lo):
            raise ValueError(f"a box needs lower < upper on every axis, got lower {lo.tolist()}, upper {hi.tolist()}")
        object.__setattr__(self, "lower", lo)
        object.__setattr__(self, "upper", hi)

    @property
    def volume(self) -> float:
        """[m^3]"""
        return float(np.prod(self.upper - self.lower))

    def shrunk(self, distance, axes=(0, 1, 2)) -> Box:
        """The box moved in by ``distance`` [m] on both sides along each of ``axes`` (away from walls).

        Raises:
            ValueError: nothing would be left.
        """
        d = float(distance)
        lo, hi = self.lower.copy(), self.upper.copy()
        for a in axes:
            k = _axis(a)
            lo[k] += d
            hi[k] -= d
        if not np.all(hi > lo):
            raise ValueError(f"the box {self.lower.tolist()}..{self.upper.tolist()} shrunk by {d:g} m is empty")
        return Box(lo, hi)

    def contains(self, points) -> np.ndarray:
        """(M,) bool, which of (M, 3) points [m] lie in the box (faces included)."""
        p = np.asarray(points, dtype=np.float64).reshape(-1, 3)
        return np.all((p >= self.lower) & (p <= self.upper), axis=1)

    @classmethod
    def around(cls, source) -> Box:
        """The smallest box holding every vertex of the counted grains."""
        g = _grains(source)
        lo, hi = np.full(3, np.inf), np.full(3, -np.inf)
        rot = quat_to_matrix(g.orientation)
        for s, shape in enumerate(g.shapes):
            rows = np.flatnonzero(g.counted & (g.body_shape == s))
            if not len(rows):
                continue
            verts = np.concatenate([p.vertices @ r.T + t for p, r, t in convex_parts(shape)])
            step = max(1, (1 << 20) // len(verts))
            for blk in range(0, len(rows), step):
                pick = rows[blk : blk + step]
                x = np.einsum("gij,vj->gvi", rot[pick], verts) + g.position[pick, None, :]
                lo = np.minimum(lo, x.min(axis=(0, 1)))
                hi = np.maximum(hi, x.max(axis=(0, 1)))
        if not np.all(hi > lo):
            raise ValueError("no counted grain to put a box around")
        return cls(lo, hi)

    def to_dict(self) -> dict:
        return {"lower": self.lower.tolist(), "upper": self.upper.tolist()}


# ---------------------------------------------------------------------------------- exact clipping


@dataclass
class _Piece:
    """A convex piece of a shape in the grain's body frame, as directed boundary segments."""

    vertices: np.ndarray  # (nv, 3) [m]
    seg0: np.ndarray  # (E,) start vertex of each segment
    seg1: np.ndarray  # (E,) end vertex
    seg_face: np.ndarray  # (E,) face of each segment
    normals: np.ndarray  # (F, 3) outward unit normals
    offsets: np.ndarray  # (F,) n . x on the face [m]
    sign: float  # +1, or -1 for a common piece that inclusion-exclusion subtracts
    volume: float  # [m^3]


def _piece(part, rot, trans, sign) -> _Piece:
    verts = part.vertices @ rot.T + trans
    normals = part.face_normals @ rot.T
    offsets = part.face_offsets + normals @ trans
    seg0 = np.concatenate([np.asarray(f, dtype=np.int64) for f in part.faces])
    seg1 = np.concatenate([np.roll(np.asarray(f, dtype=np.int64), -1) for f in part.faces])
    face = np.concatenate([np.full(len(f), k, dtype=np.int64) for k, f in enumerate(part.faces)])
    return _Piece(verts, seg0, seg1, face, normals, offsets, float(sign), float(part.volume))


def _pieces(shape) -> list[_Piece]:
    """The convex pieces whose signed volumes add up to the shape: the shape itself, a compound's
    parts, and where the parts overlap, their common pieces by inclusion-exclusion."""
    parts = convex_parts(shape)
    pieces = [_piece(p, r, t, 1.0) for p, r, t in parts]
    if not (is_compound(shape) and getattr(shape, "overlapping", False)):
        return pieces
    from scipy.optimize import linprog
    from scipy.spatial import HalfspaceIntersection

    from polydem.shapes import ConvexShape

    spaces = [np.column_stack([pc.normals, -pc.offsets]) for pc in pieces]
    centres = [t for _, _, t in parts]
    radii = [p.radius for p, _, _ in parts]
    size = float(shape.radius)

    def meet(members, space, sign):
        for j in range(members[-1] + 1, len(parts)):
            if any(np.linalg.norm(centres[j] - centres[i]) >= radii[i] + radii[j] for i in members):
                continue
            both = np.vstack([space, spaces[j]])
            # The point deepest inside all the half-spaces: an interior point for qhull, or none.
            a_ub = np.hstack([both[:, :3], np.ones((len(both), 1))])
            res = linprog([0.0, 0.0, 0.0, -1.0], A_ub=a_ub, b_ub=-both[:, 3],
                          bounds=[(None, None)] * 3 + [(None, size)], method="highs")  # fmt: skip
            if res.status != 0 or -res.fun <= 1e-9 * size:
                continue
            corners = HalfspaceIntersection(both, res.x[:3]).intersections
            try:
                common = ConvexShape.from_points(corners)
            except ValueError:  # a sliver flatter than the hull builder accepts: no volume to speak of
                continue
            pieces.append(_piece(common, common.input_rotation, common.input_translation, -sign))
            meet(members + [j], both, -sign)

    for i in range(len(parts)):
        meet([i], spaces[i], 1.0)
    return pieces


class _Templates:
    """The pieces of every shape, built once per call."""

    def __init__(self, shapes):
        self.pieces = [_pieces(s) for s in shapes]


@dataclass
class _Segments:
    """Directed boundary segments of the surfaces of items (a piece of a grain, or a piece of a grain
    below a bin edge), in coordinates centred on each item's grain."""

    item: np.ndarray  # (S,) int64
    face: np.ndarray  # (S,) int64, unique per face of an item
    p0: np.ndarray  # (S, 3) [m]
    p1: np.ndarray  # (S, 3) [m]
    n: np.ndarray  # (S, 3) outward unit normal of the segment's face
    d: np.ndarray  # (S,) n . x on the face [m]

    @staticmethod
    def join(parts) -> _Segments:
        names = ("item", "face", "p0", "p1", "n", "d")
        return _Segments(*(np.concatenate([getattr(p, k) for p in parts]) for k in names))

    def take(self, idx) -> _Segments:
        return _Segments(self.item[idx], self.face[idx], self.p0[idx], self.p1[idx], self.n[idx], self.d[idx])


def _dot(p, m) -> np.ndarray:
    # Elementwise, not einsum: a point shared by two segments must get the same value bit for bit.
    return p[:, 0] * m[:, 0] + p[:, 1] * m[:, 1] + p[:, 2] * m[:, 2]


def _clip(seg: _Segments, normal, offset, next_face: int) -> tuple[_Segments, int]:
    """Keep, of every item's closed surface, the part where ``normal . x <= offset``, and close it.

    ``normal``: (I, 3) unit normals, ``offset``: (I,) [m], per item, in its centred coordinates.
    Each face loop keeps its inside part and gets a closing segment along the plane, from where it
    leaves the half-space to where it comes back; the cap on the plane (a new face per item, ids
    from ``next_face``) gets those segments reversed. Returns the segments and the next free face id.

    Why it is exact and robust: a crossing point is computed from the inside end of its edge, so the
    two faces that share the edge compute it bit for bit alike, and every surface stays closed. Within
    a face, the closing segments all lie on one line (the face's plane meets the clipping plane), so
    sum(p0 x p1) over them depends only on their end points, not on how a face's exits and entries
    are paired: a face that rounding cuts into several pieces (one lying in the plane) is still
    counted right.
    """
    m = normal[seg.item]
    e = offset[seg.item]
    s0 = _dot(seg.p0, m) - e
    s1 = _dot(seg.p1, m) - e
    in0, in1 = s0 <= 0.0, s1 <= 0.0
    leave = in0 & ~in1
    enter = ~in0 & in1
    cross = np.flatnonzero(leave | enter)
    first_in = in0[cross]
    p_in = np.where(first_in[:, None], seg.p0[cross], seg.p1[cross])
    p_out = np.where(first_in[:, None], seg.p1[cross], seg.p0[cross])
    s_in = np.where(first_in, s0[cross], s1[cross])
    s_out = np.where(first_in, s1[cross], s0[cross])
    q = p_in + (p_out - p_in) * (s_in / (s_in - s_out))[:, None]
    p0, p1 = seg.p0.copy(), seg.p1.copy()
    p0[cross[~first_in]] = q[~first_in]
    p1[cross[first_in]] = q[first_in]
    out_idx, in_idx = cross[first_in], cross[~first_in]
    q_out, q_in = q[first_in], q[~first_in]
    order_out = np.argsort(seg.face[out_idx], kind="stable")
    order_in = np.argsort(seg.face[in_idx], kind="stable")
    if not np.array_equal(seg.face[out_idx][order_out], seg.face[in_idx][order_in]):
        raise RuntimeError("clipping: a face loop is not closed (a bug: please report it)")
    src = out_idx[order_out]
    q_out, q_in = q_out[order_out], q_in[order_in]
    item = seg.item[src]
    keep = np.flatnonzero(in0 | in1)
    closing = _Segments(item, seg.face[src], q_out, q_in, seg.n[src], seg.d[src])
    cap = _Segments(item, next_face + item, q_in.copy(), q_out.copy(), normal[item], offset[item])
    kept = _Segments(seg.item[keep], seg.face[keep], p0[keep], p1[keep], seg.n[keep], seg.d[keep])
    return _Segments.join([kept, closing, cap]), next_face + len(normal)


def _volumes(seg: _Segments, items: int) -> np.ndarray:
    """(items,) volume enclosed by each item's segments [m^3]: 1/6 sum d n . (p0 x p1)."""
    w = seg.d * _dot(np.cross(seg.p0, seg.p1), seg.n) / 6.0
    return np.bincount(seg.item, weights=w, minlength=items)


def _build(grains: Grains, templates: _Templates, bodies) -> tuple[_Segments, np.ndarray, np.ndarray, int]:
    """The segments of every piece of ``bodies`` (indices, repeats allowed), one item per (entry of
    ``bodies``, piece), centred on the body.

    Returns (segments, item source (I,) index into ``bodies``, item sign (I,), next free face id)."""
    bodies = np.asarray(bodies, dtype=np.int64)
    rot = quat_to_matrix(grains.orientation[bodies])
    shape = grains.body_shape[bodies]
    parts, item_src, item_sign = [], [], []
    items = faces = 0
    for s in np.unique(shape).tolist():
        rows = np.flatnonzero(shape == s)
        r = rot[rows]
        for pc in templates.pieces[s]:
            g, nseg, nface = len(rows), len(pc.seg0), len(pc.normals)
            x = np.einsum("gij,vj->gvi", r, pc.vertices)
            nrm = np.einsum("gij,fj->gfi", r, pc.normals)
            item = items + np.repeat(np.arange(g), nseg)
            face = faces + (np.arange(g)[:, None] * nface + pc.seg_face[None, :]).reshape(-1)
            parts.append(
                _Segments(
                    item,
                    face,
                    x[:, pc.seg0].reshape(-1, 3),
                    x[:, pc.seg1].reshape(-1, 3),
                    nrm[:, pc.seg_face].reshape(-1, 3),
                    np.tile(pc.offsets[pc.seg_face], g),
                )
            )
            item_src.append(rows)
            item_sign.append(np.full(g, pc.sign))
            items += g
            faces += g * nface
    if not parts:
        empty = np.zeros((0, 3))
        z = np.zeros(0, dtype=np.int64)
        return _Segments(z, z, empty, empty, empty, np.zeros(0)), z, np.zeros(0), 0
    return _Segments.join(parts), np.concatenate(item_src), np.concatenate(item_sign), faces


def _segments_per_body(grains: Grains, templates: _Templates) -> np.ndarray:
    per_shape = np.array([sum(len(pc.seg0) for pc in pieces) for pieces in templates.pieces], dtype=np.int64)
    return per_shape[grains.body_shape]


def _blocks(bodies, cost, budget=_BLOCK_SEGMENTS):
    """Consecutive runs of ``bodies`` whose summed ``cost`` stays within ``budget`` (at least one body)."""
    start, total = 0, 0
    for k, c in enumerate(cost.tolist()):
        if total and total + c > budget:
            yield bodies[start:k]
            start, total = k, 0
        total += c
    if start < len(bodies):
        yield bodies[start:]


def _box_planes(box: Box, centre: np.ndarray):
    """The six planes of ``box`` as (normal (3,), offsets (I,)) relative to each item's centre."""
    for k in range(3):
        axis = np.eye(3)[k]
        yield axis, box.upper[k] - centre[:, k]
        yield -axis, centre[:, k] - box.lower[k]


def _clip_to_box(seg, item_centre, box, next_face):
    for normal, offset in _box_planes(box, item_centre):
        seg, next_face = _clip(seg, np.broadcast_to(normal, (len(offset), 3)), offset, next_face)
    return seg, next_face


def _cut_by_box(grains: Grains, box: Box):
    """Split the counted grains by ``box``: (inside (M,) bodies wholly inside, cut (K,) bodies the box's
    surface may cut), by their bounding spheres."""
    idx = np.flatnonzero(grains.counted)
    c = grains.position[idx]
    r = grains.radii()[idx]
    inside = np.all((c - r[:, None] >= box.lower) & (c + r[:, None] <= box.upper), axis=1)
    gap = np.maximum(box.lower - c, 0.0) + np.maximum(c - box.upper, 0.0)
    near = np.einsum("ij,ij->i", gap, gap) < r * r
    return idx[inside], idx[near & ~inside]


def clipped_volumes(source, box: Box) -> np.ndarray:
    """(N,) volume of each grain inside ``box`` [m^3], exact (zero for bodies not counted).

    ``source``: a :class:`polydem.Simulation` (its free bodies at the current state) or :class:`Grains`.
    """
    g = _grains(source)
    out = np.zeros(g.num_bodies)
    inside, cut = _cut_by_box(g, box)
    out[inside] = g.volumes()[inside]
    if not len(cut):
        return out
    templates = _Templates(g.shapes)
    for bodies in _blocks(cut, _segments_per_body(g, templates)[cut]):
        seg, src, sign, next_face = _build(g, templates, bodies)
        item_body = bodies[src]
        seg, _ = _clip_to_box(seg, g.position[item_body], box, next_face)
        np.add.at(out, item_body, sign * _volumes(seg, len(item_body)))
    # Rounding can leave -1e-22 m^3 for a grain that only touches the box.
    return np.maximum(out, 0.0)


def packing_fraction(source, box: Box | None = None, *, margin: float = 0.0) -> float:
    """Solid fraction of ``box``: the counted grains' volume inside it, exactly, over its volume [-].

    Args:
        source: a :class:`polydem.Simulation` or :class:`Grains`.
        box: the region; default the box around the counted grains (:meth:`Box.around`).
        margin: move the box's faces in by this many grain sizes (:meth:`Grains.grain_size`), away
            from walls and the free surface.
    """
    g = _grains(source)
    box = Box.around(g) if box is None else box
    if margin:
        box = box.shrunk(float(margin) * g.grain_size())
    return float(clipped_volumes(g, box).sum() / box.volume)


@dataclass
class PackingProfile:
    """Packing fraction in slabs along one axis.

    Attributes:
        axis: 0, 1 or 2.
        edges: (K+1,) slab boundaries along the axis [m]; the last slab may be thinner than the others.
        centres: (K,) slab middles [m].
        fraction: (K,) solid fraction of each slab [-].
        solid_volume: (K,) grain volume in each slab [m^3].
        slab_volume: (K,) volume of each slab [m^3].
        box: the region the slabs divide.
    """

    axis: int
    edges: np.ndarray
    centres: np.ndarray
    fraction: np.ndarray
    solid_volume: np.ndarray
    slab_volume: np.ndarray
    box: Box

    def to_dict(self) -> dict:
        d = {k: (v.tolist() if isinstance(v, np.ndarray) else v) for k, v in asdict(self).items() if k != "box"}
        d["box"] = self.box.to_dict()
        return d


def _edges(lo: float, hi: float, width: float) -> np.ndarray:
    n = max(1, int(math.ceil((hi - lo) / width - 1e-9)))
    edges = lo + width * np.arange(n + 1)
    edges[-1] = hi
    return edges


def _ranges(starts, counts) -> np.ndarray:
    """Concatenated ``arange(s, s + c)`` over pairs, vectorised."""
    total = int(counts.sum())
    offsets = np.repeat(np.cumsum(counts) - counts, counts)
    return np.repeat(starts, counts) + np.arange(total) - offsets


def packing_profile(
    source, axis=2, bin_width: float | None = None, box: Box | None = None, *, margin: float = 0.0
) -> PackingProfile:
    """Exact packing fraction in slabs ``bin_width`` thick along ``axis``, across ``box``.

    Each grain's volume is split between the slabs exactly (its part below each slab boundary is
    clipped off), so the slabs' volumes add up to :func:`clipped_volumes` of the box.

    Args:
        source: a :class:`polydem.Simulation` or :class:`Grains`.
        axis: 0, 1, 2 or "x", "y", "z".
        bin_width: slab thickness [m]; default a quarter of the grain size.
        box: the region; default the box around the counted grains.
        margin: move the box's faces across the other two axes in by this many grain sizes (away from
            side walls); the profile itself runs the box's whole extent along ``axis``.
    """
    g = _grains(source)
    k = _axis(axis)
    box = Box.around(g) if box is None else box
    if margin:
        box = box.shrunk(float(margin) * g.grain_size(), axes=[a for a in range(3) if a != k])
    width = 0.25 * g.grain_size() if bin_width is None else _positive("bin_width", bin_width)
    edges = _edges(box.lower[k], box.upper[k], width)
    nb = len(edges) - 1
    # The grains' volume below each edge, as what lies wholly below it (added at the first edge at or
    # above an item's top, then summed up the edges) and the clipped parts of what it cuts.
    whole = np.zeros(nb + 2)
    split = np.zeros(nb + 1)
    inside, cut = _cut_by_box(g, box)
    bodies = np.sort(np.concatenate([inside, cut]))
    templates = _Templates(g.shapes)
    reps = np.ceil(2.0 * g.radii() / width).astype(np.int64) + 2
    cost = _segments_per_body(g, templates) * reps
    for block in _blocks(bodies, cost[bodies]):
        _profile_block(g, templates, block, box, k, edges, whole, split)
    below = np.cumsum(whole)[: nb + 1] + split
    solid = np.diff(below)
    slab = np.diff(edges) * float(np.prod(np.delete(box.upper - box.lower, k)))
    centres = 0.5 * (edges[1:] + edges[:-1])
    return PackingProfile(k, edges, centres, solid / slab, solid, slab, box)


def _profile_block(g, templates, bodies, box, k, edges, whole, split):
    """Add the volume of ``bodies`` in ``box`` below each edge: into ``whole`` at the first edge at or
    above an item's top, into ``split`` clipped at each edge that cuts an item."""
    seg, src, sign, next_face = _build(g, templates, bodies)
    item_body = bodies[src]
    centre = g.position[item_body]
    seg, next_face = _clip_to_box(seg, centre, box, next_face)
    n_items = len(item_body)
    v = sign * _volumes(seg, n_items)
    # The items' extent along the axis, from what is left of them.
    x0 = seg.p0[:, k] + centre[seg.item, k]
    x1 = seg.p1[:, k] + centre[seg.item, k]
    lo = np.full(n_items, np.inf)
    hi = np.full(n_items, -np.inf)
    np.minimum.at(lo, seg.item, np.minimum(x0, x1))
    np.maximum.at(hi, seg.item, np.maximum(x0, x1))
    present = np.isfinite(lo)
    np.add.at(whole, np.searchsorted(edges, hi[present], side="left"), v[present])
    first = np.searchsorted(edges, lo, side="right")
    count = np.where(present, np.maximum(np.searchsorted(edges, hi, side="left") - first, 0), 0)
    if not count.any():
        return
    pair_item = np.repeat(np.arange(n_items), count)
    pair_edge = _ranges(first, count)
    order = np.argsort(seg.item, kind="stable")
    sizes = np.bincount(seg.item, minlength=n_items)
    starts = np.cumsum(sizes) - sizes
    rep = seg.take(order[_ranges(starts[pair_item], sizes[pair_item])])
    pair_of = np.repeat(np.arange(len(pair_item)), sizes[pair_item])
    _, faces = np.unique(rep.face, return_inverse=True)
    stride = int(faces.max()) + 1
    rep = _Segments(pair_of, pair_of * stride + faces.reshape(-1), rep.p0, rep.p1, rep.n, rep.d)
    normal = np.broadcast_to(np.eye(3)[k], (len(pair_item), 3))
    offset = edges[pair_edge] - centre[pair_item, k]
    rep, _ = _clip(rep, normal, offset, stride * len(pair_item))
    np.add.at(split, pair_edge, sign[pair_item] * _volumes(rep, len(pair_item)))


# ----------------------------------------------------------------------------------- contact types


@dataclass
class ContactTypes:
    """The type of each contact, from its geometry at the current poses (module docstring).

    Attributes:
        body_a, body_b: (C,) int64 the bodies, as ``Simulation.contacts()`` (``body_b = -1 - p`` for wall p).
        kind: (C,) int64 index into :data:`KINDS`, -1 where not classified: with ``method="overlap"``
            no overlap at the current poses (a contact that opened in the last step) or one body
            inside the other; with ``"features"`` a vertex or an edge against a vertex or an edge
            other than two edges.
        ratio: (C,) ``V / (S d)`` [-] (NaN where there is no overlap).
        volume: (C,) overlap volume V [m^3]; area: (C,) S = |S_A| [m^2]; depth: (C,) d [m].
        face_angle: (C,) angle between the contact normal and the nearest face normal of either
            body facing the other [degrees] (0 for a wall contact: the wall is a face).
        feature_a, feature_b: (C,) int64 what each body presents to the other within
            ``align_angle``: 2 a face, 1 an edge, 0 a vertex (2 for a wall).
        method: "overlap" or "features", how ``kind`` was decided.
    """

    body_a: np.ndarray
    body_b: np.ndarray
    kind: np.ndarray
    ratio: np.ndarray
    volume: np.ndarray
    area: np.ndarray
    depth: np.ndarray
    face_angle: np.ndarray
    feature_a: np.ndarray | None = None
    feature_b: np.ndarray | None = None
    method: str = "overlap"

    def names(self) -> np.ndarray:
        """(C,) the kind of each contact by name ("unclassified" for -1)."""
        labels = np.array((*KINDS, "unclassified"))
        return labels[np.where(self.kind >= 0, self.kind, len(KINDS))]

    def counts(self, select=None) -> dict:
        """Contacts of each kind (of the ``select`` (C,) bool rows), by name; "unclassified" too."""
        k = self.kind if select is None else self.kind[np.asarray(select, dtype=bool)]
        out = {name: int(np.sum(k == i)) for i, name in enumerate(KINDS)}
        out["unclassified"] = int(np.sum(k < 0))
        return out


def classify(ratio, face_angle, *, face_ratio=FACE_RATIO, vertex_ratio=VERTEX_RATIO, align_angle=ALIGN_ANGLE):
    """(C,) int64 kind by the overlap's shape (index into :data:`KINDS`, -1 where ``ratio`` is NaN),
    from ``V / (S d)`` and the angle [degrees] between the contact normal and the nearest face normal
    of either body."""
    r = np.asarray(ratio, dtype=np.float64)
    a = np.asarray(face_angle, dtype=np.float64)
    if not 0.0 < vertex_ratio < face_ratio:
        raise ValueError(f"need 0 < vertex_ratio < face_ratio, got {vertex_ratio}, {face_ratio}")
    kind = np.where(r >= face_ratio, 0, np.where(r >= vertex_ratio, 1, 2))
    kind = np.where(a > align_angle, 3, kind)
    return np.where(np.isfinite(r), kind, -1).astype(np.int64)


def classify_features(feature_a, feature_b) -> np.ndarray:
    """(C,) int64 kind by the features the bodies present (2 face, 1 edge, 0 vertex; index into
    :data:`KINDS`): face and face, face and edge, face and vertex, edge and edge; -1 for the rest."""
    fa = np.asarray(feature_a, dtype=np.int64)
    fb = np.asarray(feature_b, dtype=np.int64)
    hi, lo = np.maximum(fa, fb), np.minimum(fa, fb)
    table = np.array([[-1, -1, 2], [-1, 3, 1], [2, 1, 0]])  # [lo][hi]
    return table[lo, hi]


def _gauss_map(shape):
    """The Gauss map of a shape's convex parts in its body frame: (face normals (F, 3), and for each
    edge the normals of its two faces, p (E, 3) and q (E, 3): the arc of directions it presents)."""
    normals, p, q = [], [], []
    for part, rot, _ in convex_parts(shape):
        fn = part.face_normals @ rot.T
        owner = {}
        for f, loop in enumerate(part.faces):
            ids = [int(v) for v in loop]
            for i, j in zip(ids, ids[1:] + ids[:1], strict=True):
                owner[(i, j)] = f
        for (i, j), f in owner.items():
            other = owner.get((j, i))
            if other is not None and f < other:
                p.append(fn[f])
                q.append(fn[other])
        normals.append(fn)
    return np.concatenate(normals), np.array(p).reshape(-1, 3), np.array(q).reshape(-1, 3)


def _largest_dot(u, table) -> np.ndarray:
    """(K,) max over the rows t of ``table`` (T, 3) of u_k . t, for (K, 3) ``u``, in blocks of ~1e6 products."""
    out = np.empty(len(u))
    step = max(1, (1 << 20) // max(1, len(table)))
    for start in range(0, len(u), step):
        out[start : start + step] = (u[start : start + step] @ table.T).max(axis=1)
    return out


def _presents_edge(u, p, q, sin_a) -> np.ndarray:
    """(K,) whether each direction u (K, 3) lies within asin(sin_a) of some edge's arc from p to q."""
    m = np.cross(p, q)
    m /= np.linalg.norm(m, axis=1, keepdims=True)
    after_p, before_q = np.cross(m, p), np.cross(q, m)
    out = np.zeros(len(u), dtype=bool)
    step = max(1, (1 << 20) // max(1, len(p)))
    for start in range(0, len(u), step):
        v = u[start : start + step]
        near = (np.abs(v @ m.T) <= sin_a) & (v @ after_p.T >= 0.0) & (v @ before_q.T >= 0.0)
        out[start : start + step] = near.any(axis=1)
    return out


def _features(g: Grains, gauss, bodies, direction, align_angle):
    """(cosine of the angle to the nearest face normal (K,), feature (K,): 2 face, 1 edge, 0 vertex)
    that each body presents towards ``direction`` (K, 3), world."""
    facing = np.full(len(bodies), -1.0)
    feature = np.zeros(len(bodies), dtype=np.int64)
    local = np.einsum("kji,kj->ki", quat_to_matrix(g.orientation[bodies]), direction)  # R^T n
    shape = g.body_shape[bodies]
    cos_a, sin_a = math.cos(math.radians(align_angle)), math.sin(math.radians(align_angle))
    for s in np.unique(shape).tolist():
        rows = np.flatnonzero(shape == s)
        normals, p, q = gauss[s]
        facing[rows] = _largest_dot(local[rows], normals)
        edge = _presents_edge(local[rows], p, q, sin_a) if len(p) else np.zeros(len(rows), dtype=bool)
        feature[rows] = np.where(facing[rows] >= cos_a, 2, np.where(edge, 1, 0))
    return facing, feature


def _wall_geometry(g: Grains, templates, bodies, normal, offset):
    """Overlap of each of ``bodies`` (K,) with its half-space ``normal . x <= offset`` ((K, 3) unit
    normals, (K,) offsets [m], world): (volume (K,) [m^3], area of the section by the plane (K,)
    [m^2], depth of the deepest vertex beyond the plane (K,) [m])."""
    k = len(bodies)
    volume, area = np.zeros(k), np.zeros(k)
    if not k:
        return volume, area, np.zeros(k)
    seg, src, sign, next_face = _build(g, templates, bodies)
    m = normal[src]
    rel = offset[src] - _dot(g.position[bodies[src]], m)
    lowest = np.full(k, np.inf)
    np.minimum.at(lowest, src[seg.item], _dot(seg.p0, m[seg.item]))
    depth = np.maximum(offset - _dot(g.position[bodies], normal) - lowest, 0.0)
    seg, _ = _clip(seg, m, rel, next_face)
    np.add.at(volume, src, sign * _volumes(seg, len(src)))
    cap = seg.face >= next_face
    w = 0.5 * _dot(np.cross(seg.p0[cap], seg.p1[cap]), seg.n[cap])
    np.add.at(area, src, sign * np.bincount(seg.item[cap], weights=w, minlength=len(src)))
    return np.maximum(volume, 0.0), np.maximum(area, 0.0), depth


def _lowest(g: Grains, bodies, normal) -> np.ndarray:
    """(K,) smallest ``normal . x`` over each body's vertices [m] (world; ``normal`` (K, 3))."""
    out = np.empty(len(bodies))
    local = np.einsum("kji,kj->ki", quat_to_matrix(g.orientation[bodies]), normal)
    shape = g.body_shape[bodies]
    for s in np.unique(shape).tolist():
        rows = np.flatnonzero(shape == s)
        verts = np.concatenate([p.vertices @ r.T + t for p, r, t in convex_parts(g.shapes[s])])
        out[rows] = -_largest_dot(-local[rows], verts)
    return out + _dot(g.position[bodies], normal)


def classify_contacts(
    source,
    contacts=None,
    *,
    method: str = "features",
    face_ratio: float = FACE_RATIO,
    vertex_ratio: float = VERTEX_RATIO,
    align_angle: float = ALIGN_ANGLE,
    device=None,
) -> ContactTypes:
    """Classify each contact as face-face, edge-face, vertex-face or edge-edge (module docstring).

    The overlap of each contact is taken again at the current poses, in float64: a pair's by
    :func:`polydem.overlap` (``frame="body"``), a plane wall's by clipping the grain exactly; a mesh
    wall counts as the plane of the contact's reported normal, at its reported depth below the
    grain's deepest vertex (exact where the wall is flat around the contact).

    Two methods decide the kind. ``"overlap"``: the shape of the overlap, ``V / (S d)``,
    and edge-edge where neither body has a face within ``align_angle`` of the contact plane; it
    tells what the contact law acts on, so it depends on the stiffness: faces misaligned by more
    than about d / L radians (d the depth, L the face's width) touch by a corner or an edge.
    ``"features"`` (default: in a settled pile of cubes the overlap method calls no contact face-face,
    as faces lie 0.1-2 degrees out of parallel): what each body presents to the other within
    ``align_angle`` of the contact
    normal (its Gauss map: a face whose normal is that close, else an edge whose arc of normals
    passes that close, else a vertex), the same at any stiffness; a vertex against an edge or a
    vertex is left unclassified.

    Args:
        source: a :class:`polydem.Simulation` or :class:`Grains` (with its planes for wall contacts).
        contacts: a dict as ``Simulation.contacts()`` (``body_a``, ``body_b``; ``normal`` and
            ``depth`` for mesh walls); default ``source.contacts()``.
        method: "overlap" or "features".
        face_ratio, vertex_ratio, align_angle: the thresholds (:data:`FACE_RATIO`,
            :data:`VERTEX_RATIO`, :data:`ALIGN_ANGLE` [degrees]).
        device: Warp device of the pair geometry; default the simulation's (else Warp's default).
    """
    from polydem.batch import overlap

    if method not in ("overlap", "features"):
        raise ValueError(f"method must be 'overlap' or 'features', got {method!r}")
    g = _grains(source)
    c = _contacts(source, contacts)
    if device is None and hasattr(source, "model"):
        device = source.model.device
    a = np.asarray(c["body_a"], dtype=np.int64).reshape(-1)
    b = np.asarray(c["body_b"], dtype=np.int64).reshape(-1)
    n_c = len(a)
    volume, area, depth = np.zeros(n_c), np.zeros(n_c), np.zeros(n_c)
    normal = np.zeros((n_c, 3))
    valid = np.zeros(n_c, dtype=bool)
    rows = np.flatnonzero(b >= 0)
    keys = g.body_shape[a[rows]] * len(g.shapes) + g.body_shape[b[rows]]
    for key in np.unique(keys).tolist():
        sel = rows[keys == key]
        sa, sb = divmod(key, len(g.shapes))
        pa = np.hstack([g.position[a[sel]], g.orientation[a[sel]]])
        pb = np.hstack([g.position[b[sel]], g.orientation[b[sel]]])
        r = overlap(g.shapes[sa], pa, g.shapes[sb], pb, frame="body", device=device, precision="float64")
        size = np.linalg.norm(r.area_vector, axis=1)
        volume[sel], area[sel], depth[sel] = r.volume, size, r.depth
        # Where nothing overlaps now, the normal the step reported, or overlap()'s line of centres.
        fallback = np.asarray(c["normal"], dtype=np.float64)[sel] if "normal" in c else r.normal
        unit = r.area_vector / np.where(size > 0.0, size, 1.0)[:, None]
        normal[sel] = np.where((size > 0.0)[:, None], unit, fallback)
        valid[sel] = ~r.enclosed
    walls = np.flatnonzero(b < 0)
    if len(walls):
        plane = -1 - b[walls]
        is_plane = plane < len(g.plane_offset)
        outward = np.zeros((len(walls), 3))
        offset = np.zeros(len(walls))
        outward[is_plane] = g.plane_normal[plane[is_plane]]
        offset[is_plane] = g.plane_offset[plane[is_plane]]
        mesh = np.flatnonzero(~is_plane)
        if len(mesh):
            if "normal" not in c or "depth" not in c:
                raise ValueError("contacts with mesh walls need the contacts' normal and depth")
            # The reported normal runs from the grain into the wall: the wall's own points the other way.
            outward[mesh] = -np.asarray(c["normal"], dtype=np.float64)[walls[mesh]]
            depth_reported = np.asarray(c["depth"], dtype=np.float64)[walls[mesh]]
            offset[mesh] = _lowest(g, a[walls[mesh]], outward[mesh]) + depth_reported
        templates = _Templates(g.shapes)
        volume[walls], area[walls], depth[walls] = _wall_geometry(g, templates, a[walls], outward, offset)
        normal[walls] = -outward
        valid[walls] = True
    valid &= (volume > 0.0) & (area > 0.0) & (depth > 0.0)
    ratio = np.full(n_c, np.nan)
    ratio[valid] = volume[valid] / (area[valid] * depth[valid])
    gauss = [_gauss_map(shape) for shape in g.shapes]
    facing_a, feature_a = _features(g, gauss, a, normal, align_angle)
    facing_b, feature_b = np.ones(n_c), np.full(n_c, 2, dtype=np.int64)
    facing_b[rows], feature_b[rows] = _features(g, gauss, b[rows], -normal[rows], align_angle)
    angle = np.degrees(np.arccos(np.clip(np.maximum(facing_a, facing_b), -1.0, 1.0)))
    if method == "overlap":
        kind = classify(ratio, angle, face_ratio=face_ratio, vertex_ratio=vertex_ratio, align_angle=align_angle)
    else:
        kind = classify_features(feature_a, feature_b)
    return ContactTypes(a, b, kind, ratio, volume, area, depth, angle, feature_a, feature_b, method)


# ------------------------------------------------------------------------------------ coordination


@dataclass
class Coordination:
    """Coordination number of the counted grains that are not rattlers.

    Attributes:
        z: mean number of contacts of a counted grain that is not a rattler (contacts with rattlers
            left out; with walls, fixed and kinematic bodies counted unless ``walls`` was off).
        z_by_kind: the part of ``z`` of each contact type (:data:`KINDS`, and "unclassified"), summing to ``z``.
        grains: counted grains that are not rattlers.
        rattlers: (R,) int64 the counted grains that are rattlers.
        rattler_fraction: R over the counted grains.
        contacts: (N,) int64 contacts of each body once the rattlers are removed (0 for rattlers).
        min_contacts: the rattler threshold used.
    """

    z: float
    z_by_kind: dict
    grains: int
    rattlers: np.ndarray
    rattler_fraction: float
    contacts: np.ndarray
    min_contacts: int

    def to_dict(self) -> dict:
        """Plain numbers (None for NaN: no grain left), without the per-body arrays."""
        return {
            "z": _finite(self.z),
            "z_by_kind": {k: _finite(v) for k, v in self.z_by_kind.items()},
            "grains": self.grains,
            "rattlers": int(len(self.rattlers)),
            "rattler_fraction": _finite(self.rattler_fraction),
            "min_contacts": self.min_contacts,
        }


def _finite(x):
    return float(x) if math.isfinite(x) else None


def coordination(
    source,
    contacts=None,
    types: ContactTypes | None = None,
    *,
    min_contacts: int = MIN_CONTACTS,
    walls: bool = True,
    iterate: bool = False,
    device=None,
) -> Coordination:
    """Coordination number without rattlers, and its split by contact type.

    A rattler is a free body with fewer than ``min_contacts`` contacts; it is removed with its
    contacts, and, with ``iterate``, so is every body that this leaves with too few, until none does
    (what jamming studies of spheres do: a grain held by a rattler is not held). Only free bodies
    can be rattlers; walls, fixed and kinematic bodies count as contacts of the grains they touch
    (not with ``walls`` off). ``z`` averages over the counted grains (``Grains.counted``: the free
    bodies of a simulation) that are left, counting their contacts with each other and the walls.

    Polyhedra hold with fewer contacts than spheres (a face contact blocks what three point
    contacts would): in a settled pour of cubes the mean is near 4, and removing rattlers at 4 until
    none is left strips almost the whole pile. Hence one pass by default.

    Args:
        source: a :class:`polydem.Simulation` or :class:`Grains`.
        contacts: as ``Simulation.contacts()``; default ``source.contacts()``.
        types: the contacts' :class:`ContactTypes`, for ``z_by_kind``; default computed with
            :func:`classify_contacts` (pass ``False`` to leave ``z_by_kind`` empty).
        min_contacts: the rattler threshold (default :data:`MIN_CONTACTS`; 0: no rattlers).
        walls: count contacts with walls (planes and mesh walls).
        iterate: remove rattlers until none is left (default: one pass).
        device: for :func:`classify_contacts`.
    """
    g = _grains(source)
    c = _contacts(source, contacts)
    n = g.num_bodies
    a = np.asarray(c["body_a"], dtype=np.int64).reshape(-1)
    b = np.asarray(c["body_b"], dtype=np.int64).reshape(-1)
    use = np.ones(len(a), dtype=bool) if walls else b >= 0
    if types is None:
        types = classify_contacts(g, c, device=device)
    if types is not False and len(types.kind) != len(a):
        raise ValueError(f"types has {len(types.kind)} rows for {len(a)} contacts: classify these contacts")
    alive = np.ones(n, dtype=bool)

    def counts(rows):
        live = rows & alive[a] & np.where(b >= 0, alive[np.maximum(b, 0)], True)
        pair = live & (b >= 0)
        return np.bincount(a[live], minlength=n) + np.bincount(b[pair], minlength=n)

    while True:
        per_body = counts(use)
        rattle = g.free & alive & (per_body < int(min_contacts))
        if not rattle.any():
            break
        alive &= ~rattle
        if not iterate:
            per_body = counts(use)
            break
    keep = g.counted & alive
    grains = int(keep.sum())
    z = float(per_body[keep].mean()) if grains else float("nan")
    by_kind = {}
    if types is not False:
        kind = np.asarray(types.kind)
        for i, name in enumerate((*KINDS, "unclassified")):
            rows = use & ((kind == i) if i < len(KINDS) else (kind < 0))
            by_kind[name] = float(counts(rows)[keep].mean()) if grains else float("nan")
    rattlers = np.flatnonzero(g.counted & ~alive)
    counted = int(g.counted.sum())
    return Coordination(
        z, by_kind, grains, rattlers, len(rattlers) / counted if counted else float("nan"), per_body * alive,
        int(min_contacts),
    )  # fmt: skip


# ------------------------------------------------------------------------------- contact selection


def _contact_dict(contacts) -> dict:
    if isinstance(contacts, dict):
        return contacts
    if hasattr(contacts, "contacts"):
        return contacts.contacts()
    raise TypeError(f"expected a contacts dict (Simulation.contacts()) or a Simulation, got {type(contacts).__name__}")


def _select(c: dict, walls: bool, select=None, box: Box | None = None) -> np.ndarray:
    """(C,) bool: the rows kept: pairs (and wall contacts with ``walls``), within ``select`` and with
    their contact point in ``box``."""
    b = np.asarray(c["body_b"], dtype=np.int64).reshape(-1)
    keep = np.ones(len(b), dtype=bool) if walls else b >= 0
    if select is not None:
        keep &= np.asarray(select, dtype=bool).reshape(-1)
    if box is not None:
        keep &= box.contains(c["point"])
    return keep


def _force_on_a(c: dict) -> np.ndarray:
    """(C, 3) force on A [N]: ``force`` of a contact average, else from the normal and tangential parts."""
    if "force" in c:
        return np.asarray(c["force"], dtype=np.float64).reshape(-1, 3)
    fn = np.asarray(c["normal_force"], dtype=np.float64).reshape(-1)
    ft = np.asarray(c["tangential_force"], dtype=np.float64)
    return -fn[:, None] * np.asarray(c["normal"], dtype=np.float64) + ft


def _unit_normals(c: dict) -> np.ndarray:
    n = np.asarray(c["normal"], dtype=np.float64).reshape(-1, 3)
    size = np.linalg.norm(n, axis=1, keepdims=True)
    return np.divide(n, size, out=np.zeros_like(n), where=size > 0.0)


# ------------------------------------------------------------------------------------------- fabric


def fabric(contacts, *, walls: bool = False, select=None, box: Box | None = None, weights=None) -> np.ndarray:
    """Fabric tensor ``F = sum_c w_c n_c (x) n_c / sum_c w_c``: (3, 3), trace 1; I/3 when isotropic.

    Args:
        contacts: a dict as ``Simulation.contacts()`` (its ``normal``), or a Simulation.
        walls: count the contacts with walls too (default: between grains only).
        select: (C,) bool, the contacts to count; box: only those with their point in it.
        weights: (C,) weights w_c (e.g. the normal forces, for the force-weighted fabric); default 1.

    Raises:
        ValueError: no contact is selected.
    """
    c = _contact_dict(contacts)
    keep = _select(c, walls, select, box)
    n = _unit_normals(c)[keep]
    w = np.ones(len(n)) if weights is None else np.asarray(weights, dtype=np.float64).reshape(-1)[keep]
    if not len(n) or w.sum() <= 0.0:
        raise ValueError("no contact to take the fabric of")
    return np.einsum("c,ci,cj->ij", w, n, n) / w.sum()


# -------------------------------------------------------------------------------------------- stress


def _inside_fraction(start, end, box: Box) -> np.ndarray:
    """(C,) fraction of each segment start -> end ((C, 3) [m]) inside ``box`` (Liang-Barsky)."""
    d = end - start
    t0 = np.zeros(len(d))
    t1 = np.ones(len(d))
    for k in range(3):
        moving = d[:, k] != 0.0
        with np.errstate(divide="ignore", invalid="ignore"):
            ta = (box.lower[k] - start[:, k]) / d[:, k]
            tb = (box.upper[k] - start[:, k]) / d[:, k]
        t0 = np.where(moving, np.maximum(t0, np.minimum(ta, tb)), t0)
        t1 = np.where(moving, np.minimum(t1, np.maximum(ta, tb)), t1)
        out = ~moving & ((start[:, k] < box.lower[k]) | (start[:, k] > box.upper[k]))
        t1 = np.where(out, -1.0, t1)
    return np.clip(t1 - t0, 0.0, 1.0)


def _branches(positions, c):
    """(start (C, 3), branch (C, 3)): A's centre, and the vector to B's centre or the wall contact point [m]."""
    a = np.asarray(c["body_a"], dtype=np.int64).reshape(-1)
    b = np.asarray(c["body_b"], dtype=np.int64).reshape(-1)
    start = positions[a]
    end = np.where((b >= 0)[:, None], positions[np.maximum(b, 0)], np.asarray(c["point"], dtype=np.float64))
    return start, end - start


def _stress_in(box, start, branch, f_on_b) -> np.ndarray:
    w = _inside_fraction(start, start + branch, box)
    return np.einsum("c,ci,cj->ij", w, f_on_b, branch) / box.volume


def stress(source, box: Box, contacts=None, *, walls: bool = True, weighting: str = "branch") -> np.ndarray:
    """Love-Weber stress in ``box``: (3, 3) [Pa], compressive positive, ``sigma_ij = 1/V sum_c f_i l_j``.

    f the force A exerts on B [N], l the branch vector from A's centre to B's (for a wall contact,
    to the contact point) [m]. With ``weighting="branch"`` each contact counts by the fraction of
    its branch vector inside the box (module docstring); with ``"point"``, wholly where its contact
    point lies in the box, else not at all.

    Args:
        source: a :class:`polydem.Simulation`, :class:`Grains`, or the (N, 3) centres [m].
        box: the region.
        contacts: as ``Simulation.contacts()`` or ``Simulation.contact_average()`` (its mean
            ``force``); default ``source.contacts()``.
        walls: count the contacts with walls (default on: the grains next to a wall carry its push).
    """
    x = _positions(source)
    c = _contacts(source, contacts)
    keep = _select(c, walls)
    start, branch = _branches(x, c)
    f_on_b = -_force_on_a(c)
    if weighting == "point":
        inside = keep & box.contains(c["point"])
        return np.einsum("ci,cj->ij", f_on_b[inside], branch[inside]) / box.volume
    if weighting != "branch":
        raise ValueError(f"weighting must be 'branch' or 'point', got {weighting!r}")
    return _stress_in(box, start[keep], branch[keep], f_on_b[keep])


@dataclass
class StressProfile:
    """Love-Weber stress in slabs along one axis.

    Attributes:
        axis: 0, 1 or 2; edges: (K+1,) slab boundaries [m]; centres: (K,) [m];
        stress: (K, 3, 3) [Pa], compressive positive; box: the region the slabs divide.
    """

    axis: int
    edges: np.ndarray
    centres: np.ndarray
    stress: np.ndarray
    box: Box

    def to_dict(self) -> dict:
        return {
            "axis": self.axis,
            "edges": self.edges.tolist(),
            "centres": self.centres.tolist(),
            "stress": self.stress.tolist(),
            "box": self.box.to_dict(),
        }


def stress_profile(
    source, axis=2, bin_width: float | None = None, box: Box | None = None, contacts=None, *, walls: bool = True
) -> StressProfile:
    """Love-Weber stress (:func:`stress`, branch weighting) in slabs ``bin_width`` thick along ``axis``.

    Args:
        source: a :class:`polydem.Simulation`, :class:`Grains`, or the (N, 3) centres [m] (then
            ``box`` and ``bin_width`` are needed).
        axis: 0, 1, 2 or "x", "y", "z".
        bin_width: slab thickness [m]; default the grain size.
        box: the region; default the box around the counted grains.
        contacts, walls: as :func:`stress`.
    """
    k = _axis(axis)
    if box is None or bin_width is None:
        g = _grains(source)
        box = Box.around(g) if box is None else box
        bin_width = g.grain_size() if bin_width is None else bin_width
    width = _positive("bin_width", bin_width)
    x = _positions(source)
    c = _contacts(source, contacts)
    keep = _select(c, walls)
    start, branch = _branches(x, c)
    start, branch, f_on_b = start[keep], branch[keep], -_force_on_a(c)[keep]
    edges = _edges(box.lower[k], box.upper[k], width)
    out = np.zeros((len(edges) - 1, 3, 3))
    for j in range(len(edges) - 1):
        lo, hi = box.lower.copy(), box.upper.copy()
        lo[k], hi[k] = edges[j], edges[j + 1]
        out[j] = _stress_in(Box(lo, hi), start, branch, f_on_b)
    return StressProfile(k, edges, 0.5 * (edges[1:] + edges[:-1]), out, box)


# ----------------------------------------------------------------------------------- distributions


@dataclass
class ForceDistribution:
    """Distribution of contact forces normalised by their mean, ``P(f / <f>)``.

    Attributes:
        edges: (B+1,) bin edges of f / <f> [-]; density: (B,) probability density [-] (integrates to
            1 over the bins, with the forces beyond the last edge counted in ``beyond``).
        mean: <f> [N]; count: contacts counted; beyond: fraction above the last edge.
        forces: (count,) the forces [N].
    """

    edges: np.ndarray
    density: np.ndarray
    mean: float
    count: int
    beyond: float
    forces: np.ndarray

    def to_dict(self) -> dict:
        return {
            "edges": self.edges.tolist(),
            "density": self.density.tolist(),
            "mean": self.mean,
            "count": self.count,
            "beyond": self.beyond,
        }


def force_distribution(
    contacts,
    *,
    bins=25,
    max_ratio: float | None = None,
    component: str = "normal",
    walls: bool = False,
    select=None,
    box: Box | None = None,
) -> ForceDistribution:
    """Histogram of ``f / <f>`` over the contacts with a force.

    Args:
        contacts: a dict as ``Simulation.contacts()`` or ``contact_average()``, or a Simulation.
        bins: number of bins over ``0..max_ratio``, or the (B+1,) edges.
        max_ratio: the last edge; default the largest ratio.
        component: "normal" (the normal force, default) or "total" (|normal + tangential|).
        walls, select, box: which contacts (as :func:`fabric`).
    """
    c = _contact_dict(contacts)
    keep = _select(c, walls, select, box)
    if component == "normal":
        f = np.asarray(c["normal_force"], dtype=np.float64).reshape(-1)[keep]
    elif component == "total":
        f = np.linalg.norm(_force_on_a(c)[keep], axis=1)
    else:
        raise ValueError(f"component must be 'normal' or 'total', got {component!r}")
    f = f[f > 0.0]
    if not len(f):
        raise ValueError("no contact carries a force")
    mean = float(f.mean())
    ratio = f / mean
    if np.ndim(bins) == 0:
        top = float(ratio.max()) if max_ratio is None else _positive("max_ratio", max_ratio)
        edges = np.linspace(0.0, top, int(bins) + 1)
    else:
        edges = np.asarray(bins, dtype=np.float64)
    counts, _ = np.histogram(ratio, bins=edges)
    density = counts / (len(ratio) * np.diff(edges))
    beyond = float(np.sum(ratio > edges[-1]) / len(ratio))
    return ForceDistribution(edges, density, mean, len(f), beyond, f)


def _frame(axis, reference):
    """Unit ``axis``, a unit ``reference`` perpendicular to it (default the coordinate axis most
    perpendicular) and ``axis x reference``: a right-handed frame for polar and azimuth angles."""
    u = _direction(axis)
    if reference is None:
        reference = np.eye(3)[int(np.argmin(np.abs(u)))]
    r = _direction(reference)
    e1 = r - u * float(r @ u)
    size = np.linalg.norm(e1)
    if size < 1e-9:
        raise ValueError("the reference direction must not be parallel to the axis")
    e1 /= size
    return u, e1, np.cross(u, e1)


@dataclass
class OrientationDistribution:
    """Distribution of contact normal directions over the sphere, per steradian.

    Attributes:
        polar_edges: (P+1,) angle from ``axis`` [rad], 0..pi; azimuth_edges: (A+1,) angle about it
            from ``reference`` [rad], -pi..pi.
        density: (P, A) probability per steradian (1 / (4 pi) everywhere when isotropic).
        count: contacts counted; axis, reference: (3,) unit vectors.
    """

    polar_edges: np.ndarray
    azimuth_edges: np.ndarray
    density: np.ndarray
    count: int
    axis: np.ndarray
    reference: np.ndarray

    def polar_density(self) -> np.ndarray:
        """(P,) probability per steradian of each polar band, averaged over the azimuth."""
        widths = np.diff(self.azimuth_edges)
        return (self.density * widths).sum(axis=1) / widths.sum()

    def to_dict(self) -> dict:
        return {
            "polar_edges": self.polar_edges.tolist(),
            "azimuth_edges": self.azimuth_edges.tolist(),
            "density": self.density.tolist(),
            "count": self.count,
            "axis": self.axis.tolist(),
            "reference": self.reference.tolist(),
        }


def _directions(c, walls, select, box, weights, symmetric):
    keep = _select(c, walls, select, box)
    n = _unit_normals(c)[keep]
    w = np.ones(len(n)) if weights is None else np.asarray(weights, dtype=np.float64).reshape(-1)[keep]
    if not len(n):
        raise ValueError("no contact to take the orientations of")
    if symmetric:
        # A contact has no direction of its own (A and B could be swapped): each counts half as +n, half as -n.
        n = np.concatenate([n, -n])
        w = np.concatenate([w, w]) * 0.5
    return n, w, int(keep.sum())


def normal_orientations(
    contacts,
    *,
    axis=2,
    reference=None,
    polar_bins: int = 18,
    azimuth_bins: int = 36,
    walls: bool = False,
    select=None,
    box: Box | None = None,
    weights=None,
    symmetric: bool = True,
) -> OrientationDistribution:
    """Histogram of the contact normals over polar angle (from ``axis``) and azimuth (about it).

    Args:
        contacts: a dict as ``Simulation.contacts()``, or a Simulation.
        axis: 0, 1, 2, "x", "y", "z" or a (3,) direction (default z, the vertical of a pile).
        reference: (3,) direction of azimuth 0 (default the coordinate axis most perpendicular).
        polar_bins, azimuth_bins: bins of equal angle.
        walls, select, box: which contacts (as :func:`fabric`); weights: (C,) (e.g. forces), default 1.
        symmetric: count each normal as +n and -n (default: a pair contact has no sign of its own).
    """
    c = _contact_dict(contacts)
    u, e1, e2 = _frame(axis, reference)
    n, w, count = _directions(c, walls, select, box, weights, symmetric)
    polar = np.arccos(np.clip(n @ u, -1.0, 1.0))
    azimuth = np.arctan2(n @ e2, n @ e1)
    pe = np.linspace(0.0, math.pi, int(polar_bins) + 1)
    ae = np.linspace(-math.pi, math.pi, int(azimuth_bins) + 1)
    hist, _, _ = np.histogram2d(polar, azimuth, bins=(pe, ae), weights=w)
    solid = np.outer(np.cos(pe[:-1]) - np.cos(pe[1:]), np.diff(ae))
    return OrientationDistribution(pe, ae, hist / (w.sum() * solid), count, u, e1)


@dataclass
class Rose:
    """Distribution of the contact normals' directions within a plane (a rose diagram).

    Attributes:
        edges: (B+1,) angle in the plane [rad], -pi..pi, from ``first`` towards ``second``.
        fraction: (B,) share of the (weighted) contacts in each bin, summing to 1.
        count: contacts counted; first, second: (3,) unit vectors spanning the plane.
    """

    edges: np.ndarray
    fraction: np.ndarray
    count: int
    first: np.ndarray
    second: np.ndarray

    def to_dict(self) -> dict:
        return {
            "edges": self.edges.tolist(),
            "fraction": self.fraction.tolist(),
            "count": self.count,
            "first": self.first.tolist(),
            "second": self.second.tolist(),
        }


def _direction(v) -> np.ndarray:
    u = np.eye(3)[_axis(v)] if np.ndim(v) == 0 else np.asarray(v, dtype=np.float64).reshape(3)
    size = np.linalg.norm(u)
    if not np.isfinite(size) or size == 0.0:
        raise ValueError(f"a direction must be a non-zero (3,) vector or an axis, got {v!r}")
    return u / size


def normal_rose(
    contacts,
    *,
    plane=("x", "z"),
    bins: int = 36,
    walls: bool = False,
    select=None,
    box: Box | None = None,
    weights=None,
    symmetric: bool = True,
) -> Rose:
    """Rose diagram of the contact normals projected on a plane.

    Each contact counts by its weight (default 1) at the angle of its normal's projection on the
    plane, from ``plane[0]`` towards ``plane[1]`` (default the x-z plane, from x towards z: 0 is
    horizontal, pi/2 straight up). Normals perpendicular to the plane have no angle and are left out.

    Args:
        contacts: a dict as ``Simulation.contacts()``, or a Simulation.
        plane: two directions spanning it, each 0, 1, 2, "x", "y", "z" or a (3,) vector (the second
            is made perpendicular to the first).
        bins: bins of equal angle over -pi..pi.
        walls, select, box, weights, symmetric: as :func:`normal_orientations`.
    """
    c = _contact_dict(contacts)
    e1 = _direction(plane[0])
    e2 = _direction(plane[1])
    e2 = e2 - e1 * float(e1 @ e2)
    if np.linalg.norm(e2) < 1e-9:
        raise ValueError("the two directions of the plane must not be parallel")
    e2 /= np.linalg.norm(e2)
    n, w, _ = _directions(c, walls, select, box, weights, symmetric)
    x, y = n @ e1, n @ e2
    flat = np.hypot(x, y) > 1e-9
    edges = np.linspace(-math.pi, math.pi, int(bins) + 1)
    hist, _ = np.histogram(np.arctan2(y[flat], x[flat]), bins=edges, weights=w[flat])
    total = hist.sum()
    count = int(np.sum(flat) // (2 if symmetric else 1))
    return Rose(edges, hist / total if total > 0 else hist, count, e1, e2)


# -------------------------------------------------------------------------------------------- summary


def cubic_order(source, box: Box | None = None, *, frame=None) -> float:
    """Cubatic order of the counted grains' orientations in a frame: 1 when every grain's axes lie
    along the frame's, about 0 for orientations at random.

    For grain i with body axes u_ij (the columns of its rotation) and the frame's axes e_k,
    ``Q_i = (sum_jk (u_ij . e_k)^4 - 9/5) / (6/5)``: the sum is 3 for axes along the frame's and 9/5 on
    average over uniformly random rotations (a component of a random unit vector has a mean fourth power of
    1/5), and it is unchanged by any of the cube's 24 rotations. The result is the mean of Q_i: it tells a
    tapped pile of cubes that packs past the densest random packing by aligning with its box (ordering) from
    one that stays random. Meaningful for grains whose body axes are their axes of symmetry: cubes and boxes
    (``ConvexShape.box`` builds them along the body axes). A grain turned 45 degrees about one frame axis
    gives 1/6.

    Args:
        source: a :class:`polydem.Simulation` or :class:`Grains`.
        box: count the grains whose centre lies in this box (default every counted grain).
        frame: (3, 3) rows e_k, orthonormal (default the world axes: a box container's walls).
    """
    g = _grains(source)
    e = np.eye(3) if frame is None else np.asarray(frame, dtype=np.float64)
    if e.shape != (3, 3) or not np.allclose(e @ e.T, np.eye(3), atol=1e-9):
        raise ValueError(f"frame must be 3 orthonormal rows (3, 3), got {np.array2string(np.asarray(frame))}")
    return float(_cubic_q(e, _counted_axes(g, box)).mean())


def _counted_axes(g: Grains, box: Box | None) -> np.ndarray:
    keep = g.counted.copy()
    if box is not None:
        keep &= box.contains(g.position)
    if not keep.any():
        raise ValueError("no counted grain in the box: give a larger box, or none")
    return quat_to_matrix(g.orientation[keep])  # (M, 3, 3): column j is body axis j in the world


def _cubic_q(frame: np.ndarray, rot: np.ndarray) -> np.ndarray:
    cos = frame @ rot  # (M, 3, 3): cos[m, k, j] = e_k . u_mj
    return ((cos**4).sum(axis=(1, 2)) - 1.8) / 1.2


def cubic_frame(source, box: Box | None = None, *, starts: int = 64, seed: int = 0) -> tuple[float, np.ndarray]:
    """The frame the counted grains' axes align with best, and the cubic order in it: the cubatic order
    parameter with its director frame (:func:`cubic_order` maximised over every frame).

    A pile that orders away from its container's axes (in a tilted frame, or face to face in a frame of its
    own) shows it here and not in ``cubic_order(source)``. The maximum is searched from the frames of
    ``starts`` grains (chosen with ``seed``; if a fraction f of the grains share a frame, no start lies near
    it with a chance of only (1 - f)^starts) and refined from the best two by a simplex search over rotation
    vectors. Being a maximum, it is biased up for grains at random: about 0.01-0.02 for 2,700 grains, 0.005
    for 40,000 (a local maximum of the search, not always the global one).

    Returns:
        (order, frame): order as :func:`cubic_order` gives it in ``frame``, a (3, 3) array of orthonormal rows
        (the frame's axes in the world, each only up to sign and order: the cube's symmetry).
    """
    from scipy.optimize import minimize
    from scipy.spatial.transform import Rotation

    if int(starts) < 1:
        raise ValueError(f"starts must be at least 1, got {starts}")
    rot = _counted_axes(_grains(source), box)
    rng = np.random.default_rng(seed)
    picks = rng.choice(len(rot), size=min(int(starts), len(rot)), replace=False)
    candidates = [np.eye(3)] + [rot[i].T for i in picks]  # a grain's axes as the frame's rows
    ranked = sorted(candidates, key=lambda e: -_cubic_q(e, rot).mean())

    def loss(v, e0):
        return -_cubic_q(Rotation.from_rotvec(v).as_matrix() @ e0, rot).mean()

    best_q, best_e = -np.inf, np.eye(3)
    simplex = 0.2 * np.vstack([np.zeros(3), np.eye(3)])  # rotation vectors of 0.2 rad about each axis
    for e0 in ranked[:2]:
        options = {"xatol": 1e-7, "fatol": 1e-12, "initial_simplex": simplex}
        res = minimize(loss, np.zeros(3), args=(e0,), method="Nelder-Mead", options=options)
        if -res.fun > best_q:
            best_q, best_e = float(-res.fun), Rotation.from_rotvec(res.x).as_matrix() @ e0
    return best_q, best_e


def settled_box(scene, region: dict) -> Box | None:
    """The settled region of a run's summary (``polydem.cli.diagnostics.settled_region``: lower and upper
    corners along two horizontal axes and the height) as a world :class:`Box`, where gravity lies along
    a coordinate axis (else None: the region is not axis-aligned), or None where it has no box."""
    if region is None or "lower" not in region or region.get("bodies", 0) == 0:
        return None
    g = np.asarray(scene.gravity, dtype=np.float64)
    up = -g / np.linalg.norm(g) if np.linalg.norm(g) > 0.0 else np.array([0.0, 0.0, 1.0])
    e1 = np.eye(3)[int(np.argmin(np.abs(up)))] - up * float(up[int(np.argmin(np.abs(up)))])
    e1 /= np.linalg.norm(e1)
    basis = (e1, np.cross(up, e1), up)
    lo, hi = np.zeros(3), np.zeros(3)
    for v, l_, u_ in zip(basis, region["lower"], region["upper"], strict=True):
        k = int(np.argmax(np.abs(v)))
        if abs(abs(v[k]) - 1.0) > 1e-12:
            return None
        lo[k], hi[k] = (l_, u_) if v[k] > 0 else (-u_, -l_)
    return Box(lo, hi)


def summary(
    source,
    box: Box | None = None,
    *,
    contacts=None,
    margin: float = 0.0,
    min_contacts: int = MIN_CONTACTS,
    device=None,
) -> dict:
    """The measures of a simulation's current state in ``box``, as plain numbers (for summary.json).

    Keys: ``box``; ``packing_fraction`` (exact); ``contact_types`` (counts of the contacts with
    their point in the box, by the overlap's shape) and ``contact_features`` (the same by the
    features, :func:`classify_contacts`); ``coordination`` (:meth:`Coordination.to_dict`, over the counted
    grains with their centre in the box); ``fabric`` (3x3, pair contacts in the box);
    ``stress`` (3x3 [Pa], Love-Weber); ``mean_normal_force`` [N] of the pair contacts in the box.
    ``box`` defaults to the box around the free grains, moved in by ``margin`` grain sizes.
    ``source`` is a :class:`polydem.Simulation` or :class:`Grains` (then give ``contacts``, and
    ``device`` for the pair geometry).
    """
    g = _grains(source)
    if box is None:
        box = Box.around(g)
        if margin:
            box = box.shrunk(float(margin) * g.grain_size())
    c = _contacts(source, contacts)
    if device is None and hasattr(source, "model"):
        device = source.model.device
    types = classify_contacts(g, c, device=device)
    features = replace(types, kind=classify_features(types.feature_a, types.feature_b), method="features")
    in_box = box.contains(c["point"])
    centred = Grains(g.shapes, g.body_shape, g.position, g.orientation, g.counted & box.contains(g.position), g.free,
                     g.plane_normal, g.plane_offset)  # fmt: skip
    coord = coordination(centred, c, types, min_contacts=min_contacts)
    pairs = in_box & (c["body_b"] >= 0)
    return {
        "box": box.to_dict(),
        "packing_fraction": packing_fraction(g, box),
        "contact_types": types.counts(in_box),
        "contact_features": features.counts(in_box),
        "coordination": coord.to_dict(),
        "fabric": fabric(c, select=in_box).tolist() if pairs.any() else None,
        "stress": stress(g, box, c).tolist(),
        "mean_normal_force": float(np.mean(c["normal_force"][pairs])) if pairs.any() else None,
    }
