"""Shapes packed into flat device arrays, as the narrow-phase kernels read them."""

import numpy as np
import warp as wp

from polydem.kernels.geometry import shapes_struct
from polydem.shapes import largest_face_area

PRECISIONS = {"float32": wp.float32, "float64": wp.float64}


def scalar_type(precision):
    """The Warp scalar type for a precision name ("float32" or "float64")."""
    if precision not in PRECISIONS:
        raise ValueError(f"precision must be 'float32' or 'float64', got {precision!r}")
    return PRECISIONS[precision]


class ShapeSet:
    """A list of :class:`~polydem.ConvexShape` packed for the kernels, all in body frames.

    Attributes:
        shape_vert_start: (S+1,) int32, first vertex of each shape in ``vert``.
        shape_face_start: (S+1,) int32, first face of each shape in ``face_plane``.
        shape_radius: (S,) bounding radius about the centroid [m].
        shape_face_area: (S,) largest face area [m^2] (of a compound grain: the largest of its parts').
        face_plane: (F,) vec4 ``(nx, ny, nz, d)``, outward unit normal and offset, n.x = d [m].
        face_sphere: (F,) vec4 ``(cx, cy, cz, r)``, a sphere around the face's vertices [m].
        face_loop_start: (F+1,) int32, first entry of each face in ``face_loop``.
        face_loop: (L,) int32, global vertex indices of each face, counter-clockwise from outside.
        vert: (V,) vec3 vertex positions [m].
        face_internal: (F,) int32, 1 for a face inside its grain: a compound grain's part face lying
            wholly on a sibling part's face with the opposite normal (a cut plane), or a face a convex
            shape marks in its ``internal_faces`` (bool per face). A coincident face of another body
            there is the union's boundary: it takes the whole shared region, the internal face none.
        shape_part_start: (S+1) int32, first part of each shape in ``part_shape``.
        part_shape: (P,) int32, the convex shape (an index in this set) of each part.
        part_q: (P,) float64 transform, each part's pose in its grain's body frame ([m] and a
            quaternion). A convex shape is one part, itself at the identity; a
            :class:`~polydem.compound.CompoundShape` has an entry without faces (its bounding
            radius only) and its parts follow the shapes given, as convex entries of their own.
        compound: whether any shape is compound (the kernels then take the variant that loops over parts).
        face_plane64, vert64: ``face_plane`` and ``vert`` in float64 whatever the precision: the
            geometry sets a pair up in float64 from them, so float32 contacts see the same bodies
            as float64 ones (a size of 0.018 m is 4e-10 m off in float32, 4% of a 1e-8 m depth).
        arrays: all of the above in one ``wp.struct`` (:func:`polydem.kernels.geometry.shapes_struct`).
    """

    ARRAYS = (
        "shape_vert_start",
        "shape_face_start",
        "shape_radius",
        "shape_face_area",
        "face_plane",
        "face_sphere",
        "face_loop_start",
        "face_loop",
        "face_internal",
        "vert",
        "face_plane64",
        "vert64",
        "shape_part_start",
        "part_shape",
        "part_q",
    )

    def __init__(self, shapes, device=None, precision="float32", packed=()):
        """``packed``: the cells of mesh walls (:class:`~polydem.meshwall.MeshCells`), shapes of their own
        after ``shapes``, taken from their packed arrays (no object per cell)."""
        from polydem.compound import is_compound

        shapes = list(shapes)
        packed = list(packed)
        if not shapes:
            raise ValueError("a ShapeSet needs at least one shape")
        self.shapes = shapes
        self.compound = any(is_compound(s) for s in shapes)
        n_packed = sum(c.num_cells for c in packed)
        # Every convex entry: the shapes given (a compound one as an empty entry), the packed cells, then
        # the compound shapes' parts.
        entries = list(shapes)
        internal = [None] * len(entries)
        part_start, part_shape, part_q = [0], [], []
        for k, shape in enumerate(shapes):
            if is_compound(shape):
                for part, t, q, inside in zip(
                    shape.parts, shape.part_translation, shape.part_orientation, internal_part_faces(shape), strict=True
                ):
                    part_shape.append(len(entries) + n_packed)
                    part_q.append(np.concatenate([t, q]))
                    entries.append(part)
                    internal.append(inside)
            else:
                part_shape.append(k)
                part_q.append(np.array([0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 1.0]))
            part_start.append(len(part_shape))
        part_shape += range(len(shapes), len(shapes) + n_packed)
        part_q += [np.array([0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 1.0])] * n_packed
        part_start += range(part_start[-1] + 1, part_start[-1] + 1 + n_packed)
        convex = [s for s in entries if not is_compound(s)]
        self.precision = precision
        self.scalar = scalar_type(precision)
        self.device = wp.get_device(device)
        np_scalar = np.float32 if self.scalar == wp.float32 else np.float64
        vec3 = wp.types.vector(3, self.scalar)
        vec4 = wp.types.vector(4, self.scalar)

        vert_start = [0]
        face_start = [0]
        loop_start = [0]
        loops, verts, planes, spheres, inside = [], [], [], [], []
        radii, areas = [], []

        def add(shape, marked):
            radii.append(np.array([shape.radius]))
            areas.append(np.array([largest_face_area(shape)]))
            if is_compound(shape):
                vert_start.append(vert_start[-1])
                face_start.append(face_start[-1])
                return
            base = vert_start[-1]
            verts.append(np.asarray(shape.vertices, dtype=np.float64))
            for loop in shape.faces:
                loops.append(np.asarray(loop, dtype=np.int64) + base)
                loop_start.append(loop_start[-1] + len(loop))
            planes.append(np.column_stack([shape.face_normals, shape.face_offsets]))
            if marked is None:
                marked = getattr(shape, "internal_faces", None)
            inside.append(np.zeros(len(shape.faces), bool) if marked is None else np.asarray(marked, bool))
            spheres.append(np.column_stack([shape.face_centers, shape.face_radii]))
            vert_start.append(base + len(shape.vertices))
            face_start.append(face_start[-1] + len(shape.faces))

        def add_cells(cells):
            base = vert_start[-1]
            nf, nloop = np.diff(cells.cell_face_start), np.diff(cells.face_loop_start)
            loop_cell = np.repeat(np.repeat(np.arange(cells.num_cells), nf), nloop)
            loops.append(cells.face_loop + base + cells.cell_vert_start[loop_cell])
            loop_start.extend((loop_start[-1] + cells.face_loop_start[1:]).tolist())
            verts.append(cells.cell_vertices)
            planes.append(cells.face_planes)
            inside.append(np.zeros(len(nloop), bool))
            spheres.append(cells.face_spheres())
            vert_start.extend((base + cells.cell_vert_start[1:]).tolist())
            face_start.extend((face_start[-1] + cells.cell_face_start[1:]).tolist())
            radii.append(cells.cell_radius)
            areas.append(cells.largest_face_areas())

        for shape, marked in zip(entries[: len(shapes)], internal[: len(shapes)], strict=True):
            add(shape, marked)
        for cells in packed:
            add_cells(cells)
        for shape, marked in zip(entries[len(shapes) :], internal[len(shapes) :], strict=True):
            add(shape, marked)

        # The culling spheres are padded so that rounding in the float32 tests cannot cull a face
        # that touches.
        spheres = np.concatenate(spheres)
        radii = np.concatenate(radii)
        areas = np.concatenate(areas)
        spheres[:, 3] *= 1.0 + 1e-5
        spheres[:, 3] += 1e-6 * radii.max()

        def arr(a, dtype):
            return wp.array(a, dtype=dtype, device=self.device)

        self.shape_vert_start = arr(np.array(vert_start, dtype=np.int32), int)
        self.shape_face_start = arr(np.array(face_start, dtype=np.int32), int)
        self.shape_radius = arr(radii.astype(np_scalar), self.scalar)
        self.shape_face_area = arr(areas.astype(np_scalar), self.scalar)
        self.face_plane = arr(np.concatenate(planes).astype(np_scalar), vec4)
        self.face_sphere = arr(spheres.astype(np_scalar), vec4)
        self.face_loop_start = arr(np.array(loop_start, dtype=np.int32), int)
        self.face_loop = arr(np.concatenate(loops).astype(np.int32), int)
        self.face_internal = arr(np.concatenate(inside).astype(np.int32), int)
        self.vert = arr(np.concatenate(verts).astype(np_scalar), vec3)
        self.shape_part_start = arr(np.array(part_start, dtype=np.int32), int)
        self.part_shape = arr(np.array(part_shape, dtype=np.int32), int)
        self.part_q = arr(np.array(part_q, dtype=np.float64), wp.types.transformation(wp.float64))
        self.num_entries = len(radii)
        if self.scalar == wp.float64:
            self.face_plane64 = self.face_plane
            self.vert64 = self.vert
        else:
            self.face_plane64 = arr(np.concatenate(planes), wp.types.vector(4, wp.float64))
            self.vert64 = arr(np.concatenate(verts), wp.types.vector(3, wp.float64))
        # The same arrays as one kernel argument (the ``shapes`` of the geometry functions).
        self.arrays = shapes_struct(self.scalar)()
        for name in self.ARRAYS:
            setattr(self.arrays, name, getattr(self, name))

        max_face_verts = max(
            [s.max_face_vertices for s in convex] + [int(np.diff(c.face_loop_start).max()) for c in packed]
        )
        max_faces = max([s.num_faces for s in convex] + [int(np.diff(c.cell_face_start).max()) for c in packed])
        # Clipping a convex polygon by k planes adds at most one vertex per plane.
        self.max_poly_bound = max_face_verts + max_faces
        # Pieces met in practice are far below the bound for shapes with many faces; start small
        # and let an overflow grow the buffer (see kernels.narrowphase.launch_overlap).
        self.default_poly_capacity = min(self.max_poly_bound, max_face_verts + 16)
        self.max_faces = max_faces

    def kernel_args(self):
        """The shape arguments of the geometry kernels: one ``shapes`` struct."""
        return [self.arrays]


# Two part faces lie on one cut plane when their normals are opposite within this and their planes within
# this share of the grain's bounding radius; the face is inside when the other covers all but this share of it.
CUT_PLANE_COS = 1.0 - 1.0e-9
CUT_PLANE_TOL = 1.0e-9
CUT_COVER = 1.0e-6


def _clip_polygon(poly: np.ndarray, a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """The part of the convex 2D polygon ``poly`` left of the directed line a -> b (Sutherland-Hodgman)."""
    if len(poly) == 0:
        return poly
    edge = b - a
    side = edge[0] * (poly[:, 1] - a[1]) - edge[1] * (poly[:, 0] - a[0])
    out = []
    for i in range(len(poly)):
        j = (i + 1) % len(poly)
        if side[i] >= 0.0:
            out.append(poly[i])
        if (side[i] >= 0.0) != (side[j] >= 0.0):
            t = side[i] / (side[i] - side[j])
            out.append(poly[i] + t * (poly[j] - poly[i]))
    return np.array(out).reshape(-1, 2)


def _area(poly: np.ndarray) -> float:
    if len(poly) < 3:
        return 0.0
    x, y = poly[:, 0], poly[:, 1]
    return 0.5 * abs(float(np.dot(x, np.roll(y, -1)) - np.dot(y, np.roll(x, -1))))


def internal_part_faces(compound) -> list[np.ndarray]:
    """Per part of a compound grain, which of its faces lie inside the grain: on a cut plane, wholly covered
    by a face of a sibling part with the opposite normal (a grain cut in two, a convex decomposition). A
    face only partly covered is not marked (the shared region is then split half to each body, as for any
    coincident face)."""
    placed = []
    for part, rot, t in zip(compound.parts, compound.part_rotation, compound.part_translation, strict=True):
        v = np.asarray(part.vertices) @ np.asarray(rot).T + t
        n = np.asarray(part.face_normals) @ np.asarray(rot).T
        placed.append(
            (v, [np.asarray(f) for f in part.faces], n, np.einsum("ij,ij->i", n, v[[f[0] for f in part.faces]]))
        )
    tol = CUT_PLANE_TOL * compound.radius
    marks = [np.zeros(len(p[1]), bool) for p in placed]
    for k, (vk, fk, nk, dk) in enumerate(placed):
        for l_, (vl, fl, nl, dl) in enumerate(placed):
            if l_ == k:
                continue
            for i, fi in enumerate(fk):
                if marks[k][i]:
                    continue
                for j, fj in enumerate(fl):
                    if nk[i] @ nl[j] > -CUT_PLANE_COS or abs(dk[i] + dl[j]) > tol:
                        continue
                    # Both polygons in face i's plane, counter-clockwise about n_i.
                    u = vk[fi[1]] - vk[fi[0]]
                    u /= np.linalg.norm(u)
                    w = np.cross(nk[i], u)
                    pi = np.column_stack([vk[fi] @ u, vk[fi] @ w])
                    pj = np.column_stack([vl[fj] @ u, vl[fj] @ w])[::-1]  # opposite normal: reverse its order
                    cut = pi
                    for m in range(len(pj)):
                        cut = _clip_polygon(cut, pj[m], pj[(m + 1) % len(pj)])
                    area = _area(pi)
                    if area > 0.0 and _area(cut) >= (1.0 - CUT_COVER) * area:
                        marks[k][i] = True
                        break
    return marks
