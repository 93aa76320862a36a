"""Triangle-mesh walls: the convex cells that turn a triangle mesh into a solid the contact model can clip.

A mesh wall is solid *behind* its triangles (against their normals, counter-clockwise winding seen
from the front) to a depth ``thickness``. The solid is cut into one convex **cell** per triangle:

* the triangle's plane (front), a plane ``thickness`` behind it (back), and
* through each edge, the plane that bisects the dihedral angle between the two triangles that share
  it (at an edge of one triangle only, the plane through the edge perpendicular to the triangle).

Neighbouring cells share their bisector plane with opposite normals, so the cells tile the solid
without gaps or overlaps near the surface: at a flat region the bisectors stand perpendicular to it,
at a concave crease (a valley seen from the grains) the cells widen behind the surface, at a convex
edge (a ridge) they narrow. A grain's overlap with the wall is the sum of its exact overlaps with the
cells it touches, and the contact law is applied once to that sum (kernels/meshwall.py), so the
energy is W(V) of the grain's overlap with the solid itself: a flat region of many triangles acts
exactly like one plane, and no edge or vertex of the mesh adds a force of its own. See the README
("Triangle-mesh walls") for what this means at creases and where it stops being exact.
"""

from __future__ import annotations

import functools
import itertools
from dataclasses import dataclass

import numpy as np

# Edges shorter than this fraction of the mesh's bounding diagonal, and triangles of smaller area
# (relative to the diagonal squared), are degenerate: their normals are noise.
DEGENERATE = 1e-10
# Two triangles whose dihedral angle differs from flat by less than this [rad] are coplanar: a file
# in float32 (STL) leaves planar quads bent by about 1e-7.
FLAT = 1e-6


class MeshWallError(ValueError):
    """A mesh that cannot be a wall (open edges shared by three faces, inconsistent winding, ...)."""


@dataclass
class CellShape:
    """One convex cell in its own frame (centred on its vertices' mean), in the form
    :class:`~polydem.shapeset.ShapeSet` packs (see :class:`~polydem.shapes.ConvexShape`)."""

    name: str
    vertices: np.ndarray
    faces: list
    face_normals: np.ndarray
    face_offsets: np.ndarray
    face_centers: np.ndarray
    face_radii: np.ndarray
    radius: float
    center: np.ndarray  # (3,) the cell frame's origin in the mesh frame [m]
    # (4,) the plane (normal, offset) of the triangle the cell lies behind, in the mesh frame;
    # zeros for the cells of concave edges and corners.
    front: np.ndarray = None

    @property
    def num_faces(self) -> int:
        return len(self.faces)

    @property
    def max_face_vertices(self) -> int:
        return max(len(f) for f in self.faces)


def triangle_normals(vertices: np.ndarray, faces: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Unit normals (right-hand rule) and areas of the triangles ``faces`` of ``vertices``."""
    tri = vertices[faces]
    cross = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    twice = np.linalg.norm(cross, axis=1)
    with np.errstate(invalid="ignore", divide="ignore"):
        normals = cross / twice[:, None]
    return normals, 0.5 * twice


def clean_triangles(vertices, faces, label="mesh"):
    """Merged vertices and the non-degenerate triangles of a triangle soup.

    Returns ``(vertices, faces)``: float64 (nv, 3) and int64 (nf, 3). Raises MeshWallError when
    nothing is left.
    """
    v = np.asarray(vertices, dtype=np.float64)
    f = np.asarray(faces, dtype=np.int64)
    if v.ndim != 2 or v.shape[1] != 3 or len(v) < 3:
        raise MeshWallError(f"{label} needs at least 3 vertices of 3 coordinates, got shape {v.shape}")
    if f.ndim != 2 or f.shape[1] != 3 or len(f) == 0:
        raise MeshWallError(f"{label} needs triangles (an (n, 3) index array), got shape {f.shape}")
    if not np.all(np.isfinite(v)):
        raise MeshWallError(f"{label} has non-finite vertex coordinates")
    if f.min() < 0 or f.max() >= len(v):
        raise MeshWallError(f"{label} has triangle indices outside its {len(v)} vertices")
    diag = float(np.linalg.norm(v.max(axis=0) - v.min(axis=0)))
    if diag == 0.0:
        raise MeshWallError(f"{label} has all its vertices at one point")
    # Merge vertices closer than the degenerate length, so that the adjacency is found even in
    # STL files, which repeat every vertex per triangle.
    q = np.round(v / (DEGENERATE * 1e3 * diag)).astype(np.int64)
    _, first, inverse = np.unique(q, axis=0, return_index=True, return_inverse=True)
    v = v[first]
    f = inverse.reshape(-1)[f]
    _, area = triangle_normals(v, f)
    keep = (area > DEGENERATE * diag * diag) & (f[:, 0] != f[:, 1]) & (f[:, 1] != f[:, 2]) & (f[:, 2] != f[:, 0])
    f = f[keep]
    if len(f) == 0:
        raise MeshWallError(f"{label} has no triangle of non-zero area")
    # Drop exact duplicates (the same triangle twice, in either winding, would be a zero-thickness solid).
    _, uniq = np.unique(np.sort(f, axis=1), axis=0, return_index=True)
    f = f[np.sort(uniq)]
    return v, f


def _edge_planes(vertices, faces, normals, label):
    """Per triangle and edge j (from vertex j to j+1): the unit normal and offset of the side plane.

    Raises MeshWallError where two triangles sharing an edge are wound inconsistently.
    """
    a = faces
    b = np.roll(faces, -1, axis=1)
    start, end = vertices[a], vertices[b]
    t = end - start
    t /= np.linalg.norm(t, axis=2, keepdims=True)
    # In-plane outward normal of each edge: the interior lies to the left of a counter-clockwise edge.
    u = np.cross(t, normals[:, None, :])
    u /= np.linalg.norm(u, axis=2, keepdims=True)
    side = u.copy()

    key = np.sort(np.stack([a, b], axis=2).reshape(-1, 2), axis=1)
    _, inverse, counts = np.unique(key, axis=0, return_inverse=True, return_counts=True)
    inverse = inverse.reshape(-1)
    order = np.argsort(inverse, kind="stable")
    edge_of = inverse[order]
    starts = np.searchsorted(edge_of, np.arange(len(counts)))
    pairs = np.flatnonzero(counts == 2)
    first = order[starts[pairs]]
    second = order[starts[pairs] + 1]
    f1, j1 = np.divmod(first, 3)
    f2, j2 = np.divmod(second, 3)
    same_direction = a[f1, j1] == a[f2, j2]
    if np.any(same_direction):
        k = int(np.flatnonzero(same_direction)[0])
        raise MeshWallError(
            f"{label}: triangles {f1[k]} and {f2[k]} share an edge but are wound the same way along it, so "
            f"their normals disagree about which side is solid ({int(same_direction.sum())} such edge(s)); "
            "orient the faces consistently (e.g. trimesh.repair.fix_winding(mesh), then export again)"
        )
    u1 = u[f1, j1]
    u2 = u[f2, j2]
    m = u1 - u2
    norm = np.linalg.norm(m, axis=1)
    # Convex edges (the far vertex of the neighbour behind the triangle's plane) get the bisector;
    # flat and concave ones keep the perpendicular planes, and the gap that the perpendicular
    # planes leave behind a concave edge becomes a cell of its own (see _wedge_cells).
    far2 = vertices[faces[f2, (j2 + 2) % 3]]
    rise = np.einsum("ek,ek->e", normals[f1], far2 - start[f1, j1])
    length = np.linalg.norm(end[f1, j1] - start[f1, j1], axis=1)
    bend = rise / length
    convex = (bend < -FLAT) & (norm > 1e-9)
    m[convex] /= norm[convex, None]
    side[f1[convex], j1[convex]] = m[convex]
    side[f2[convex], j2[convex]] = -m[convex]
    offset = np.einsum("fjk,fjk->fj", side, start)
    nonmanifold = int(np.sum(counts > 2))
    concave = bend > FLAT
    edges = np.column_stack([f1[concave], j1[concave], f2[concave], j2[concave]])
    return side, offset, nonmanifold, edges


@functools.cache
def _triples(k: int) -> np.ndarray:
    return np.array(list(itertools.combinations(range(k), 3)), dtype=np.int64).reshape(-1, 3)


def _polytope(planes: np.ndarray, tol: float):
    """Vertices and counter-clockwise face loops of {x : N x <= d} for a bounded set of planes
    ``(k, 4)``; faces that touch the polytope in fewer than 3 vertices are dropped."""
    # One face per plane: drop repeated planes (a corner's plane can repeat an edge bisector).
    diff = np.abs(planes[:, None, :3] - planes[None, :, :3]).max(axis=2) + np.abs(
        planes[:, None, 3] - planes[None, :, 3]
    )
    same = np.triu(diff <= tol, k=1)
    planes = planes[~same.any(axis=0)]
    idx = _triples(len(planes))
    a = planes[idx, :3]
    det = np.linalg.det(a)
    ok = np.abs(det) > 1e-12
    if not ok.any():
        return None
    x = np.linalg.solve(a[ok], planes[idx[ok], 3][..., None])[..., 0]
    feasible = np.all(x @ planes[:, :3].T <= planes[:, 3] + tol, axis=1)
    x = x[feasible]
    if len(x) < 4:
        return None
    # Merge the copies of a vertex met by more than three planes.
    _, first = np.unique(np.round(x / (4.0 * tol)).astype(np.int64), axis=0, return_index=True)
    verts = x[np.sort(first)]
    if len(verts) < 4:
        return None
    faces, normals, offsets = [], [], []
    for i in range(len(planes)):
        n, d = planes[i, :3], planes[i, 3]
        on = np.flatnonzero(np.abs(verts @ n - d) <= 8.0 * tol)
        if len(on) < 3:
            continue
        c = verts[on].mean(axis=0)
        e1 = verts[on[0]] - c
        e1 /= np.linalg.norm(e1)
        e2 = np.cross(n, e1)
        ang = np.arctan2((verts[on] - c) @ e2, (verts[on] - c) @ e1)
        faces.append(on[np.argsort(ang)])
        normals.append(n)
        offsets.append(d)
    if len(faces) < 4:
        return None
    return verts, faces, np.array(normals), np.array(offsets)


def _vertex_planes(vertices, faces, normals, front_d, tol):
    """Extra side planes of each cell from the triangles that share only a vertex with it.

    Where non-coplanar triangles i and j meet at a vertex, the solid near it is split between them
    by the plane of equal depth behind both (s_i = s_j, s the signed distance to a triangle's plane):
    at a convex meeting (j's centre behind i's plane) i keeps the points nearer its plane (s_i >= s_j).
    This is the edge bisector's rule carried to triangles that meet at a corner only; without it, the
    cells of a face split into two triangles would overlap its neighbours' near the corner. Concave
    meetings need nothing: there the cells stop at their perpendicular planes. The plane is added
    only where both triangles lie wholly on their own side of it (at a saddle they may not: the
    cells are then left as they are).
    Returns a list per triangle of (4,) planes."""
    nf = len(faces)
    extra = [[] for _ in range(nf)]
    by_vertex = {}
    for f, tri in enumerate(faces.tolist()):
        for v in tri:
            by_vertex.setdefault(v, []).append(f)
    seen = set()
    tri_sets = [set(t) for t in faces.tolist()]
    centres = vertices[faces].mean(axis=1)
    for fs in by_vertex.values():
        for a in range(len(fs)):
            for b in range(a + 1, len(fs)):
                i, j = fs[a], fs[b]
                key = (min(i, j), max(i, j))
                if key in seen or len(tri_sets[i] & tri_sets[j]) >= 2:
                    continue  # edge neighbours have their bisector already
                seen.add(key)
                if np.dot(normals[i], normals[j]) > 1.0 - 1e-12:
                    continue  # coplanar: the perpendicular edge planes separate them
                if np.dot(normals[i], centres[j]) - front_d[i] >= 0.0:
                    continue  # concave: the cells stop at the perpendicular planes there
                # Half-space of i: (n_j - n_i).x <= d_j - d_i.
                n = normals[j] - normals[i]
                d = front_d[j] - front_d[i]
                norm = np.linalg.norm(n)
                n, d = n / norm, d / norm
                if np.all(vertices[faces[i]] @ n <= d + tol) and np.all(vertices[faces[j]] @ n >= d - tol):
                    extra[i].append(np.append(n, d))
                    extra[j].append(np.append(-n, -d))
    return extra


def _cell(planes, label, tol) -> CellShape | None:
    poly = _polytope(planes, tol)
    if poly is None:
        return None
    verts, faces, normals, offsets = poly
    c = verts.mean(axis=0)
    local = verts - c
    offsets = offsets - normals @ c
    centers = np.array([local[f].mean(axis=0) for f in faces])
    radii = np.array([np.max(np.linalg.norm(local[f] - centers[i], axis=1)) for i, f in enumerate(faces)])
    return CellShape(
        name=label,
        vertices=local,
        faces=[np.asarray(f, dtype=np.int64) for f in faces],
        face_normals=normals,
        face_offsets=offsets,
        face_centers=centers,
        face_radii=radii,
        radius=float(np.max(np.linalg.norm(local, axis=1))),
        center=c,
    )


@dataclass
class MeshCells:
    """The cells of one mesh wall, in the mesh frame.

    Attributes:
        vertices: (nv, 3) merged vertices of the surface [m] (mesh frame).
        faces: (nf, 3) int64 triangles, counter-clockwise seen from the front (non-solid) side.
        cells: nf :class:`CellShape`, cell k behind triangle k.
        lower, upper: (nf, 3) bounds of each cell in the mesh frame [m].
        nonmanifold_edges: edges shared by more than two triangles (given perpendicular side planes).
        thickness: depth of the solid behind each triangle [m].
    """

    vertices: np.ndarray
    faces: np.ndarray
    cells: list
    lower: np.ndarray
    upper: np.ndarray
    nonmanifold_edges: int
    thickness: float


def build_cells(vertices, faces, thickness: float, label: str = "mesh") -> MeshCells:
    """The convex cells of the solid ``thickness`` [m] deep behind the triangles (see the module docstring)."""
    if not (np.isfinite(thickness) and thickness > 0.0):
        raise MeshWallError(f"{label}: thickness must be a positive length in m, got {thickness!r}")
    v, f = clean_triangles(vertices, faces, label)
    normals, _ = triangle_normals(v, f)
    side, offset, nonmanifold, concave = _edge_planes(v, f, normals, label)
    front_d = np.einsum("fk,fk->f", normals, v[f[:, 0]])
    diag = float(np.linalg.norm(v.max(axis=0) - v.min(axis=0)))
    extra = _vertex_planes(v, f, normals, front_d, 1e-9 * diag)
    cells, lower, upper = [], [], []
    for k in range(len(f)):
        planes = np.empty((5 + len(extra[k]), 4))
        planes[0, :3], planes[0, 3] = normals[k], front_d[k]
        planes[1, :3], planes[1, 3] = -normals[k], -(front_d[k] - thickness)
        planes[2:5, :3] = side[k]
        planes[2:5, 3] = offset[k]
        if extra[k]:
            planes[5:] = extra[k]
        scale = max(thickness, np.max(np.linalg.norm(v[f[k]] - v[f[k]].mean(axis=0), axis=1)))
        cell = _cell(planes, f"{label} cell {k}", 1e-9 * max(scale, diag * 1e-3))
        if cell is None:
            raise MeshWallError(
                f"{label}: the cell behind triangle {k} is empty (its side planes meet before the front); "
                "the mesh folds back on itself there"
            )
        cell.front = planes[0].copy()
        cells.append(cell)
    tol = 1e-9 * max(thickness, diag * 1e-3)
    cells += _wedge_cells(v, f, normals, front_d, concave, thickness, label, tol)
    for cell in cells:
        if cell.front is None:
            cell.front = np.zeros(4)
        world = cell.vertices + cell.center
        lower.append(world.min(axis=0))
        upper.append(world.max(axis=0))
    return MeshCells(v, f, cells, np.array(lower), np.array(upper), nonmanifold, float(thickness))


def _wedge_cells(v, f, normals, front_d, concave, thickness, label, tol):
    """Cells of the solid behind concave edges and corners, which the triangles' prisms leave out.

    Behind a concave edge, between the two triangles' perpendicular planes, lies a wedge of solid
    behind both triangles: one cell, capped by the planes perpendicular to the edge through its
    ends. Where concave edges meet at a vertex whose edges are all concave or flat, the caps leave
    the solid behind every triangle there: one more cell (x - v).t <= 0 for each concave edge t
    leaving the vertex."""
    out = []
    ends = {}
    for f1, j1, f2, _ in concave.tolist():
        a, b = v[f[f1, j1]], v[f[f1, (j1 + 1) % 3]]
        t = (b - a) / np.linalg.norm(b - a)
        u1 = np.cross(t, normals[f1])
        u2 = np.cross(-t, normals[f2])
        planes = [
            np.append(-u1, -u1 @ a),
            np.append(-u2, -u2 @ a),
            np.append(normals[f1], front_d[f1]),
            np.append(normals[f2], front_d[f2]),
            np.append(-normals[f1], -(front_d[f1] - thickness)),
            np.append(-normals[f2], -(front_d[f2] - thickness)),
            np.append(-t, -t @ a),
            np.append(t, t @ b),
        ]
        cell = _cell(np.array(planes), f"{label} edge cell", tol)
        if cell is not None and cell.radius <= 2.0 * (thickness + np.linalg.norm(b - a)):
            out.append(cell)
        for vi, direction in ((f[f1, j1], t), (f[f1, (j1 + 1) % 3], -t)):
            ends.setdefault(int(vi), []).append((direction, f1, f2))
    # Vertices where every non-flat edge is concave.
    normals_f, faces_l = normals, f.tolist()
    for vi, items in ends.items():
        dirs = np.array([d for d, _, _ in items])
        if np.linalg.matrix_rank(dirs, tol=1e-9) < 2:
            continue  # collinear edges through the vertex: their caps meet flush
        faces_here = np.flatnonzero(np.any(f == vi, axis=1))
        x = v[vi]
        if _has_convex_edge(v, faces_l, normals_f, front_d, faces_here, tol * 1e3):
            continue  # a convex edge meets here too (a saddle): left as it is
        planes = [np.append(d, d @ x) for d in dirs]
        planes += [np.append(normals_f[i], front_d[i]) for i in faces_here]
        planes += [np.append(-normals_f[i], -(front_d[i] - thickness)) for i in faces_here]
        cell = _cell(np.array(planes), f"{label} corner cell", tol)
        # A corner whose concave edges do not close the solid around it (they do at the corner of
        # a box's inside) leaves this region unbounded along the surface: no cell there.
        if cell is not None and cell.radius <= 4.0 * thickness:
            out.append(cell)
    return out


def _has_convex_edge(v, faces, normals, front_d, around, tol):
    for i in around:
        for j in around:
            shared = set(faces[i]) & set(faces[j])
            if i != j and len(shared) == 2:
                far = next(k for k in faces[j] if k not in shared)
                if np.dot(normals[i], v[far]) - front_d[i] < -tol:
                    return True
    return False


def check_winding(vertices, faces, label: str = "mesh") -> None:
    """Raise MeshWallError where two triangles sharing an edge disagree about which side is solid."""
    normals, _ = triangle_normals(vertices, faces)
    _edge_planes(vertices, faces, normals, label)
