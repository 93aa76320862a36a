"""Independent float64 reference for the overlap of two convex polyhedra.

This module deliberately shares no code with ``polydem``: it only uses numpy and
scipy (qhull + HiGHS) so that it can serve as an obviously-correct oracle for the
Warp clipping kernel.

Conventions
-----------
* A convex body is given by the world-space positions of its vertices; its
  halfspace description is ``n . x <= d`` with ``n`` the *outward* unit normal.
* For the intersection ``P = A ∩ B`` every boundary facet of ``P`` lies on a face
  plane of ``A`` or of ``B``.  With ``dA`` the facets on A's planes,

      S_A = sum_{f in dA} area_f * n_f          (area vector)
      M_A = sum_{f in dA} area_f * (c_f x n_f)  (moment about the world origin)

  where ``n_f`` is A's outward unit normal and ``c_f`` the facet centroid.  These
  are the shape derivatives of the overlap volume: translating A by ``t`` gives
  ``dV = S_A . t`` and rotating A by a small angle ``theta`` about the axis ``e``
  through a point ``c`` gives ``dV = theta * e . (M_A - c x S_A)``.
  Since the closed surface of P has zero total area vector and zero total
  moment, ``S_A + S_B = 0`` and ``M_A + M_B = 0``.
* Coincident faces: if a facet of P lies on a plane of A *and* on a plane of B
  with the same outward normal (touching faces, e.g. equal-height boxes), its
  area is split half to A and half to B.  V is not differentiable there; the
  half split is the symmetric (average of one-sided derivatives) choice and
  keeps ``S_A + S_B = 0`` exact.
"""

from __future__ import annotations

import numpy as np
from scipy.optimize import linprog
from scipy.spatial import ConvexHull, HalfspaceIntersection

__all__ = ["halfspaces_from_points", "reference_overlap"]

# Relative tolerances (multiplied by the length scale of the problem).
PLANE_MERGE_RTOL = 1e-12
EMPTY_RADIUS_RTOL = 1e-12
ON_PLANE_RTOL = 1e-8
VERTEX_MERGE_RTOL = 1e-12


def _as_points(points) -> np.ndarray:
    p = np.asarray(points, dtype=np.float64)
    if p.ndim != 2 or p.shape[1] != 3 or p.shape[0] < 4:
        raise ValueError(f"expected an (n>=4, 3) array of points, got shape {p.shape}")
    return p


def _length_scale(points: np.ndarray) -> float:
    ext = np.ptp(points, axis=0).max()
    return float(max(ext, np.abs(points).max(), 1e-300))


def halfspaces_from_points(points) -> tuple[np.ndarray, np.ndarray]:
    """Halfspace description of the convex hull of ``points``.

    Returns ``(normals (F,3), offsets (F,))`` with unit outward normals such that
    ``normals @ x <= offsets`` exactly on the hull.  qhull's triangulated facets
    of one planar face are merged into a single plane (tolerance 1e-12 relative
    to the size of the point set).
    """
    p = _as_points(points)
    scale = _length_scale(p)
    eq = ConvexHull(p).equations  # rows [n, off] with n.x + off <= 0 inside, |n| = 1
    normals = eq[:, :3] / np.linalg.norm(eq[:, :3], axis=1, keepdims=True)
    offsets = -eq[:, 3] / np.linalg.norm(eq[:, :3], axis=1)

    keep_n: list[np.ndarray] = []
    keep_d: list[float] = []
    for n, d in zip(normals, offsets, strict=True):
        dup = False
        for kn, kd in zip(keep_n, keep_d, strict=True):
            if np.abs(n - kn).max() <= PLANE_MERGE_RTOL and abs(d - kd) <= PLANE_MERGE_RTOL * scale:
                dup = True
                break
        if not dup:
            keep_n.append(n)
            keep_d.append(float(d))
    return np.array(keep_n), np.array(keep_d)


def _chebyshev_center(normals: np.ndarray, offsets: np.ndarray, scale: float) -> tuple[np.ndarray, float]:
    """Centre and radius of the largest ball inside {x : normals x <= offsets} (unit normals)."""
    m = normals.shape[0]
    a_ub = np.hstack([normals, np.ones((m, 1))])  # n.x + r |n| <= d, |n| = 1
    c = np.array([0.0, 0.0, 0.0, -1.0])  # maximise r
    bounds = [(None, None)] * 3 + [(0.0, 10.0 * scale)]
    res = linprog(c, A_ub=a_ub, b_ub=offsets, bounds=bounds, method="highs")
    if res.status == 2:  # infeasible: empty intersection
        return np.zeros(3), 0.0
    if res.status != 0:
        raise RuntimeError(f"Chebyshev-centre LP failed: {res.message}")
    return np.asarray(res.x[:3]), float(res.x[3])


def _merge_vertices(v: np.ndarray, tol: float) -> np.ndarray:
    out: list[np.ndarray] = []
    for x in v:
        if not any(np.abs(x - y).max() <= tol for y in out):
            out.append(x)
    return np.array(out)


def _zero_result() -> dict:
    z = np.zeros(3)
    return {
        "volume": 0.0,
        "centroid": z.copy(),
        "area_vector": z.copy(),
        "moment": z.copy(),
        "area_vector_b": z.copy(),
        "moment_b": z.copy(),
    }


def reference_overlap(points_a, points_b) -> dict:
    """Exact (float64) overlap of the convex hulls of two world-space point sets.

    Returns a dict with
      ``volume``         V = vol(A ∩ B)
      ``centroid``       (3,) centroid of A ∩ B (zeros if V == 0)
      ``area_vector``    S_A, sum of area * A's outward normal over facets on A's boundary
      ``moment``         M_A, sum of area * (facet centroid x normal) about the world origin
      ``area_vector_b``  S_B, same for B's facets
      ``moment_b``       M_B, same for B's facets
    Coincident A/B faces are split half to each body (see module docstring).
    """
    pa = _as_points(points_a)
    pb = _as_points(points_b)

    # Work about a local origin for conditioning.
    origin = np.vstack([pa, pb]).mean(axis=0)
    la = pa - origin
    lb = pb - origin
    scale = max(_length_scale(la), _length_scale(lb))

    na, da = halfspaces_from_points(la)
    nb, db = halfspaces_from_points(lb)
    normals = np.vstack([na, nb])
    offsets = np.concatenate([da, db])
    n_a = na.shape[0]

    center, radius = _chebyshev_center(normals, offsets, scale)
    if radius <= EMPTY_RADIUS_RTOL * scale:
        return _zero_result()

    hs = HalfspaceIntersection(np.hstack([normals, -offsets[:, None]]), center)
    verts = _merge_vertices(hs.intersections, VERTEX_MERGE_RTOL * scale)
    hull = ConvexHull(verts)

    tol = ON_PLANE_RTOL * scale
    volume = 0.0
    first_moment = np.zeros(3)  # integral of x dV (local coords)
    s = [np.zeros(3), np.zeros(3)]  # S_A, S_B (local == world, translation invariant)
    m = [np.zeros(3), np.zeros(3)]  # M_A, M_B about the local origin

    for simplex, eq in zip(hull.simplices, hull.equations, strict=True):
        tri = verts[simplex]
        cross = np.cross(tri[1] - tri[0], tri[2] - tri[0])
        if np.dot(cross, eq[:3]) < 0.0:  # orient outward
            tri = tri[[0, 2, 1]]
            cross = -cross
        area = 0.5 * np.linalg.norm(cross)
        tri_centroid = tri.mean(axis=0)

        # Signed tetrahedron from the (interior) Chebyshev centre.
        t_vol = np.dot(tri[0] - center, np.cross(tri[1] - center, tri[2] - center)) / 6.0
        volume += t_vol
        first_moment += t_vol * (center + tri[0] + tri[1] + tri[2]) / 4.0

        # Classify: planes that all three vertices lie on, facing the same way.
        residual = np.abs(tri @ normals.T - offsets).max(axis=0)  # (F,)
        facing = normals @ eq[:3] > 0.5
        cand = (residual <= tol) & facing
        owners = []
        for body, sl in ((0, slice(0, n_a)), (1, slice(n_a, None))):
            idx = np.flatnonzero(cand[sl])
            if idx.size:
                best = idx[np.argmin(residual[sl][idx])] + sl.start
                owners.append((body, normals[best]))
        if not owners:
            if area <= 1e-14 * scale * scale:
                continue  # numerically degenerate sliver
            raise RuntimeError(
                f"overlap facet (area {area:.3e}) lies on no input plane; residual min {residual.min():.3e}"
            )
        w = area / len(owners)
        for body, n in owners:
            s[body] += w * n
            m[body] += w * np.cross(tri_centroid, n)

    if volume <= 0.0:
        return _zero_result()

    centroid_local = first_moment / volume
    # Shift moments back to the world origin: M_world = M_local + o x S.
    return {
        "volume": float(volume),
        "centroid": centroid_local + origin,
        "area_vector": s[0],
        "moment": m[0] + np.cross(origin, s[0]),
        "area_vector_b": s[1],
        "moment_b": m[1] + np.cross(origin, s[1]),
    }
