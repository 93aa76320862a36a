"""Flat patches of a mesh wall's cells joined into fewer, larger convex cells.

A flat region of many triangles is solid behind it like one slab, but cut into one cell per triangle it
costs a grain one clipping per cell it reaches: on a floor of triangles twice a grain's size, four to six.
Where the cells of coplanar neighbouring triangles together form a convex solid (the union's convex hull
has the union's volume), they become one cell: the planes of that hull, each one of the member cells'
own planes. A grain's overlap with the joined cell is its overlap with the members together, so V, S_A
and M_A are the same sums (to rounding, not bit for bit) and the wall acts as before; it only clips fewer
cells.

A flat patch whose cells are not convex together (an L-shaped floor, a floor with a hole) keeps one
cell per triangle: cutting it into convex parts is not done yet. Each patch costs a convex hull (0.2 to
2 ms), so patches of fewer than MIN_PATCH cells (the quads of two triangles of a cylinder's side or a
box's face) are left as they are; a patch that cannot be a convex polygon of few enough corners in its
plane (a disc's fan) is turned down by a test in 2-D before its hull.
A joined cell may have no more faces, nor more vertices on a face, than the wall's own cells or a box
(6 faces of 4 corners), so that joining raises the polygon capacity of the contact kernels
(:class:`polydem.shapeset.ShapeSet`) at most to what a box needs. Only exactly coplanar triangles join
(within the cells' tolerance): triangles of a float32 file (STL) bent by rounding stay apart.
"""

from __future__ import annotations

import numpy as np

from polydem.meshwall import CELL_TOLERANCE, TRIANGLE, MeshCells, edge_pairs, ragged

# The fewest cells of a patch that are joined: a convex hull costs 0.2-2 ms in Python, so a mesh of many
# quads (two triangles each, a cylinder's side) would take seconds per thousand; they keep their two cells.
MIN_PATCH = 3
# A hull facet's normal within this of a member plane's (1 - cos) is that plane.
_SAME_NORMAL = 1e-9
# Hulls of more triangles than this cannot fit the face limits: not joined.
_MAX_HULL_FACETS = 256


def cell_volumes(face_planes, face_areas, cell_face_start) -> np.ndarray:
    """(C,) each cell's volume [m^3] by the divergence theorem: a third of the sum of offset x area."""
    return np.add.reduceat(face_planes[:, 3] * face_areas, cell_face_start[:-1]) / 3.0


def flat_neighbours(cells, f1, f2, tol) -> tuple[np.ndarray, np.ndarray]:
    """``(r1, r2)``: the rows of the cells of triangles ``f1`` and ``f2`` (that share an edge) where both
    have a cell and lie behind the same plane."""
    tri = np.flatnonzero(cells.cell_kind == TRIANGLE)
    row = np.full(len(cells.faces), -1, dtype=np.int64)
    row[cells.cell_source[tri, 0]] = tri
    r1, r2 = row[f1], row[f2]
    both = (r1 >= 0) & (r2 >= 0)
    r1, r2 = r1[both], r2[both]
    f1, f2 = cells.cell_front[r1], cells.cell_front[r2]
    same = (np.abs(f1[:, :3] - f2[:, :3]).max(axis=1) <= _SAME_NORMAL) & (np.abs(f1[:, 3] - f2[:, 3]) <= tol)
    return r1[same], r2[same]


def join_flat_cells(cells):
    """``cells`` (:class:`polydem.meshwall.MeshCells`, one per triangle, as
    :func:`~polydem.meshwall.build_cells` makes them) with each flat patch's cells joined into one where
    they are convex together (see the module docstring): the cells left as they were first, in their
    order, then the joined ones (``cell_source`` names a joined cell's first triangle). Returns ``cells``
    itself where nothing joins."""
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components

    v, f = cells.vertices, cells.faces
    diag = float(np.linalg.norm(v.max(axis=0) - v.min(axis=0)))
    tol = CELL_TOLERANCE * max(cells.thickness, diag * 1e-3)  # as the cells were built to
    f1, _, f2, _, _ = edge_pairs(f, cells.label)
    r1, r2 = flat_neighbours(cells, f1, f2, tol)
    if not len(r1):
        return cells
    n = cells.num_cells
    graph = coo_matrix((np.ones(len(r1)), (r1, r2)), shape=(n, n)).tocsr()
    count, label = connected_components(graph, directed=False)
    sizes = np.bincount(label, minlength=count)
    joiner = _Joiner(cells, tol)
    joined = []
    # Each patch's cells at once (a scan of every label per patch would cost patches x cells).
    by_patch = np.split(np.argsort(label, kind="stable"), np.cumsum(sizes)[:-1])
    for patch in (by_patch[c] for c in np.flatnonzero(sizes >= MIN_PATCH)):
        cell = joiner.hull_cell(patch)
        if cell is not None:
            joined.append((patch, cell))
    if not joined:
        return cells
    return _rebuild(cells, joined)


class _Joiner:
    """The world planes, vertices and volumes of the cells, and the face limits of a joined cell."""

    def __init__(self, cells, tol):
        self.cells, self.tol = cells, tol
        self.planes, _ = cells.world_planes()
        counts = np.diff(cells.cell_vert_start)
        row, _ = ragged(counts)
        self.points = cells.cell_vertices + cells.cell_center[row]
        self.volumes = cell_volumes(cells.face_planes, cells.face_areas(), cells.cell_face_start)
        self.max_faces = max(6, int(np.diff(cells.cell_face_start).max()))
        self.max_face_vertices = max(4, int(np.diff(cells.face_loop_start).max()))

    def plausible(self, rows) -> bool:
        """Whether the triangles of the cells ``rows`` make a convex polygon of few enough corners, in their
        plane (a cheap test in 2-D that spares the 3-D hull of a large patch that cannot join)."""
        if len(rows) <= 2:
            return True
        from scipy.spatial import ConvexHull, QhullError

        c = self.cells
        tri = c.faces[c.cell_source[rows, 0]]
        normal = c.cell_front[rows[0], :3]
        u = np.cross(normal, np.eye(3)[int(np.argmin(np.abs(normal)))])
        u /= np.linalg.norm(u)
        w = np.cross(normal, u)
        corners = np.unique(tri)
        flat = c.vertices[corners] @ np.column_stack([u, w])
        try:
            hull = ConvexHull(flat)
        except QhullError:
            return False
        if len(hull.vertices) > self.max_face_vertices + 2:  # a margin for corners on its sides
            return False
        a, b, d = (c.vertices[tri[:, k]] for k in range(3))
        area = 0.5 * np.linalg.norm(np.cross(b - a, d - a), axis=1).sum()
        return abs(hull.volume - area) <= 1e-9 * area + self.tol * hull.area

    def hull_cell(self, rows):
        """The convex cell that is the union of the cells ``rows``, as ``(points, rings, planes)`` in the
        mesh frame (each face's corners as indices into the points, counter-clockwise from outside);
        None where the union is not convex or the cell would exceed the face limits."""
        from scipy.spatial import ConvexHull, QhullError

        if not self.plausible(rows):
            return None
        vs = self.cells.cell_vert_start
        row, col = ragged(vs[rows + 1] - vs[rows])
        pts = self.points[vs[rows][row] + col]
        # The members' shared corners once, mostly (copies apart by rounding that straddle a step of the grid
        # stay two; the hull and the rings take either).
        _, first = np.unique(np.round(pts / self.tol), axis=0, return_index=True)
        pts = pts[np.sort(first)]
        try:
            hull = ConvexHull(pts)
        except QhullError:
            return None
        # The union lies inside its hull: it is the hull where their volumes agree to a skin of the tolerance
        # over the hull's surface, both ways (members that overlap, at a fold of the mesh, sum to more).
        excess = hull.volume - float(self.volumes[rows].sum())
        if abs(excess) > self.tol * hull.area or len(hull.simplices) > _MAX_HULL_FACETS:
            return None
        fs = self.cells.cell_face_start
        row, col = ragged(fs[rows + 1] - fs[rows])
        planes = self.planes[fs[rows][row] + col]
        # Each facet is one of the members' planes (the first that matches it); coplanar facets make one face.
        eq = hull.equations
        match = (1.0 - eq[:, :3] @ planes[:, :3].T <= _SAME_NORMAL) & (
            np.abs(eq[:, 3, None] + planes[None, :, 3]) <= self.tol
        )
        if not match.any(axis=1).all():
            return None
        rows_used, facet_face = np.unique(match.argmax(axis=1), return_inverse=True)
        used = planes[rows_used]
        # Members' planes that coincide (two cells' fronts) are one face.
        same = (1.0 - used[:, :3] @ used[:, :3].T <= _SAME_NORMAL) & (
            np.abs(used[:, 3, None] - used[None, :, 3]) <= self.tol
        )
        first = same.argmax(axis=1)
        keep, face_of = np.unique(first, return_inverse=True)
        if len(keep) > self.max_faces:
            return None
        used = used[keep]
        facet_face = face_of[facet_face]
        rings = []
        for k in range(len(used)):
            idx = np.unique(hull.simplices[facet_face == k])
            if np.abs(pts[idx] @ used[k, :3] - used[k, 3]).max() > self.tol:
                return None
            ring = idx[_polygon(pts[idx], used[k, :3], self.tol)]
            if len(ring) > self.max_face_vertices:
                return None
            rings.append(ring)
        return pts, rings, used


def _cross(a, b):
    """Row-wise cross products of (n, 3) arrays (np.cross costs more on small arrays)."""
    return a[:, [1, 2, 0]] * b[:, [2, 0, 1]] - a[:, [2, 0, 1]] * b[:, [1, 2, 0]]


def _polygon(points, normal, tol) -> np.ndarray:
    """The indices of the corners of the convex polygon ``points`` (on a plane of unit ``normal``),
    counter-clockwise seen from the side ``normal`` points to; points on its sides (within ``tol``) left out."""
    rel = points - points.mean(axis=0)
    u = rel[np.argmax(np.einsum("ij,ij->i", rel, rel))]
    u = u / np.sqrt(u @ u)
    w = _cross(normal[None], u[None])[0]
    ring = np.argsort(np.arctan2(rel @ w, rel @ u), kind="stable")
    while len(ring) > 3:
        p = rel[ring]
        prev, nxt = p[np.arange(-1, len(p) - 1)], p[np.r_[1 : len(p), 0]]
        chord = nxt - prev
        # How far each corner stands off the chord between its neighbours.
        off = np.sqrt(np.einsum("ij,ij->i", *(2 * (_cross(chord, p - prev),))))
        off /= np.maximum(np.sqrt(np.einsum("ij,ij->i", chord, chord)), 1e-300)
        k = int(np.argmin(off))
        if off[k] > tol:
            break
        ring = np.delete(ring, k)
    return ring


def _rebuild(cells, joined):
    """MeshCells with the members of each joined cell replaced by it: the cells left as they were first,
    in their order, then the joined ones."""
    gone = np.zeros(cells.num_cells, bool)
    for rows, _ in joined:
        gone[rows] = True
    keep = np.flatnonzero(~gone)
    vs, fs, ls = cells.cell_vert_start, cells.cell_face_start, cells.face_loop_start
    nv, nf = np.diff(vs)[keep], np.diff(fs)[keep]
    row, col = ragged(nv)
    verts = [cells.cell_vertices[vs[keep][row] + col]]
    row, col = ragged(nf)
    face = fs[keep][row] + col
    planes = [cells.face_planes[face]]
    nloop = [np.diff(ls)[face]]
    row, col = ragged(nloop[0])
    loops = [cells.face_loop[ls[face][row] + col]]
    center, radius = [cells.cell_center[keep]], [cells.cell_radius[keep]]
    front, kind, source = [cells.cell_front[keep]], [cells.cell_kind[keep]], [cells.cell_source[keep]]
    lower, upper = [cells.lower[keep]], [cells.upper[keep]]
    nv, nf = [nv], [nf]
    for rows, (pts, rings, used) in joined:
        first = int(rows.min())
        ids, index = np.unique(np.concatenate(rings), return_inverse=True)
        corners = pts[ids]
        mid = corners.mean(axis=0)
        local = corners - mid
        p = used.copy()
        p[:, 3] -= p[:, :3] @ mid
        verts.append(local)
        planes.append(p)
        sizes = np.array([len(r) for r in rings])
        nloop.append(sizes)
        loops.append(index.reshape(-1))
        center.append(mid[None])
        radius.append([float(np.linalg.norm(local, axis=1).max())])
        front.append(cells.cell_front[first][None])
        kind.append(cells.cell_kind[first][None])
        source.append(cells.cell_source[first][None])
        lower.append(corners.min(axis=0)[None])
        upper.append(corners.max(axis=0)[None])
        nv.append([len(corners)])
        nf.append([len(rings)])
    nv, nf, nloop = np.concatenate(nv), np.concatenate(nf), np.concatenate(nloop)
    return MeshCells(
        vertices=cells.vertices,
        faces=cells.faces,
        lower=np.concatenate(lower),
        upper=np.concatenate(upper),
        nonmanifold_edges=cells.nonmanifold_edges,
        thickness=cells.thickness,
        cell_center=np.concatenate(center),
        cell_radius=np.concatenate(radius).astype(np.float64),
        cell_front=np.concatenate(front),
        cell_kind=np.concatenate(kind),
        cell_source=np.concatenate(source),
        cell_vert_start=np.r_[0, np.cumsum(nv)],
        cell_vertices=np.concatenate(verts),
        cell_face_start=np.r_[0, np.cumsum(nf)],
        face_planes=np.concatenate(planes),
        face_loop_start=np.r_[0, np.cumsum(nloop)],
        face_loop=np.concatenate(loops).astype(np.int64),
        label=cells.label,
    )
