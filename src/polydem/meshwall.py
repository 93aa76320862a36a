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

Set-up. The cells of a block of triangles are built at once, in numpy arrays over the block (no
Python loop per triangle): a triangle's prism straight from its five planes, then cut by its vertex
planes one at a time (a box around the cell cut by all its planes, for the cells of concave edges and
corners). On one CPU core that is about 6 microseconds per triangle for a flat mesh and 25 for a
sphere (where every cell is cut by vertex planes), plus 10 for each :class:`CellShape` made; the cells
keep about 1 kB per triangle, and the set-up peaks at about 3 kB per triangle more
(``benchmarks/meshwall_setup.py``). A set-up that takes longer than ``PROGRESS_AFTER`` seconds says
how far it is on stderr.
"""

from __future__ import annotations

import functools
import itertools
import sys
import time
from dataclasses import dataclass, field

import numpy as np

# Edges shorter than this fraction of the mesh's bounding diagonal, and triangles of smaller area
# (relative to the diagonal squared), are degenerate: their normals are noise.
DEGENERATE = 1e-10
# Two triangles whose dihedral angle differs from flat by less than this [rad] are coplanar: a file
# in float32 (STL) leaves planar quads bent by about 1e-7.
FLAT = 1e-6
# Cells are built to this fraction of their size (their triangle's or the thickness, whichever is
# larger), so the smaller of the two must be this many times larger than that tolerance: a cell
# resolves its thickness and its triangle to 1e-3 when they are at most MAX_SIZE_RATIO apart.
CELL_TOLERANCE = 1e-9
MAX_SIZE_RATIO = 1e6
# Cells built together: the block's arrays take about 2 kB per cell and plane.
BLOCK = 4096
# A set-up running longer than this [s] prints its progress on stderr.
PROGRESS_AFTER = 3.0

# Two planes whose unit normals' dot product exceeds 1 - NEAR_PARALLEL point the same way (within
# 1.4e-6 rad, the bend below which FLAT takes two triangles as coplanar).
NEAR_PARALLEL = 1e-12

# The clipping starts from a box around each cell; its 6 planes take the first incidence bits
# (bit 2 k the face x_k = +half, 2 k + 1 the face x_k = -half).
_BOX = 6
_CORNERS = np.array(list(itertools.product((-1.0, 1.0), repeat=3)))
_BOX_NORMALS = np.array([[1.0, 0, 0], [-1, 0, 0], [0, 1, 0], [0, -1, 0], [0, 0, 1], [0, 0, -1]])
# Cell kinds (MeshCells.cell_kind).
TRIANGLE, EDGE, CORNER = 0, 1, 2


class MeshWallError(ValueError):
    """A mesh that cannot be a wall (open edges shared by three faces, inconsistent winding, ...)."""


@dataclass(slots=True)
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
    internal_faces = None

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


def triangle_sizes(vertices: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """(nf,) the largest distance of each triangle's corners from its centroid [m]: the size its cell
    is built to (see CELL_TOLERANCE)."""
    tri = vertices[faces]
    return np.linalg.norm(tri - tri.mean(axis=1, keepdims=True), axis=2).max(axis=1)


def thickness_range(vertices, faces) -> tuple[float, float]:
    """``(lowest, highest)`` thickness [m] whose cells resolve every triangle of the mesh and the
    thickness itself (see MAX_SIZE_RATIO); lowest > highest where the triangles alone span more
    than MAX_SIZE_RATIO squared."""
    v = np.asarray(vertices, dtype=np.float64)
    sizes = triangle_sizes(v, np.asarray(faces, dtype=np.int64))
    diag = float(np.linalg.norm(v.max(axis=0) - v.min(axis=0)))
    low = max(float(sizes.max()), 1e-3 * diag) / MAX_SIZE_RATIO
    return low, float(sizes.min()) * MAX_SIZE_RATIO


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


def edge_pairs(faces, label):
    """The triangle pairs that share an edge: ``(f1, j1, f2, j2)``, edge j1 of triangle f1 (from its
    vertex j1 to j1 + 1) being edge j2 of f2, and the number of edges shared by more than two.

    Raises MeshWallError where two triangles sharing an edge are wound inconsistently.
    """
    a = faces
    b = np.roll(faces, -1, axis=1)
    lo, hi = np.minimum(a, b).reshape(-1), np.maximum(a, b).reshape(-1)
    _, inverse, counts = np.unique(lo * (int(faces.max()) + 1) + hi, return_inverse=True, return_counts=True)
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
    return f1, j1, f2, j2, int(np.sum(counts > 2))


def _edge_planes(vertices, faces, normals, label):
    """Per triangle and edge j (from vertex j to j+1): the unit normal and offset of the side plane.

    Returns ``(side, offset, nonmanifold, concave, pairs, bend)``: the planes, the count of edges
    shared by more than two triangles, the concave edges as rows (f1, j1, f2, j2), every shared
    edge as such rows and each one's bend (the rise of f2's far vertex over f1's plane, per length
    of the edge: negative at a convex edge).
    """
    f1, j1, f2, j2, nonmanifold = edge_pairs(faces, label)
    a = faces
    b = np.roll(faces, -1, axis=1)
    start, end = vertices[a], vertices[b]
    t = end - start
    t /= np.linalg.norm(t, axis=2, keepdims=True)
    # In-plane outward normal of each edge: the interior lies to the left of a counter-clockwise edge.
    u = np.cross(t, normals[:, None, :])
    u /= np.linalg.norm(u, axis=2, keepdims=True)
    side = u.copy()
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
    concave = bend > FLAT
    edges = np.column_stack([f1[concave], j1[concave], f2[concave], j2[concave]])
    pairs = np.column_stack([f1, j1, f2, j2])
    return side, offset, nonmanifold, edges, pairs, bend


def _vertex_planes(vertices, faces, normals, front_d, tol):
    """Extra side planes of the cells from the triangles that share only a vertex with them.

    Where non-coplanar triangles i and j meet at a vertex, the solid near it is split between them
    by the plane of equal depth behind both (s_i = s_j, s the signed distance to a triangle's plane):
    at a convex meeting (j's centre behind i's plane) i keeps the points nearer its plane (s_i >= s_j).
    This is the edge bisector's rule carried to triangles that meet at a corner only; without it, the
    cells of a face split into two triangles would overlap its neighbours' near the corner. Concave
    meetings need nothing: there the cells stop at their perpendicular planes. The plane is added
    only where both triangles lie wholly on their own side of it (at a saddle they may not: the
    cells are then left as they are).
    Returns ``(owner, planes)``: (E,) the triangle of each plane and (E, 4) the planes (normal, offset).
    """
    nf = len(faces)
    corner_v = faces.reshape(-1)
    corner_f = np.repeat(np.arange(nf), 3)
    order = np.lexsort((corner_f, corner_v))
    sv, sf = corner_v[order], corner_f[order]
    group_end = np.r_[np.flatnonzero(sv[1:] != sv[:-1]) + 1, len(sv)]
    end_of = np.repeat(group_end, np.diff(np.r_[0, group_end]))
    partners = end_of - np.arange(len(sv)) - 1  # later triangles at the same vertex
    # Where every triangle at a vertex is coplanar with the first, no pair there gets a plane.
    group_start = np.r_[0, group_end[:-1]]
    first_normal = np.repeat(normals[sf[group_start]], np.diff(np.r_[0, group_end]), axis=0)
    bent = np.einsum("ck,ck->c", normals[sf], first_normal) <= 1.0 - 1e-12
    flat = np.logical_or.reduceat(bent, group_start) == 0
    partners[np.repeat(flat, np.diff(np.r_[0, group_end]))] = 0
    centres = vertices[faces].mean(axis=1)
    owners, planes = [], []
    # Pairs of triangles around each vertex, in blocks: a vertex shared by n triangles gives n^2 / 2.
    cum = np.cumsum(partners)
    step = 1 << 18
    lo = 0
    while lo < len(sv):
        hi = int(np.searchsorted(cum, (cum[lo - 1] if lo else 0) + step, side="right"))
        hi = max(hi, lo + 1)
        cnt = partners[lo:hi]
        total = int(cnt.sum())
        if total:
            left = np.repeat(np.arange(lo, hi), cnt)
            right = left + 1 + np.arange(total) - np.repeat(np.cumsum(cnt) - cnt, cnt)
            i, j = sf[left], sf[right]
            shared = (faces[i][:, :, None] == faces[j][:, None, :]).sum(axis=(1, 2))
            keep = shared < 2  # edge neighbours have their bisector already
            keep &= np.einsum("pk,pk->p", normals[i], normals[j]) <= 1.0 - 1e-12  # coplanar: perpendicular planes
            # Concave: the cells stop at the perpendicular planes there.
            keep &= np.einsum("pk,pk->p", normals[i], centres[j]) - front_d[i] < 0.0
            i, j = i[keep], j[keep]
            # Half-space of i: (n_j - n_i).x <= d_j - d_i.
            n = normals[j] - normals[i]
            d = front_d[j] - front_d[i]
            norm = np.linalg.norm(n, axis=1)
            n, d = n / norm[:, None], d / norm
            vi = np.einsum("pck,pk->pc", vertices[faces[i]], n)
            vj = np.einsum("pck,pk->pc", vertices[faces[j]], n)
            ok = (vi.max(axis=1) <= d + tol) & (vj.min(axis=1) >= d - tol)
            i, j, n, d = i[ok], j[ok], n[ok], d[ok]
            owners += [i, j]
            planes += [np.column_stack([n, d]), np.column_stack([-n, -d])]
        lo = hi
    if not owners:
        return np.zeros(0, dtype=np.int64), np.zeros((0, 4))
    return np.concatenate(owners), np.concatenate(planes)


def _bits(index):
    """(word, bit) of incidence bit ``index``."""
    word, bit = divmod(int(index), 64)
    return word, np.uint64(1) << np.uint64(bit)


def _words(k_max):
    return (_BOX + k_max + 63) // 64


@functools.cache
def _triples(k: int) -> np.ndarray:
    return np.array(list(itertools.combinations(range(k), 3)), dtype=np.int64).reshape(-1, 3)


def _box(half, k_max):
    """The box ``|x_k| <= half`` (b,) that the clipping of a cell of ``k_max`` planes starts from, as
    ``(x, live, inc)`` (see _clip): its corners and their bits (0-5 the box's faces)."""
    b = len(half)
    x = np.broadcast_to(_CORNERS, (b, 8, 3)) * half[:, None, None]
    inc = np.zeros((b, 8, _words(k_max)), dtype=np.uint64)
    bits = sum((np.uint64(1) << (2 * axis + (_CORNERS[:, axis] < 0)).astype(np.uint64)) for axis in range(3))
    inc[:, :, 0] = bits
    return x, np.ones((b, 8), dtype=bool), inc


def _enumerate(planes, count, tol, skip_first_pair=False):
    """The vertices of ``{x : n.x <= d}`` for the first ``count`` of a few planes (b, K, 4) (bounded),
    by trying every three (but those with the first two where ``skip_first_pair``: parallel planes):
    ``(x, live, inc)`` as _clip takes them, copies of a vertex merged."""
    b, k = planes.shape[:2]
    idx = _triples(count)
    if skip_first_pair:
        idx = idx[~((idx[:, 0] == 0) & (idx[:, 1] == 1))]
    n = planes[:, idx, :3]
    d = planes[:, idx, 3]
    c12 = np.cross(n[:, :, 1], n[:, :, 2])
    det = np.einsum("btk,btk->bt", n[:, :, 0], c12)
    ok = np.abs(det) > 1e-12
    x = (
        d[..., 0, None] * c12
        + d[..., 1, None] * np.cross(n[:, :, 2], n[:, :, 0])
        + d[..., 2, None] * np.cross(n[:, :, 0], n[:, :, 1])
    ) / np.where(ok, det, 1.0)[..., None]
    s = np.einsum("btk,bpk->btp", x, planes[:, :count, :3]) - planes[:, None, :count, 3]
    ok &= np.all(s <= tol[:, None, None], axis=2)
    on = np.abs(s) <= tol[:, None, None]
    # The vertices found, first in each row (most triples miss: parallel planes, or outside).
    width = max(int(ok.sum(axis=1).max()), 1)
    rank = np.cumsum(ok, axis=1) - 1
    rc, rt = np.nonzero(ok)
    x_out = np.zeros((b, width, 3))
    x_out[rc, rank[rc, rt]] = x[rc, rt]
    on_out = np.zeros((b, width, count), dtype=bool)
    on_out[rc, rank[rc, rt]] = on[rc, rt]
    live = np.arange(width) < ok.sum(axis=1)[:, None]
    inc = np.zeros((b, width, _words(k)), dtype=np.uint64)
    for p in range(count):
        word, bit = _bits(_BOX + p)
        inc[..., word] |= np.where(on_out[..., p], bit, np.uint64(0))
    # A vertex met by more than three planes is found once per three of them.
    rows = np.flatnonzero(np.any(live & (on_out.sum(axis=2) > 3), axis=1))
    if rows.size:
        live[rows], inc[rows] = _merge(x_out[rows], live[rows], inc[rows], tol[rows])
    return x_out, live, inc


def _clip(x, live, inc, planes, first, count, tol):
    """Cut convex polytopes by their planes ``first`` to ``count`` - 1 in turn, a block of them at once.

    The polytopes are given by their vertices x (b, V, 3), which are in use (live) and the planes
    each lies on (inc (b, V, W) uint64 bits: 0-5 a start box's, _BOX + k plane k). A plane that cuts
    a polytope by more than ``tol`` (b,) becomes a face; one that does not is skipped (it is no face).
    A new vertex is where an edge crosses the plane, the edges being the vertex pairs on two common
    faces. planes: (b, K, 4) normal and offset; count: (b,). Returns ``(x, live, inc, applied,
    suspect)``: the polytopes, the planes that cut each, and which may hold copies of a vertex
    (a plane that cut within a few ``tol`` of one).
    """
    b, k_max = planes.shape[:2]
    words = inc.shape[2]
    used = live.shape[1]
    cap = used + 8
    x = np.concatenate([x, np.zeros((b, cap - used, 3))], axis=1)
    live = np.concatenate([live, np.zeros((b, cap - used), dtype=bool)], axis=1)
    inc = np.concatenate([inc, np.zeros((b, cap - used, words), dtype=np.uint64)], axis=1)
    applied = np.zeros((b, k_max), dtype=bool)
    applied[:, :first] = True
    suspect = np.zeros(b, dtype=bool)
    width = np.full(b, used)
    for i in range(first, k_max):
        rows = np.flatnonzero(count > i)
        if not rows.size:
            break
        v_used = int(width[rows].max())
        xr = x[rows, :v_used]
        lr = live[rows, :v_used]
        s = np.einsum("bvk,bk->bv", xr, planes[rows, i, :3]) - planes[rows, i, 3, None]
        tr = tol[rows, None]
        # Only the planes that cut are faces, and only faces give vertices their bits: a plane that
        # repeats a face would make every two vertices of that face look like an edge. So does one
        # that all but repeats it (the planes of two triangles of a flat quad bent by float32 rounding
        # in an STL file): it is taken as the same plane.
        cut = np.where(lr, s, -np.inf).max(axis=1) > tr[:, 0]
        if i:
            p = planes[rows, :i]
            twin = (np.einsum("bjk,bk->bj", p[..., :3], planes[rows, i, :3]) > 1.0 - NEAR_PARALLEL) & (
                np.abs(p[..., 3] - planes[rows, i, 3, None]) <= NEAR_PARALLEL**0.5 * tr / CELL_TOLERANCE
            )
            cut &= ~np.any(twin & applied[rows, :i], axis=1)
        if not cut.any():
            continue
        a = rows[cut]
        applied[a, i] = True
        word, bit = _bits(_BOX + i)
        xa, la, sa, ta = xr[cut], lr[cut], s[cut], tr[cut]
        ma = inc[a, :v_used]
        outside = la & (sa > ta)
        keep = la & ~outside
        ma[..., word] |= np.where(keep & (sa >= -ta), bit, np.uint64(0))
        suspect[a] |= np.any(outside & (sa <= 16.0 * ta), axis=1)
        # Edges from each vertex cut off to the vertices left strictly inside.
        oc, ov = np.nonzero(outside)
        common = np.bitwise_count(ma[oc] & ma[oc, ov][:, None, :])
        common = common.sum(axis=2) if words > 1 else common[..., 0]
        e, cu = np.nonzero((common >= 2) & la[oc] & (sa[oc] < -ta[oc]))
        cc, cv = oc[e], ov[e]
        su, sv = sa[cc, cu], sa[cc, cv]
        xu = xa[cc, cu]
        new_x = xu + (su / (su - sv))[:, None] * (xa[cc, cv] - xu)
        new_m = ma[cc, cu] & ma[cc, cv]
        new_m[:, word] |= bit
        # A new vertex may lie on an earlier face as well (a corner met by more than three planes).
        if i:
            p = planes[a[cc], :i]
            hit = np.abs(np.einsum("ek,ejk->ej", new_x, p[..., :3]) - p[..., 3]) <= tol[a[cc], None]
            hit &= applied[a[cc], :i]
            for j in np.flatnonzero(hit.any(axis=0)).tolist():
                wj, bj = _bits(_BOX + j)
                new_m[:, wj] |= np.where(hit[:, j], bj, np.uint64(0))
        # (cc is in cell order: np.nonzero walks the outside vertices row by row.)
        nk = keep.sum(axis=1)
        nn = np.bincount(cc, minlength=len(a))
        total = nk + nn
        need = int(total.max())
        if need > cap:
            grow = need + 8 - cap
            x = np.concatenate([x, np.zeros((b, grow, 3))], axis=1)
            live = np.concatenate([live, np.zeros((b, grow), dtype=bool)], axis=1)
            inc = np.concatenate([inc, np.zeros((b, grow, words), dtype=np.uint64)], axis=1)
            cap += grow
        span = max(need, v_used)
        x2 = np.zeros((len(a), span, 3))
        m2 = np.zeros((len(a), span, words), dtype=np.uint64)
        kc, kv = np.nonzero(keep)
        pos_k = np.arange(len(kc)) - (np.cumsum(nk) - nk)[kc]
        x2[kc, pos_k] = xa[kc, kv]
        m2[kc, pos_k] = ma[kc, kv]
        pos_n = nk[cc] + np.arange(len(cc)) - (np.cumsum(nn) - nn)[cc]
        x2[cc, pos_n] = new_x
        m2[cc, pos_n] = new_m
        x[a, :span] = x2
        inc[a, :span] = m2
        live[a, :span] = np.arange(span) < total[:, None]
        width[a] = np.maximum(total, 1)
        # A polytope of F faces has at most 2 F - 4 vertices: more are copies or lie inside a face or
        # an edge (near-degenerate planes); drop them before they breed more.
        faces = applied[a].sum(axis=1) + _BOX
        crowded = a[total > 2 * faces + 8]
        if crowded.size:
            v_used = int(width[crowded].max())
            live[crowded, :v_used], inc[crowded, :v_used] = _tidy(
                x[crowded, :v_used], live[crowded, :v_used], inc[crowded, :v_used], planes[crowded], tol[crowded]
            )
    v_used = int(width.max())
    return x[:, :v_used], live[:, :v_used], inc[:, :v_used], applied, suspect


def _merge(x, live, inc, tol):
    """Merge the vertices of a cell closer than 4 ``tol`` (their incidence bits joined): the copies of
    a vertex met by more than three planes. Returns ``(live, inc)``."""
    d2 = np.sum((x[:, :, None, :] - x[:, None, :, :]) ** 2, axis=3)
    close = (d2 <= (4.0 * tol[:, None, None]) ** 2) & live[:, :, None] & live[:, None, :]
    rep = np.argmax(close, axis=2)  # the first vertex each one is close to
    for _ in range(3):  # a chain of close vertices joins its first
        rep = np.take_along_axis(rep, rep, axis=1)
    idx = np.arange(x.shape[1])
    keep = live & (rep == idx)
    into = (rep[:, :, None] == idx) & live[:, :, None]
    joined = np.bitwise_or.reduce(np.where(into[..., None], inc[:, :, None], np.uint64(0)), axis=1)
    return keep, np.where(keep[..., None], joined, inc)


def _tidy(x, live, inc, planes, tol):
    """``(live, inc)`` with copies merged (_merge) and the vertices dropped that are no corner: those
    whose faces' normals (the start box's and the planes') do not span space."""
    live, inc = _merge(x, live, inc, tol)
    b, v = live.shape
    k = planes.shape[1]
    normals = np.concatenate([np.broadcast_to(_BOX_NORMALS, (b, _BOX, 3)), planes[..., :3]], axis=1)
    bit = np.arange(_BOX + k)
    on = ((inc[:, :, bit // 64] >> (bit % 64).astype(np.uint64)) & np.uint64(1)) != 0
    gram = np.einsum("bvp,bpi,bpj->bvij", on.astype(np.float64), normals, normals)
    corner = np.linalg.eigvalsh(gram)[..., 0] > NEAR_PARALLEL
    return live & corner, inc


@dataclass
class _Block:
    """Cells of one block, packed: per cell its vertices (frame origin at their mean) and faces."""

    ids: np.ndarray  # (c,) the cells' ids (their order in the wall)
    center: np.ndarray  # (c, 3) frame origins in the mesh frame
    nv: np.ndarray  # (c,) vertices per cell
    verts: np.ndarray  # (sum nv, 3)
    nfaces: np.ndarray  # (c,) faces per cell
    planes: np.ndarray  # (F, 4) face normal and offset in the cell frame
    nloop: np.ndarray  # (F,) vertices per face
    loops: np.ndarray  # (L,) indices into the cell's vertices
    radius: np.ndarray  # (c,)


def _faces(x, live, inc, planes, applied, origin, ids):
    """The cells' faces (the planes that cut, on at least three vertices), packed as a _Block in the
    frame of each cell's vertices' mean; and the ids of the cells that are empty or reach their
    start box (unbounded)."""
    b, v = live.shape
    k = planes.shape[1]
    bounded = ~np.any(((inc[..., 0] & np.uint64(0b111111)) != 0) & live, axis=1)
    bit = _BOX + np.arange(k)
    on = (inc.transpose(0, 2, 1)[:, bit // 64, :] >> (bit % 64).astype(np.uint64)[None, :, None]) & np.uint64(1)
    on = (on != 0) & live[:, None, :] & applied[:, :, None]  # (b, k, v): the vertices on each plane
    cnt = on.sum(axis=2)
    has = cnt >= 3
    nv = live.sum(axis=1)
    good = bounded & (nv >= 4) & (has.sum(axis=1) >= 4)
    has &= good[:, None]
    centre = np.where(live[..., None], x, 0.0).sum(axis=1) / np.maximum(nv, 1)[:, None]
    local = x - centre[:, None, :]
    fc, fp = np.nonzero(has)
    n = planes[fc, fp, :3]
    nloop = cnt[fc, fp]
    # The faces' vertices, face by face in vertex order (the entries of the loops before sorting).
    bc, bp, bv = np.nonzero(on & has[:, :, None])
    ef = (np.cumsum(has.reshape(-1)) - 1).reshape(b, k)[bc, bp]
    pts = local[bc, bv]
    starts = np.cumsum(nloop) - nloop
    c = np.add.reduceat(pts, starts, axis=0) / nloop[:, None]
    rel = pts - c[ef]
    e1 = rel[starts]
    e1 /= np.linalg.norm(e1, axis=1, keepdims=True)
    e2 = np.cross(n, e1)
    ang = np.arctan2(np.einsum("ek,ek->e", rel, e2[ef]), np.einsum("ek,ek->e", rel, e1[ef]))
    index = np.cumsum(live, axis=1) - 1  # into the cell's own vertices (those in use, in order)
    # Each face's vertices by angle: a row per face, padded, sorted row by row (short rows sort fast).
    slot = np.arange(len(ef)) - starts[ef]
    table = np.full((len(nloop), int(nloop.max(initial=1))), np.inf)
    table[ef, slot] = ang
    order = np.argsort(table, axis=1)[np.arange(table.shape[1]) < nloop[:, None]]
    loops = index[bc, bv][starts[np.repeat(np.arange(len(nloop)), nloop)] + order]
    offsets = planes[fc, fp, 3] - np.einsum("fk,fk->f", n, centre[fc])
    radius = np.sqrt(np.where(live, np.sum(local * local, axis=2), 0.0).max(axis=1))
    cells = np.flatnonzero(good)
    block = _Block(
        ids=ids[cells],
        center=origin[cells] + centre[cells],
        nv=nv[cells],
        verts=local[live & good[:, None]],
        nfaces=np.bincount(fc, minlength=b)[cells],
        planes=np.column_stack([n, offsets]),
        nloop=nloop,
        loops=loops,
        radius=radius[cells],
    )
    return block, ids[~good]


def _polytopes(start, planes, first, count, origin, tol, ids):
    """Cells cut from the polytopes ``start`` (x, live, inc) by their planes ``first`` to ``count`` - 1
    (see _clip), in the frame of ``origin``; packed by _faces."""
    x, live, inc, applied, suspect = _clip(*start, planes, first, count, tol)
    if suspect.any():
        rows = np.flatnonzero(suspect)
        live[rows], inc[rows] = _merge(x[rows], live[rows], inc[rows], tol[rows])
    return _faces(x, live, inc, planes, applied, origin, ids)


def ragged(counts):
    """(sum counts,) the row of each entry of consecutive groups of ``counts`` and its place in it."""
    starts = np.cumsum(counts) - counts
    row = np.repeat(np.arange(len(counts)), counts)
    return row, np.arange(int(np.sum(counts))) - starts[row]


class _Progress:
    """Progress of a long set-up: ``report(done, total)`` or, by default, a line on stderr now and then
    once it has taken PROGRESS_AFTER seconds."""

    def __init__(self, label, total, report):
        self.label, self.total, self.report = label, total, report
        self.t0 = time.perf_counter()
        self.last = self.t0

    def __call__(self, done):
        if self.report is False:
            return
        if callable(self.report):
            self.report(done, self.total)
            return
        now = time.perf_counter()
        if now - self.t0 >= PROGRESS_AFTER and now - self.last >= PROGRESS_AFTER:
            self.last = now
            print(
                f"polydem: {self.label}: cells of {done:,} of {self.total:,} triangles built ({now - self.t0:.0f} s)",
                file=sys.stderr,
                flush=True,
            )


@dataclass
class MeshCells:
    """The cells of one mesh wall, in the mesh frame.

    Attributes:
        vertices: (nv, 3) merged vertices of the surface [m] (mesh frame).
        faces: (nf, 3) int64 triangles, counter-clockwise seen from the front (non-solid) side.
        lower, upper: (C, 3) bounds of each cell in the mesh frame [m].
        nonmanifold_edges: edges shared by more than two triangles (given perpendicular side planes).
        thickness: depth of the solid behind each triangle [m].
        cell_center: (C, 3) each cell's frame origin (its vertices' mean) [m]; cell_radius: (C,) [m].
        cell_front: (C, 4) the plane of the triangle a cell lies behind (zeros for the cells of
            concave edges and corners).
        cell_kind: (C,) TRIANGLE, EDGE or CORNER; cell_source: (C, 2) what it lies behind: the
            triangle (and -1), the edge's two vertices, or the corner's vertex (and -1).
        cell_vert_start: (C+1,) first vertex of each cell in ``cell_vertices`` (C, its frame);
        cell_face_start: (C+1,) first face of each cell in ``face_planes`` ((F, 4) normal and
            offset in the cell's frame); face_loop_start: (F+1,) first entry of each face in
            ``face_loop`` (the cell's own vertex indices, counter-clockwise seen from outside).
        cells: C :class:`CellShape` (cell k < nf behind triangle k, as :func:`build_cells` makes them;
            :func:`polydem.meshmerge.join_flat_cells` puts the joined cells last, each naming its first
            triangle in ``cell_source``), made from the arrays above on first use.
    """

    vertices: np.ndarray
    faces: np.ndarray
    lower: np.ndarray
    upper: np.ndarray
    nonmanifold_edges: int
    thickness: float
    cell_center: np.ndarray
    cell_radius: np.ndarray
    cell_front: np.ndarray
    cell_kind: np.ndarray
    cell_source: np.ndarray
    cell_vert_start: np.ndarray
    cell_vertices: np.ndarray
    cell_face_start: np.ndarray
    face_planes: np.ndarray
    face_loop_start: np.ndarray
    face_loop: np.ndarray
    label: str = "mesh"
    _cells: list | None = field(default=None, repr=False)

    @property
    def num_cells(self) -> int:
        return len(self.cell_center)

    def world_planes(self) -> tuple[np.ndarray, np.ndarray]:
        """``(planes (F, 4), cell (F,))``: every face's plane in the mesh frame and its cell."""
        cell = np.repeat(np.arange(self.num_cells), np.diff(self.cell_face_start))
        p = self.face_planes.copy()
        p[:, 3] += np.einsum("fk,fk->f", p[:, :3], self.cell_center[cell])
        return p, cell

    @property
    def cells(self) -> list:
        if self._cells is None:
            self._cells = self._make_cells()
        return self._cells

    def face_spheres(self) -> np.ndarray:
        """(F, 4) each face's centre (its loop's vertices' mean, in its cell's frame) and the largest
        distance of its vertices from it [m]."""
        ls = self.face_loop_start
        face_row, _ = ragged(np.diff(ls))
        owner = np.repeat(np.arange(self.num_cells), np.diff(self.cell_face_start))
        pts = self.cell_vertices[self.cell_vert_start[owner][face_row] + self.face_loop]
        centers = np.add.reduceat(pts, ls[:-1], axis=0) / np.diff(ls)[:, None]
        radii = np.maximum.reduceat(np.linalg.norm(pts - centers[face_row], axis=1), ls[:-1])
        return np.column_stack([centers, radii])

    def largest_face_areas(self) -> np.ndarray:
        """(C,) the area of each cell's largest face [m^2] (:func:`polydem.shapes.largest_face_area`)."""
        return np.maximum.reduceat(self.face_areas(), self.cell_face_start[:-1])

    def face_areas(self) -> np.ndarray:
        """(F,) the area of each face [m^2]."""
        ls = self.face_loop_start
        face_row, col = ragged(np.diff(ls))
        owner = np.repeat(np.arange(self.num_cells), np.diff(self.cell_face_start))
        first = self.cell_vert_start[owner][face_row]
        nxt = np.where(col + 1 < np.diff(ls)[face_row], np.arange(len(col)) + 1, ls[:-1][face_row])
        a, b = self.cell_vertices[first + self.face_loop], self.cell_vertices[first + self.face_loop[nxt]]
        twice = np.add.reduceat(np.cross(a, b), ls[:-1], axis=0)
        return 0.5 * np.abs(np.einsum("fk,fk->f", twice, self.face_planes[:, :3]))

    def _make_cells(self) -> list:
        ls = self.face_loop_start
        local = self.cell_vertices
        face_row, _ = ragged(np.diff(ls))
        # Each face's centre and radius, over its own loop.
        owner = np.repeat(np.arange(self.num_cells), np.diff(self.cell_face_start))
        pts = local[self.cell_vert_start[owner][face_row] + self.face_loop]
        nloop = np.diff(ls)
        centers = np.add.reduceat(pts, ls[:-1], axis=0) / nloop[:, None]
        radii = np.maximum.reduceat(np.linalg.norm(pts - centers[face_row], axis=1), ls[:-1])
        # Plain slices (np.split is several times slower per piece).
        loop, bounds = self.face_loop, ls.tolist()
        loops = [loop[i:j] for i, j in zip(bounds[:-1], bounds[1:], strict=True)]
        names = {TRIANGLE: f"{self.label} cell", EDGE: f"{self.label} edge cell", CORNER: f"{self.label} corner cell"}
        vs, fs = self.cell_vert_start.tolist(), self.cell_face_start.tolist()
        normals, offsets = self.face_planes[:, :3], self.face_planes[:, 3]
        kinds, radius = self.cell_kind.tolist(), self.cell_radius.tolist()
        center, front = self.cell_center, self.cell_front
        return [
            CellShape(
                f"{names[kinds[k]]} {k}",
                local[vs[k] : vs[k + 1]],
                loops[fs[k] : fs[k + 1]],
                normals[fs[k] : fs[k + 1]],
                offsets[fs[k] : fs[k + 1]],
                centers[fs[k] : fs[k + 1]],
                radii[fs[k] : fs[k + 1]],
                radius[k],
                center[k],
                front[k],
            )
            for k in range(self.num_cells)
        ]


def build_cells(vertices, faces, thickness: float, label: str = "mesh", progress=None) -> MeshCells:
    """The convex cells of the solid ``thickness`` [m] deep behind the triangles (see the module docstring;
    :func:`polydem.meshmerge.join_flat_cells` joins those of flat patches for the contact kernels).

    ``progress``: None prints a line on stderr now and then once the set-up has taken PROGRESS_AFTER
    seconds; False prints nothing; a callable gets ``(triangles done, triangles)`` after each block.
    """
    if not (np.isfinite(thickness) and thickness > 0.0):
        raise MeshWallError(f"{label}: thickness must be a positive length in m, got {thickness!r}")
    v, f = clean_triangles(vertices, faces, label)
    h = float(thickness)
    low, high = thickness_range(v, f)
    if not low <= h <= high:
        raise MeshWallError(f"{label}: {thickness_problem(v, f, h)}")
    normals, _ = triangle_normals(v, f)
    side, offset, nonmanifold, concave, pairs, bend = _edge_planes(v, f, normals, label)
    front_d = np.einsum("fk,fk->f", normals, v[f[:, 0]])
    diag = float(np.linalg.norm(v.max(axis=0) - v.min(axis=0)))
    owner, extra = _vertex_planes(v, f, normals, front_d, CELL_TOLERANCE * diag)
    report = _Progress(label, len(f), progress)
    blocks = []
    tri = _triangle_cells(v, f, normals, front_d, side, offset, owner, extra, h, diag, blocks, report, label)
    tol = CELL_TOLERANCE * max(h, diag * 1e-3)
    edge_ends = _wedge_cells(v, f, normals, front_d, concave, h, tol, len(f), blocks)
    corner_vertex = _corner_cells(v, f, normals, front_d, concave, pairs, h, tol, len(f) + len(concave), blocks)
    return _assemble(v, f, blocks, tri, edge_ends, corner_vertex, nonmanifold, h, label)


def thickness_problem(vertices, faces, thickness: float, what: str = "") -> str:
    """Why ``thickness`` [m] (``what``: a note on where it came from) is outside :func:`thickness_range`
    of the mesh, and the range."""
    sizes = triangle_sizes(np.asarray(vertices, dtype=np.float64), np.asarray(faces, dtype=np.int64))
    low, high = thickness_range(vertices, faces)
    h = f"the thickness {thickness:.3g} m{what}"
    why = (
        f"the cells are built to {CELL_TOLERANCE:g} of the larger of their thickness and their triangle's size "
        f"(centre to corner), so the two may be at most {MAX_SIZE_RATIO:g} times apart"
    )
    if low > high:
        return (
            f"its triangles range from {sizes.min():.3g} m to {sizes.max():.3g} m (centre to corner), over "
            f"{MAX_SIZE_RATIO**2:g} times apart, so no thickness suits them all ({why}); remesh it more evenly"
        )
    if thickness > high:
        return (
            f"{h} is over {MAX_SIZE_RATIO:g} times the size of its smallest triangle ({sizes.min():.3g} m): {why}; "
            f"give a thickness from {low:.3g} m to {high:.3g} m"
        )
    return (
        f"its largest triangle ({sizes.max():.3g} m) is over {MAX_SIZE_RATIO:g} times {h}: {why}; give a thickness "
        f"from {low:.3g} m to {high:.3g} m"
    )


def _widen(inc, words):
    """Incidence bits ``inc`` with room for ``words`` 64-bit words."""
    if inc.shape[2] >= words:
        return inc
    return np.concatenate([inc, np.zeros((*inc.shape[:2], words - inc.shape[2]), dtype=np.uint64)], axis=2)


# A triangle's prism: its corners 0-2 then the back ones 3-5 (behind 0-2), and its faces' loops:
# the front, the back, and the side behind edge j (from corner j to j + 1).
_PRISM_LOOPS = np.array([0, 1, 2, 3, 5, 4, 0, 3, 4, 1, 1, 4, 5, 2, 2, 5, 3, 0])
_PRISM_NLOOP = np.array([3, 3, 4, 4, 4])


def _prism(base, corners, tol):
    """The cells whose five planes (front, back, sides behind edges 0-2; (b, 5, 4)) make a prism: the
    triangle's ``corners`` (b, 3, 3) and the back plane's points on the side planes through each,
    all six apart and inside every plane. Returns ``(x (b, 6, 3), prism (b,), inc (b, 6, 1))`` as
    _clip takes them (valid where ``prism``)."""
    b = len(base)
    n0, d0 = base[:, 1, :3], base[:, 1, 3]
    x = np.empty((b, 6, 3))
    x[:, :3] = corners
    ok = np.ones(b, dtype=bool)
    for j in range(3):
        n1, d1 = base[:, 2 + (j - 1) % 3, :3], base[:, 2 + (j - 1) % 3, 3]
        n2, d2 = base[:, 2 + j, :3], base[:, 2 + j, 3]
        c12 = np.cross(n1, n2)
        det = np.einsum("bk,bk->b", n0, c12)
        ok &= np.abs(det) > 1e-12
        num = d0[:, None] * c12 + d1[:, None] * np.cross(n2, n0) + d2[:, None] * np.cross(n0, n1)
        x[:, 3 + j] = num / np.where(ok, det, 1.0)[:, None]
    s = np.einsum("bvk,bpk->bvp", x, base[..., :3]) - base[:, None, :, 3]
    ok &= np.all(s <= tol[:, None, None], axis=(1, 2))
    back = x[:, 3:]
    gap = np.linalg.norm(back[:, [0, 1, 2]] - back[:, [1, 2, 0]], axis=2).min(axis=1)
    ok &= gap > 8.0 * tol
    inc = np.zeros((b, 6, 1), dtype=np.uint64)
    for j in range(3):
        sides = (np.uint64(1) << np.uint64(_BOX + 2 + (j - 1) % 3)) | (np.uint64(1) << np.uint64(_BOX + 2 + j))
        inc[:, j, 0] = sides | (np.uint64(1) << np.uint64(_BOX))
        inc[:, 3 + j, 0] = sides | (np.uint64(1) << np.uint64(_BOX + 1))
    return x, ok, inc


def _prism_block(x, planes, origin, ids):
    """The prisms ``x`` (c, 6, 3) of _prism with their planes (c, 5, 4), as a _Block."""
    c = len(ids)
    centre = x.mean(axis=1)
    local = x - centre[:, None, :]
    n = planes[..., :3]
    offsets = planes[..., 3] - np.einsum("cfk,ck->cf", n, centre)
    return _Block(
        ids=ids,
        center=origin + centre,
        nv=np.full(c, 6),
        verts=local.reshape(-1, 3),
        nfaces=np.full(c, 5),
        planes=np.concatenate([n, offsets[..., None]], axis=2).reshape(-1, 4),
        nloop=np.tile(_PRISM_NLOOP, c),
        loops=np.tile(_PRISM_LOOPS, c),
        radius=np.sqrt(np.sum(local * local, axis=2).max(axis=1)),
    )


def _triangle_cells(v, f, normals, front_d, side, offset, owner, extra, h, diag, blocks, report, label):
    """The cell behind each triangle: the polytope of its front, back and side planes (every three of
    them tried), cut by those of its vertex planes that cut it (see _vertex_planes); a block of
    triangles at a time, grouped by that number of planes."""
    nf = len(f)
    origin = v[f].mean(axis=1)
    tol_all = CELL_TOLERANCE * np.maximum(np.maximum(h, triangle_sizes(v, f)), diag * 1e-3)
    order = np.argsort(owner, kind="stable")
    owner, extra = owner[order], extra[order]
    bounds = np.searchsorted(owner, np.arange(nf + 1))
    empty = []
    for lo in range(0, nf, BLOCK):
        ids = np.arange(lo, min(nf, lo + BLOCK))
        parts = []
        o, tol = origin[ids], tol_all[ids]
        base = np.empty((len(ids), 5, 4))
        base[:, 0, :3] = normals[ids]
        base[:, 0, 3] = front_d[ids]
        base[:, 1, :3] = -normals[ids]
        base[:, 1, 3] = -(front_d[ids] - h)
        base[:, 2:5, :3] = side[ids]
        base[:, 2:5, 3] = offset[ids]
        base[..., 3] -= np.einsum("bpk,bk->bp", base[..., :3], o)
        x, prism, inc = _prism(base, v[f[ids]] - o[:, None, :], tol)
        live = np.ones(x.shape[:2], dtype=bool)
        if not prism.all():
            # The side planes meet before the back (or the cell is degenerate): try every three planes.
            rows = np.flatnonzero(~prism)
            xe, le, ie = _enumerate(base[rows], 5, tol[rows], skip_first_pair=True)  # the front and back are parallel
            width = max(6, xe.shape[1])
            x = np.concatenate([x, np.zeros((len(ids), width - 6, 3))], axis=1)
            live = np.concatenate([live, np.zeros((len(ids), width - 6), dtype=bool)], axis=1)
            inc = np.concatenate([inc, np.zeros((len(ids), width - 6, 1), dtype=np.uint64)], axis=1)
            x[rows], live[rows], inc[rows] = 0.0, False, 0
            x[rows, : xe.shape[1]], live[rows, : xe.shape[1]], inc[rows, : xe.shape[1]] = xe, le, ie
        # A vertex plane that does not cut this polytope cannot cut the smaller one either.
        e0, e1 = bounds[lo], bounds[ids[-1] + 1]
        own = owner[e0:e1] - lo
        ex = extra[e0:e1].copy()
        ex[:, 3] -= np.einsum("ek,ek->e", ex[:, :3], o[own])
        reach = np.where(live[own], np.einsum("evk,ek->ev", x[own], ex[:, :3]), -np.inf).max(axis=1)
        cuts = reach - ex[:, 3] > tol[own]
        own, ex = own[cuts], ex[cuts]
        n_cut = np.bincount(own, minlength=len(ids))
        first = np.cumsum(n_cut) - n_cut
        for k in np.unique(n_cut).tolist():
            g = np.flatnonzero(n_cut == k)
            planes = np.empty((len(g), 5 + k, 4))
            planes[:, :5] = base[g]
            if k:
                planes[:, 5:] = ex[first[g][:, None] + np.arange(k)]
                start = (x[g], live[g], _widen(inc[g], _words(5 + k)))
                block, bad = _polytopes(start, planes, 5, np.full(len(g), 5 + k), o[g], tol[g], ids[g])
            else:
                simple = prism[g]
                if simple.any():
                    parts.append(_prism_block(x[g[simple], :6], planes[simple], o[g[simple]], ids[g[simple]]))
                g, planes = g[~simple], planes[~simple]
                if not len(g):
                    continue
                block, bad = _faces(x[g], live[g], inc[g], planes, np.ones((len(g), 5), dtype=bool), o[g], ids[g])
            parts.append(block)
            empty += bad.tolist()
        blocks.append(_merge_blocks(parts))
        report(int(ids[-1]) + 1)
    if empty:
        k = min(empty)
        raise MeshWallError(
            f"{label}: the cell behind triangle {k} is empty (its side planes meet before the front); "
            f"the mesh folds back on itself there ({len(empty)} such triangle(s))"
        )
    return nf


def _wedge_cells(v, f, normals, front_d, concave, h, tol, first_id, blocks):
    """Cells of the solid behind concave edges, which the triangles' prisms leave out.

    Behind a concave edge, between the two triangles' perpendicular planes, lies a wedge of solid
    behind both triangles: one cell, capped by the planes perpendicular to the edge through its
    ends. Returns (E, 2) the vertices of each concave edge (a wedge id each; empty wedges are left out)."""
    if not len(concave):
        return np.zeros((0, 2), dtype=np.int64)
    f1, j1, f2, _ = concave.T
    a, b = v[f[f1, j1]], v[f[f1, (j1 + 1) % 3]]
    length = np.linalg.norm(b - a, axis=1)
    t = (b - a) / length[:, None]
    n1, n2 = normals[f1], normals[f2]
    u1 = np.cross(t, n1)
    u2 = np.cross(-t, n2)

    def plane(n, d):
        return np.concatenate([n, d[:, None]], axis=1)

    def dot(p, q):
        return np.einsum("ek,ek->e", p, q)

    planes = np.stack(
        [
            plane(-u1, -dot(u1, a)),
            plane(-u2, -dot(u2, a)),
            plane(n1, front_d[f1]),
            plane(n2, front_d[f2]),
            plane(-n1, -(front_d[f1] - h)),
            plane(-n2, -(front_d[f2] - h)),
            plane(-t, -dot(t, a)),
            plane(t, dot(t, b)),
        ],
        axis=1,
    )
    origin = 0.5 * (a + b)
    planes[..., 3] -= np.einsum("bpk,bk->bp", planes[..., :3], origin)
    reach = 2.0 * (h + length)
    for lo in range(0, len(concave), BLOCK):
        sl = slice(lo, lo + BLOCK)
        ids = first_id + np.arange(len(concave))[sl]
        box0 = _box(4.0 * reach[sl], 8)
        block, _ = _polytopes(box0, planes[sl], 0, np.full(len(ids), 8), origin[sl], np.full(len(ids), tol), ids)
        blocks.append(_select(block, block.radius <= reach[ids - first_id]))
    return np.column_stack([f[f1, j1], f[f1, (j1 + 1) % 3]])


def _corner_cells(v, f, normals, front_d, concave, pairs, h, tol, first_id, blocks):
    """Cells behind the vertices where concave edges meet and no edge is convex.

    The caps of the concave edges' wedges leave the solid behind every triangle there: one cell,
    (x - v).t <= 0 for each concave edge t leaving the vertex, behind every triangle at it. A corner
    whose concave edges do not close the solid around it (they do at the corner of a box's inside)
    leaves this region unbounded along the surface: no cell there. Returns the vertex of each corner id."""
    if not len(concave):
        return np.zeros(0, dtype=np.int64)
    f1, j1, _, _ = concave.T
    ia, ib = f[f1, j1], f[f1, (j1 + 1) % 3]
    t = v[ib] - v[ia]
    t /= np.linalg.norm(t, axis=1, keepdims=True)
    vert = np.concatenate([ia, ib])
    dirs = np.concatenate([t, -t])
    order = np.argsort(vert, kind="stable")
    vert, dirs = vert[order], dirs[order]
    corners, start, m = np.unique(vert, return_index=True, return_counts=True)
    # Collinear edges through the vertex: their caps meet flush.
    spread = np.linalg.norm(np.cross(dirs, dirs[np.repeat(start, m)]), axis=1)
    ok = np.maximum.reduceat(spread, start) > 1e-9
    # A convex edge meeting there too (a saddle): left as it is.
    p1, q1, p2, q2 = pairs.T
    far2 = v[f[p2, (q2 + 2) % 3]]
    far1 = v[f[p1, (q1 + 2) % 3]]
    below = (np.einsum("ek,ek->e", normals[p1], far2) - front_d[p1] < -tol * 1e3) | (
        np.einsum("ek,ek->e", normals[p2], far1) - front_d[p2] < -tol * 1e3
    )
    convex_at = np.zeros(len(v), dtype=bool)
    convex_at[f[p1[below], q1[below]]] = True
    convex_at[f[p1[below], (q1[below] + 1) % 3]] = True
    ok &= ~convex_at[corners]
    # The triangles at each vertex.
    corner_v = f.reshape(-1)
    tri_order = np.argsort(corner_v, kind="stable")
    tri_of = tri_order // 3
    tri_start = np.searchsorted(corner_v[tri_order], corners)
    tri_n = np.searchsorted(corner_v[tri_order], corners, side="right") - tri_start
    ids_all = first_id + np.arange(len(corners))
    k_all = m + 2 * tri_n
    parts = []
    for k in np.unique(k_all[ok]).tolist():
        group = np.flatnonzero(ok & (k_all == k))
        for lo in range(0, len(group), BLOCK):
            g = group[lo : lo + BLOCK]
            x = v[corners[g]]
            planes = np.zeros((len(g), k, 4))
            mg, tg = m[g], tri_n[g]
            row, col = ragged(mg)
            planes[row, col, :3] = dirs[start[g][row] + col]
            row, col = ragged(tg)
            tri = tri_of[tri_start[g][row] + col]
            planes[row, mg[row] + col, :3] = normals[tri]
            planes[row, mg[row] + col, 3] = front_d[tri] - np.einsum("ek,ek->e", normals[tri], x[row])
            planes[row, mg[row] + tg[row] + col, :3] = -normals[tri]
            planes[row, mg[row] + tg[row] + col, 3] = -(front_d[tri] - h) + np.einsum("ek,ek->e", normals[tri], x[row])
            box0 = _box(np.full(len(g), 16.0 * h), k)
            block, _ = _polytopes(box0, planes, 0, np.full(len(g), k), x, np.full(len(g), tol), ids_all[g])
            parts.append(_select(block, block.radius <= 4.0 * h))
    if parts:
        blocks.append(_merge_blocks(parts))
    return corners


def _select(block: _Block, keep: np.ndarray) -> _Block:
    """The cells ``keep`` (bool per cell) of a block."""
    vrow, _ = ragged(block.nv)
    frow, _ = ragged(block.nfaces)
    lrow, _ = ragged(block.nloop)
    fkeep = keep[frow]
    return _Block(
        ids=block.ids[keep],
        center=block.center[keep],
        nv=block.nv[keep],
        verts=block.verts[keep[vrow]],
        nfaces=block.nfaces[keep],
        planes=block.planes[fkeep],
        nloop=block.nloop[fkeep],
        loops=block.loops[fkeep[lrow]],
        radius=block.radius[keep],
    )


def _merge_blocks(blocks) -> _Block:
    """One block of the cells of ``blocks``, in the order of their ids."""
    ids = np.concatenate([b.ids for b in blocks])
    order = np.argsort(ids, kind="stable")
    cat = {name: np.concatenate([getattr(b, name) for b in blocks]) for name in _Block.__dataclass_fields__}
    if np.all(order == np.arange(len(order))):
        return _Block(**cat)
    nv, nfaces, nloop = cat["nv"], cat["nfaces"], cat["nloop"]
    # Ragged gathers: the cells in id order, then their faces, then the faces' loops.
    row, col = ragged(nv[order])
    verts = cat["verts"][(np.cumsum(nv) - nv)[order][row] + col]
    row, col = ragged(nfaces[order])
    face_order = (np.cumsum(nfaces) - nfaces)[order][row] + col
    row, col = ragged(nloop[face_order])
    loops = cat["loops"][(np.cumsum(nloop) - nloop)[face_order][row] + col]
    return _Block(
        ids=ids[order],
        center=cat["center"][order],
        nv=nv[order],
        verts=verts,
        nfaces=nfaces[order],
        planes=cat["planes"][face_order],
        nloop=nloop[face_order],
        loops=loops,
        radius=cat["radius"][order],
    )


def _assemble(v, f, blocks, n_tri, edge_ends, corner_vertex, nonmanifold, h, label) -> MeshCells:
    """The blocks' cells (each block in id order, the blocks in turn) packed as MeshCells."""
    all_ = _merge_blocks(blocks)
    blocks.clear()  # their arrays are copied: let them go before the rest is built
    ids, center, radius, nv, nfaces = all_.ids, all_.center, all_.radius, all_.nv, all_.nfaces
    verts, planes, nloop, loops = all_.verts, all_.planes, all_.nloop, all_.loops
    kind = np.where(ids < n_tri, TRIANGLE, np.where(ids < n_tri + len(edge_ends), EDGE, CORNER)).astype(np.int8)
    normals, _ = triangle_normals(v, f)
    front = np.zeros((len(ids), 4))
    tri = ids < n_tri
    front[tri, :3] = normals[ids[tri]]
    front[tri, 3] = np.einsum("fk,fk->f", normals[ids[tri]], v[f[ids[tri], 0]])
    source = np.full((len(ids), 2), -1, dtype=np.int64)
    source[tri, 0] = ids[tri]
    edge = kind == EDGE
    source[edge] = edge_ends[ids[edge] - n_tri]
    corner = kind == CORNER
    source[corner, 0] = corner_vertex[ids[corner] - n_tri - len(edge_ends)]
    vert_start = np.r_[0, np.cumsum(nv)]
    face_start = np.r_[0, np.cumsum(nfaces)]
    loop_start = np.r_[0, np.cumsum(nloop)]
    world = verts + np.repeat(center, nv, axis=0)
    lower = np.minimum.reduceat(world, vert_start[:-1], axis=0)
    upper = np.maximum.reduceat(world, vert_start[:-1], axis=0)
    return MeshCells(
        vertices=v,
        faces=f,
        lower=lower,
        upper=upper,
        nonmanifold_edges=nonmanifold,
        thickness=float(h),
        cell_center=center,
        cell_radius=radius,
        cell_front=front,
        cell_kind=kind,
        cell_source=source,
        cell_vert_start=vert_start,
        cell_vertices=verts,
        cell_face_start=face_start,
        face_planes=planes,
        face_loop_start=loop_start,
        face_loop=loops,
        label=label,
    )


def check_winding(vertices, faces, label: str = "mesh") -> None:
    """Raise MeshWallError where two triangles sharing an edge disagree about which side is solid."""
    edge_pairs(np.asarray(faces, dtype=np.int64), label)


# ---------------------------------------------------------------------- host-side queries (scene checks)


def near_pairs(centres_a, radii_a, centres_b, radii_b) -> tuple[np.ndarray, np.ndarray]:
    """``(ia, ib)``: the pairs whose spheres meet, ``|c_a - c_b| <= r_a + r_b``.

    A k-d tree per class of B's radii (each a factor 4 wide), searched with A's radius plus the
    largest of the class: a few huge spheres (a floor of two triangles) then do not widen every search.
    """
    from scipy.spatial import cKDTree

    ca, ra = np.asarray(centres_a, dtype=np.float64), np.asarray(radii_a, dtype=np.float64)
    cb, rb = np.asarray(centres_b, dtype=np.float64), np.asarray(radii_b, dtype=np.float64)
    if not len(ca) or not len(cb):
        return np.zeros(0, dtype=np.int64), np.zeros(0, dtype=np.int64)
    floor = max(float(rb.min()), 1e-300)
    cls = np.floor(np.log(np.maximum(rb, floor) / floor) / np.log(4.0)).astype(np.int64)
    out_a, out_b = [], []
    tree_a = cKDTree(ca)
    for c in np.unique(cls).tolist():
        members = np.flatnonzero(cls == c)
        # Pairs as arrays straight from the trees (per-query lists cost a Python object each).
        found = tree_a.sparse_distance_matrix(
            cKDTree(cb[members]), float(ra.max() + rb[members].max()), output_type="ndarray"
        )
        ia, ib = found["i"].astype(np.int64), members[found["j"]]
        meet = found["v"] <= ra[ia] + rb[ib]
        out_a.append(ia[meet])
        out_b.append(ib[meet])
    if not out_a:
        return np.zeros(0, dtype=np.int64), np.zeros(0, dtype=np.int64)
    return np.concatenate(out_a), np.concatenate(out_b)


def cell_reach(cells: MeshCells, cell: np.ndarray, points: np.ndarray) -> np.ndarray:
    """(P, m): how far each of the points (P, m, 3) [m, mesh frame] lies outside cell ``cell`` (P,): the
    largest of n.x - d over the cell's faces (<= 0 inside)."""
    planes, _ = cells.world_planes()
    start = cells.cell_face_start
    counts = start[cell + 1] - start[cell]
    row, col = ragged(counts)
    faces = planes[start[cell][row] + col]
    s = np.einsum("emk,ek->em", points[row], faces[:, :3]) - faces[:, 3, None]
    return np.maximum.reduceat(s, np.cumsum(counts) - counts, axis=0)


def ray_exit(cells: MeshCells, cell: np.ndarray, origin: np.ndarray, direction: np.ndarray) -> np.ndarray:
    """(R,) the distance along each unit ``direction`` (R, 3) from ``origin`` (R, 3) [m], inside cell
    ``cell`` (R,), to where the ray leaves the cell."""
    planes, _ = cells.world_planes()
    start = cells.cell_face_start
    counts = start[cell + 1] - start[cell]
    row, col = ragged(counts)
    faces = planes[start[cell][row] + col]
    rate = np.einsum("ek,ek->e", faces[:, :3], direction[row])
    gap = faces[:, 3] - np.einsum("ek,ek->e", faces[:, :3], origin[row])
    with np.errstate(divide="ignore", invalid="ignore"):
        t = np.where(rate > 1e-12, gap / rate, np.inf)
    return np.minimum.reduceat(t, np.cumsum(counts) - counts)


def ray_hits(origin, direction, corners):
    """Möller-Trumbore: the distance t along ``direction`` (P, 3) from ``origin`` (P, 3) at which each
    ray meets its triangle ``corners`` (P, 3, 3), NaN where it misses (or runs parallel to it)."""
    e1 = corners[:, 1] - corners[:, 0]
    e2 = corners[:, 2] - corners[:, 0]
    p = np.cross(direction, e2)
    det = np.einsum("pk,pk->p", e1, p)
    with np.errstate(divide="ignore", invalid="ignore"):
        inv = 1.0 / det
        s = origin - corners[:, 0]
        u = np.einsum("pk,pk->p", s, p) * inv
        q = np.cross(s, e1)
        v = np.einsum("pk,pk->p", direction, q) * inv
        t = np.einsum("pk,pk->p", e2, q) * inv
        hit = (np.abs(det) > 1e-300) & (u >= 0.0) & (v >= 0.0) & (u + v <= 1.0)
    return np.where(hit, t, np.nan)


def is_closed(faces) -> bool:
    """Whether every edge of the triangles is shared by exactly two of them (a closed surface)."""
    f = np.asarray(faces, dtype=np.int64)
    a, b = f.reshape(-1), np.roll(f, -1, axis=1).reshape(-1)
    key = np.minimum(a, b) * (int(f.max()) + 1) + np.maximum(a, b)
    _, counts = np.unique(key, return_counts=True)
    return bool(np.all(counts == 2))


def winding(points, vertices, faces) -> np.ndarray:
    """(P,) int: how many times a closed surface winds around each point: the signed count of the
    triangles a ray from it along +x leaves through (+1 through a triangle's front, -1 its back), so
    1 inside a surface facing out, -1 inside one facing in, 0 outside. The points are moved by 1e-9
    of the mesh's size first, so that no ray runs along an edge."""
    pts = np.asarray(points, dtype=np.float64)
    v = np.asarray(vertices, dtype=np.float64)
    f = np.asarray(faces, dtype=np.int64)
    out = np.zeros(len(pts), dtype=np.int64)
    if not len(pts):
        return out
    lo_all, hi_all = v.min(axis=0), v.max(axis=0)
    size = float(np.linalg.norm(hi_all - lo_all))
    pts = pts + np.array([0.0, 0.7548776662, 0.5698402910]) * 1e-9 * size
    tri = v[f]
    normals, _ = triangle_normals(v, f)
    lo, hi = tri[:, :, 1:].min(axis=1), tri[:, :, 1:].max(axis=1)
    span = float(max((hi_all - lo_all)[1:].max(), 1e-300))
    cell = max(float(np.median((hi - lo).max(axis=1))), span / 512.0)
    n_bins = int(span / cell) + 2
    i0 = np.floor((lo - lo_all[1:]) / cell).astype(np.int64)
    i1 = np.floor((hi - lo_all[1:]) / cell).astype(np.int64)
    wide = i1 - i0 + 1
    count = wide[:, 0] * wide[:, 1]
    t_row, k = ragged(count)
    by = i0[t_row, 0] + k // wide[t_row, 1]
    bz = i0[t_row, 1] + k % wide[t_row, 1]
    key = by * n_bins + bz
    order = np.argsort(key, kind="stable")
    key, t_row = key[order], t_row[order]
    inside = np.all((pts[:, 1:] >= lo_all[1:]) & (pts[:, 1:] <= hi_all[1:]), axis=1) & (pts[:, 0] <= hi_all[0])
    which = np.flatnonzero(inside)
    pb = np.floor((pts[which, 1:] - lo_all[1:]) / cell).astype(np.int64)
    pkey = pb[:, 0] * n_bins + pb[:, 1]
    first = np.searchsorted(key, pkey)
    n = np.searchsorted(key, pkey, side="right") - first
    p_row, k = ragged(n)
    cand = t_row[first[p_row] + k]
    p = pts[which[p_row]]
    c = tri[cand]
    a0, a1, a2 = c[:, 0, 1:], c[:, 1, 1:], c[:, 2, 1:]
    e0, e1, r = a1 - a0, a2 - a0, p[:, 1:] - a0
    det = e0[:, 0] * e1[:, 1] - e0[:, 1] * e1[:, 0]
    with np.errstate(divide="ignore", invalid="ignore"):
        s = (r[:, 0] * e1[:, 1] - r[:, 1] * e1[:, 0]) / det
        t = (e0[:, 0] * r[:, 1] - e0[:, 1] * r[:, 0]) / det
        x = c[:, 0, 0] + s * (c[:, 1, 0] - c[:, 0, 0]) + t * (c[:, 2, 0] - c[:, 0, 0])
        hit = (det != 0.0) & (s >= 0.0) & (t >= 0.0) & (s + t <= 1.0) & (x > p[:, 0])
    sign = np.sign(normals[cand, 0]) * hit
    out[which] = np.round(np.bincount(p_row, weights=sign, minlength=len(which))).astype(np.int64)
    return out
