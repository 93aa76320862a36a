"""Non-convex grains: rigid unions of convex parts.

A :class:`CompoundShape` is a grain made of convex parts (:class:`~polydem.ConvexShape`) that move as
one rigid body. Its mass, centroid and inertia are those of the union of the parts, so parts that
overlap each other count their common volume once: exactly, in float64, by inclusion-exclusion over
the parts' common pieces (each the convex intersection of their half-spaces). Its body frame is the
union's: origin at the union's centroid, axes along its principal axes, like a convex shape's. The
surface drawn (USD, VTK) is the boolean union from manifold3d where parts overlap and that optional
package is installed, else the parts' surfaces together.

Contact: the overlap of two compound grains is taken part by part. Each part pair is clipped
exactly (:mod:`polydem.kernels.geometry`), and the volumes, first moments, S_A and M_A of all part
pairs are summed (moments moved to the grain's centre) before the contact law is applied once. The
energy W(sum V) is then a function of the two poses and the force is its exact gradient. Where the
parts of one grain only touch, the sum is the exact overlap of the two unions. Where parts of one
grain overlap each other, a region of the other grain inside both parts is counted twice, so V
(and the force) is too large there; ``benchmarks/compound_error.py`` measures it against the exact
union. Decompositions that partition the grain (parts that only touch) have no such error.

Drawing and output use the union's surface (:attr:`CompoundShape.vertices` / ``faces``); the contact
uses the parts (:attr:`CompoundShape.parts` and their poses in the grain's frame).
"""

from __future__ import annotations

from os import PathLike

import numpy as np

from polydem.quaternions import quat_from_matrices, quat_from_matrix
from polydem.shapes import ConvexShape, load_mesh, principal_frame

# Parts whose interiors overlap by more than this fraction of the smaller part's size overlap.
_OVERLAP_RTOL = 1e-9
# The most parts a grain may have: each contact clips every pair of parts that can touch.
MAX_PARTS = 64

_EXTRA_HINT = "install the optional dependencies with: pip install 'polydem[compound]'"


class CompoundShapeError(ValueError):
    """A compound shape cannot be built from the parts given (the message says why and what to do)."""


class CompoundShape:
    """A rigid grain made of convex parts; the union of the parts is the grain.

    Array attributes are read-only numpy arrays (float64) in the body frame: origin at the union's
    centroid, axes along its principal axes of inertia (right-handed), sorted so that
    ``inertia[0] <= inertia[1] <= inertia[2]``.

    Attributes:
        name: str, label used in messages and output.
        parts: list of P :class:`~polydem.ConvexShape`, each in its own body frame.
        part_rotation: (P, 3, 3) rotation of each part's frame in the grain's body frame [-].
        part_translation: (P, 3) each part's centroid in the grain's body frame [m].
        part_orientation: (P, 4) quaternions (x, y, z, w) of ``part_rotation``.
        vertices: (nv, 3) vertices of the surface drawn [m] (see the module docstring).
        faces: list of nf int64 triangles of the union's surface, counter-clockwise from outside.
        face_normals: (nf, 3) their unit outward normals [-].
        volume: float, volume of the union [m^3].
        inertia: (3,) principal moments of inertia of the union per unit density [m^5].
        radius: float, largest distance of a part vertex from the centroid [m] (bounding sphere).
        input_transform: (4, 4) body frame -> the frame the parts were given in: ``x_in = R x + t``.
        overlapping: bool, whether some parts overlap each other.
        tolerance: float, the largest of the parts' tolerances [m].
    """

    is_compound = True

    def __init__(self, parts, name: str | None = None):
        """Build a grain from convex parts, each placed in the common input frame by its own
        ``input_transform`` (a part built from points or a mesh in that frame is already in place;
        see :meth:`ConvexShape.placed` to move a primitive)."""
        parts = list(parts)
        if not parts:
            raise CompoundShapeError("a compound shape needs at least one part")
        if len(parts) > MAX_PARTS:
            raise CompoundShapeError(
                f"a compound shape may have at most {MAX_PARTS} parts, got {len(parts)}: decompose with a larger "
                "concavity threshold (fewer, larger parts)"
            )
        for k, p in enumerate(parts):
            if not isinstance(p, ConvexShape):
                raise CompoundShapeError(f"part {k} is a {type(p).__name__}, not a ConvexShape")
        self.name = "compound" if name is None else str(name)
        self.parts = parts
        volume, centre, tensor, self.overlapping = _union_properties(parts)
        rot = principal_frame(tensor)
        union = _surface([_input_mesh(p) for p in parts], self.overlapping)
        self.volume = float(volume)
        self.inertia = _frozen(np.diag(rot.T @ tensor @ rot))
        transform = np.eye(4)
        transform[:3, :3] = rot
        transform[:3, 3] = centre
        self.input_transform = _frozen(transform)
        self.vertices = _frozen((np.asarray(union.vertices, dtype=np.float64) - centre) @ rot)
        tris = np.asarray(union.faces, dtype=np.int64)
        self.faces = [_frozen(t, np.int64) for t in tris]
        self.face_normals = _frozen(np.asarray(union.face_normals, dtype=np.float64) @ rot)
        # x_in = R_p x_p + t_p and x_in = R x_b + t give x_b = R^T R_p x_p + R^T (t_p - t).
        self.part_rotation = _frozen(np.array([rot.T @ p.input_rotation for p in parts]))
        self.part_translation = _frozen(np.array([rot.T @ (p.input_translation - centre) for p in parts]))
        self.part_orientation = _frozen(np.array([quat_from_matrix(r) for r in self.part_rotation]))
        reach = [
            np.linalg.norm(p.vertices @ r.T + t, axis=1).max()
            for p, r, t in zip(parts, self.part_rotation, self.part_translation, strict=True)
        ]
        self.radius = float(max(reach))
        self.tolerance = float(max(p.tolerance for p in parts))

    # ------------------------------------------------------------------ constructors

    @classmethod
    def from_meshes(cls, meshes, name: str | None = None) -> CompoundShape:
        """A grain from convex meshes (trimesh objects or (vertices, faces) pairs) in one frame; each
        part is the convex hull of its mesh."""
        parts = []
        for k, m in enumerate(meshes):
            v = m.vertices if hasattr(m, "vertices") else m[0]
            try:
                parts.append(ConvexShape.from_points(np.asarray(v, dtype=np.float64), name=f"{name or 'part'}[{k}]"))
            except ValueError as exc:
                raise CompoundShapeError(f"part {k}: {exc}") from None
        return cls(parts, name=name)

    @classmethod
    def from_mesh(
        cls,
        mesh,
        name: str | None = None,
        *,
        decompose: str = "coacd",
        threshold: float = 0.05,
        max_parts: int = 16,
        seed: int = 0,
    ) -> CompoundShape:
        """A grain from a non-convex closed mesh (a trimesh object or a file path).

        ``decompose``: "coacd" cuts the mesh into convex parts with CoACD (``threshold`` its
        concavity limit, relative to the mesh's size; ``max_parts`` the most parts; ``seed`` its
        random seed, for a repeatable result); "components" takes the convex hull of each connected
        piece of the mesh (a mesh that already is a set of convex pieces).
        """
        if isinstance(mesh, str | PathLike):
            mesh = load_mesh(mesh)
        if decompose == "components":
            pieces = mesh.split(only_watertight=False)
            if len(pieces) == 0:
                raise CompoundShapeError("the mesh has no connected pieces")
            grain = cls.from_meshes(pieces, name=name)
            _warn_non_convex_pieces(pieces, grain.parts, name)
            return grain
        if decompose != "coacd":
            raise CompoundShapeError(f"decompose must be 'coacd' or 'components', got {decompose!r}")
        if not 0.0 < float(threshold) <= 1.0:
            raise CompoundShapeError(f"threshold must be in (0, 1], got {threshold!r} (CoACD's default: 0.05)")
        if not (isinstance(max_parts, int) and 1 <= max_parts <= MAX_PARTS):
            raise CompoundShapeError(f"max_parts must be an integer from 1 to {MAX_PARTS}, got {max_parts!r}")
        try:
            import coacd
        except ImportError:
            raise CompoundShapeError(f"decompose = 'coacd' needs the coacd package; {_EXTRA_HINT}") from None
        coacd.set_log_level("error")
        cm = coacd.Mesh(np.asarray(mesh.vertices, dtype=np.float64), np.asarray(mesh.faces, dtype=np.int64))
        pieces = coacd.run_coacd(cm, threshold=float(threshold), max_convex_hull=int(max_parts), seed=int(seed))
        return cls.from_meshes([(np.asarray(v), np.asarray(f)) for v, f in pieces], name=name)

    # ------------------------------------------------------------------ the ConvexShape interface

    @property
    def num_parts(self) -> int:
        return len(self.parts)

    @property
    def num_vertices(self) -> int:
        return len(self.vertices)

    @property
    def num_faces(self) -> int:
        return len(self.faces)

    @property
    def max_face_vertices(self) -> int:
        return 3

    @property
    def input_rotation(self) -> np.ndarray:
        return self.input_transform[:3, :3]

    @property
    def input_translation(self) -> np.ndarray:
        return self.input_transform[:3, 3]

    def to_input_frame(self, points) -> np.ndarray:
        """Map (..., 3) body-frame points [m] to the input frame: ``R @ x + t``."""
        return np.asarray(points, dtype=np.float64) @ self.input_rotation.T + self.input_translation

    def to_trimesh(self):
        """The union's surface in the body frame."""
        import trimesh

        return trimesh.Trimesh(vertices=self.vertices.copy(), faces=np.array(self.faces), process=False)

    def part_vertices(self) -> list[np.ndarray]:
        """Each part's vertices in the grain's body frame [m]."""
        return [
            p.vertices @ r.T + t for p, r, t in zip(self.parts, self.part_rotation, self.part_translation, strict=True)
        ]

    def scaled(self, factor: float) -> CompoundShape:
        """New grain scaled by ``factor`` about the input-frame origin (every part scaled)."""
        return CompoundShape([p.scaled(factor) for p in self.parts], name=self.name)

    def __repr__(self) -> str:
        return (
            f"CompoundShape(name={self.name!r}, parts={self.num_parts}, volume={self.volume:.4g} m^3, "
            f"radius={self.radius:.4g} m)"
        )


def is_compound(shape) -> bool:
    """Whether ``shape`` is a :class:`CompoundShape`."""
    return getattr(shape, "is_compound", False)


def convex_parts(shape) -> list[tuple[ConvexShape, np.ndarray, np.ndarray]]:
    """``(part, rotation (3, 3), translation (3,))`` of each convex piece of ``shape`` in its body
    frame: the shape itself with the identity for a convex shape."""
    if is_compound(shape):
        return list(zip(shape.parts, shape.part_rotation, shape.part_translation, strict=True))
    return [(shape, np.eye(3), np.zeros(3))]


def expand_bodies(shapes, body_shape, position, orientation):
    """Bodies with each compound grain replaced by its convex parts, for code that handles convex
    shapes only (the initial-overlap check, the ray caster).

    Args:
        shapes: the shapes bodies refer to (convex or compound); body_shape: (N,) indices into them;
        position: (N, 3) [m]; orientation: (N, 4) quaternions (x, y, z, w).

    Returns:
        ``(convex, part_shape, part_position, part_orientation, owner)``: the convex shapes (those
        of ``shapes`` in order, each compound one's parts in place of it), and per part of a body
        its shape in ``convex``, its pose, and the body it belongs to. Convex bodies are one part.
    """
    from polydem.quaternions import quat_to_matrix

    convex, first, count, rows_r, rows_t = [], [], [], [], []
    for s in shapes:
        first.append(len(convex))
        parts = convex_parts(s)
        count.append(len(parts))
        for part, r, t in parts:
            convex.append(part)
            rows_r.append(r)
            rows_t.append(t)
    first, count = np.array(first, dtype=np.int64), np.array(count, dtype=np.int64)
    sid = np.asarray(body_shape, dtype=np.int64).reshape(-1)
    position = np.asarray(position, dtype=np.float64).reshape(-1, 3)
    orientation = np.asarray(orientation, dtype=np.float64).reshape(-1, 4)
    per = count[sid]
    owner = np.repeat(np.arange(len(sid)), per)
    k = np.arange(len(owner)) - np.repeat(np.cumsum(per) - per, per)
    part = first[sid[owner]] + k
    rot_b = quat_to_matrix(orientation[owner])
    rot_p = np.array(rows_r).reshape(-1, 3, 3)[part]
    pos = position[owner] + np.einsum("pij,pj->pi", rot_b, np.array(rows_t).reshape(-1, 3)[part])
    quat = orientation[owner].copy()
    moved = np.flatnonzero(~np.all(np.isclose(rot_p, np.eye(3), rtol=0.0, atol=0.0), axis=(1, 2)))
    if moved.size:
        quat[moved] = quat_from_matrices(rot_b[moved] @ rot_p[moved])
    return convex, part, pos, quat, owner


# ---------------------------------------------------------------------- helpers


def _warn_non_convex_pieces(pieces, parts, name) -> None:
    """The warning ``ConvexShape.from_mesh`` gives for a non-convex mesh, for the pieces that
    ``decompose = "components"`` takes whole: each becomes its convex hull."""
    import warnings

    from polydem.scene.errors import SceneWarning
    from polydem.shapes import CONVEX_VOLUME_RTOL

    label = f"compound shape {name!r}" if name else "compound shape"
    hint = "use decompose = 'coacd' (CompoundShape.from_mesh(..., decompose='coacd')) to cut it into convex parts"
    for k, (piece, part) in enumerate(zip(pieces, parts, strict=True)):
        if piece.is_watertight:
            volume = abs(float(piece.volume))
            rel = abs(part.volume - volume) / part.volume
            if rel > CONVEX_VOLUME_RTOL:
                what = (
                    f"is not convex: mesh volume {volume:.6g} m^3, convex hull volume {part.volume:.6g} m^3 "
                    f"(relative difference {rel:.3%})"
                )
            else:
                continue
        else:
            what = "is not watertight, so its volume is undefined and its convexity cannot be checked"
        warnings.warn(
            f"{label}: piece {k} of {len(pieces)} of the mesh {what}; decompose = 'components' takes each "
            f"connected piece as its convex hull; {hint}",
            SceneWarning,
            stacklevel=4,
        )


def _frozen(a, dtype=np.float64) -> np.ndarray:
    out = np.array(a, dtype=dtype)
    out.flags.writeable = False
    return out


def _input_mesh(part: ConvexShape):
    m = part.to_trimesh()
    m.apply_transform(part.input_transform)
    return m


def _surface(meshes, overlapping):
    """The union's surface for drawing: the boolean union (manifold3d, float32 inside) where parts
    overlap and the package is there, else the parts' surfaces together (faces where parts meet
    stay inside, unseen)."""
    import trimesh

    if overlapping:
        try:
            import manifold3d  # noqa: F401
        except ImportError:
            return trimesh.util.concatenate(meshes)
        union = trimesh.boolean.union(meshes, engine="manifold")
        if union.is_volume:
            return union
    return trimesh.util.concatenate(meshes)


def _halfspaces(part: ConvexShape) -> np.ndarray:
    """(nf, 4) rows (n, -d) of the part's face planes in the input frame: n.x - d <= 0 inside."""
    rot, t = part.input_rotation, part.input_translation
    normals = part.face_normals @ rot.T
    offsets = part.face_offsets + normals @ t
    return np.column_stack([normals, -offsets])


def _deepest_point(halfspaces: np.ndarray, bound: float):
    """The point inside all half-spaces furthest from their planes, and that distance (a linear
    programme); distance <= 0 where they have no common interior."""
    from scipy.optimize import linprog

    a_ub = np.hstack([halfspaces[:, :3], np.ones((len(halfspaces), 1))])
    res = linprog(
        c=[0.0, 0.0, 0.0, -1.0],
        A_ub=a_ub,
        b_ub=-halfspaces[:, 3],
        bounds=[(None, None)] * 3 + [(None, bound)],
        method="highs",
    )
    if res.status != 0:
        return None, 0.0
    return res.x[:3], -res.fun


def _moments(shape: ConvexShape):
    """(volume, first moment, second-moment tensor about the input origin) per unit density: the
    inertia tensor J = sum over the volume of (|x|^2 E - x x^T)."""
    rot, c = shape.input_rotation, shape.input_translation
    v = shape.volume
    about_centre = rot @ np.diag(shape.inertia) @ rot.T
    return v, v * c, about_centre + v * (np.dot(c, c) * np.eye(3) - np.outer(c, c))


def _union_properties(parts):
    """Volume, centroid, inertia tensor about the centroid (input frame, per unit density) of the
    union of convex parts, exact in float64, and whether any two parts overlap.

    Inclusion-exclusion: the union's moments are the parts' minus those of each pair's common
    piece plus each triple's, and so on; each common piece of convex parts is convex (the
    intersection of their half-spaces), and a set whose pieces do not meet ends the recursion.
    """
    from scipy.spatial import HalfspaceIntersection

    spaces = [_halfspaces(p) for p in parts]
    centres = [p.input_translation for p in parts]
    radii = [p.radius for p in parts]
    vol, first, second = 0.0, np.zeros(3), np.zeros((3, 3))
    overlapping = False

    def add(shape, sign):
        nonlocal vol, first, second
        v, f, s = _moments(shape)
        vol += sign * v
        first += sign * f
        second += sign * s

    def meet(members, space, size):
        # `space`: the half-spaces of the common piece of `members`; extend it by each later part.
        nonlocal overlapping
        for j in range(members[-1] + 1, len(parts)):
            if any(np.linalg.norm(centres[j] - centres[i]) >= radii[i] + radii[j] for i in members):
                continue
            both = np.vstack([space, spaces[j]])
            inner, depth = _deepest_point(both, min(size, radii[j]))
            if inner is None or depth <= _OVERLAP_RTOL * min(size, radii[j]):
                continue
            overlapping = True
            try:
                corners = HalfspaceIntersection(both, inner).intersections
                piece = ConvexShape.from_points(corners)
            except (ValueError, RuntimeError) as exc:  # a sliver below the hull's tolerance
                if depth > 1e-6 * min(size, radii[j]):
                    raise CompoundShapeError(f"cannot intersect parts {[*members, j]}: {exc}") from None
                continue
            add(piece, (-1.0) ** len(members))
            meet([*members, j], both, piece.radius)

    for i, p in enumerate(parts):
        add(p, 1.0)
        meet([i], spaces[i], radii[i])
    if not vol > 0.0:
        raise CompoundShapeError(f"the union of the parts has no volume ({vol:g} m^3)")
    centre = first / vol
    tensor = second - vol * (np.dot(centre, centre) * np.eye(3) - np.outer(centre, centre))
    return vol, centre, 0.5 * (tensor + tensor.T), overlapping


def place(shape: ConvexShape, position=(0.0, 0.0, 0.0), orientation=(0.0, 0.0, 0.0, 1.0)) -> ConvexShape:
    """A copy of a convex shape placed as a part: its input frame rotated by ``orientation`` (a
    quaternion x, y, z, w) and moved by ``position`` [m] in the compound's frame."""
    from polydem.quaternions import quat_to_matrix

    q = np.asarray(orientation, dtype=np.float64)
    norm = np.linalg.norm(q)
    if q.shape != (4,) or not np.isfinite(q).all() or norm == 0.0:
        raise CompoundShapeError(f"orientation must be a non-zero quaternion [x, y, z, w], got {orientation!r}")
    p = np.asarray(position, dtype=np.float64)
    if p.shape != (3,) or not np.isfinite(p).all():
        raise CompoundShapeError(f"position must be [x, y, z] in m, got {position!r}")
    return shape.placed(quat_to_matrix(q / norm), p)
