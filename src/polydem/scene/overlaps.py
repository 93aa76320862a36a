"""Initial overlaps: free bodies that start behind a plane wall or inside another body."""

from __future__ import annotations

import numpy as np

from polydem.compound import expand_bodies, is_compound
from polydem.quaternions import quat_to_matrix
from polydem.scene.bodies import KIND_FREE
from polydem.scene.values import row_norms

# Initial overlaps, as a fraction of the thinner body's thickness along the separating axis.
INITIAL_OVERLAP_WARNING = 0.01
INITIAL_OVERLAP_ERROR = 0.5

_BLOCK = 1 << 22  # floats per block of the vectorised overlap tests (32 MiB)
MAX_EDGE_AXES = 4096  # edge-direction pairs tested per body pair; beyond, face normals only
# A body whose bounding radius is more than this many times the bodies' median (a container's slab, a drum, a
# boulder) searches the others instead of being searched, and comes first in its pairs.
BIG_RADIUS_RATIO = 4.0


def _blocks(n: int, per_item: int):
    step = max(1, _BLOCK // max(1, per_item))
    for start in range(0, n, step):
        yield slice(start, min(n, start + step))


class OverlapRecords:
    """Initial overlaps as arrays, in the order they were found: per record its share of the basis
    (``rel``), its depth [m] and its body, and ``words(k)``, the ``(where, of what basis, fix)`` of
    record k, made only for the records a message shows (a pile may hold millions of small overlaps).
    :func:`report_overlaps` takes these or a list of ``(rel, depth, body, where, basis, fix)`` tuples."""

    def __init__(self, rel, depth, body, words, other=None):
        self.rel = np.asarray(rel, dtype=np.float64).reshape(-1)
        self.depth = np.asarray(depth, dtype=np.float64).reshape(-1)
        self.body = np.asarray(body, dtype=np.int64).reshape(-1)
        # what the body overlaps (another body, a plane wall): orders records as deep
        self.other = (
            np.zeros(len(self.rel), dtype=np.int64) if other is None else np.asarray(other, np.int64).reshape(-1)
        )
        self.words = words

    def __len__(self) -> int:
        return len(self.rel)

    @classmethod
    def none(cls) -> OverlapRecords:
        return cls(np.zeros(0), np.zeros(0), np.zeros(0, dtype=np.int64), None)

    @classmethod
    def of_tuples(cls, records: list[tuple]) -> OverlapRecords:
        rel = [r[0] for r in records]
        return cls(rel, [r[1] for r in records], [r[2] for r in records], lambda k: tuple(records[k][3:6]))

    @classmethod
    def join(cls, parts: list[OverlapRecords]) -> OverlapRecords:
        """The records of ``parts`` one after the other."""
        parts = [p for p in parts if len(p)]
        if len(parts) <= 1:
            return parts[0] if parts else cls.none()
        ends = np.cumsum([len(p) for p in parts])

        def words(k):
            i = int(np.searchsorted(ends, k, side="right"))
            return parts[i].words(k - (int(ends[i - 1]) if i else 0))

        rel, depth, body, other = (
            np.concatenate([getattr(p, f) for p in parts]) for f in ("rel", "depth", "body", "other")
        )
        return cls(rel, depth, body, words, other)


def _plane_overlaps(planes, plane_keys, shapes, a) -> OverlapRecords:
    """Free bodies reaching behind a plane wall (records of :class:`OverlapRecords`)."""
    free = np.flatnonzero(a["kind"] == KIND_FREE)
    if not planes or not free.size:
        return OverlapRecords.none()
    sid = a["shape"][free]
    reach = np.array([s.radius for s in shapes])[sid]
    found = []  # per block: rel, depth, body, the plane's index
    for p, plane in enumerate(planes):
        nrm = np.asarray(plane.normal, dtype=np.float64)
        height = a["position"][free] @ nrm - float(nrm @ np.asarray(plane.point))
        near = np.flatnonzero(height < reach)
        for s in np.unique(sid[near]).tolist():
            verts = shapes[s].vertices
            rows = near[sid[near] == s]
            for blk in _blocks(len(rows), len(verts)):
                pick = rows[blk]
                local = np.einsum("pji,j->pi", quat_to_matrix(a["orientation"][free[pick]]), nrm)
                proj = local @ verts.T
                low = height[pick] + proj.min(axis=1)
                thick = proj.max(axis=1) - proj.min(axis=1)
                rel = -low / thick
                h = np.flatnonzero(rel > INITIAL_OVERLAP_WARNING)
                if h.size:
                    found.append((rel[h], -low[h], free[pick[h]], np.full(h.size, p)))
    if not found:
        return OverlapRecords.none()
    rel, depth, body, plane = (np.concatenate(c) for c in zip(*found, strict=True))

    def words(k):
        key, nrm = plane_keys[int(plane[k])], np.asarray(planes[int(plane[k])].normal, dtype=np.float64)
        normal = ", ".join(f"{x:.3g}" for x in nrm)
        return (
            f"behind the plane wall {key}",
            "its thickness",
            f"move it by at least {float(depth[k]):.3g} m along the wall's normal [{normal}], to the side it "
            "points to, or move the wall",
        )

    return OverlapRecords(rel, depth, body, words, plane)


def _candidate_pairs(pos: np.ndarray, rad: np.ndarray, near_big=None, tol: float = 0.0) -> np.ndarray:
    """(K, 2) body pairs whose bounding spheres meet, from k-d trees on the centres.

    Bodies more than 4 times the median radius (container slabs, drums, boulders) would make one
    tree's search radius huge, so they search the tree of the others one by one instead: each gets
    the others in its ball in the tree's order (``tree.indices``, the order of the ball query). Where
    its ball holds a quarter of them or more (a container's slab holds most of a pile), those are
    found by a vectorised pass over the tree's order instead of the query's lists (a Python integer
    each). ``near_big(b, pos_t, rad_idx)``, where given, keeps of a big body ``b``'s candidates (their
    centres as the columns of ``pos_t``, their radii) those it returns True for (a superset of the pairs
    the caller keeps after its own first cut); then the pass tests that alone. Pairs beyond its ball
    that the pass keeps are dropped by the final sphere test like any other, so the pairs and their
    order are those of the ball queries, less the ones ``near_big`` drops. ``tol``: the pass's margin
    on the ball [m].
    """
    from scipy.spatial import cKDTree

    n = len(pos)
    if n < 2:
        return np.zeros((0, 2), dtype=np.int64)
    big_mask = rad > BIG_RADIUS_RATIO * float(np.median(rad))
    small, big = np.flatnonzero(~big_mask), np.flatnonzero(big_mask)
    parts = []
    tree = cKDTree(pos[small]) if small.size else None
    if small.size >= 2:
        parts.append(small[tree.query_pairs(2.0 * float(rad[small].max()), output_type="ndarray")])
    if big.size and small.size:
        reach = rad[big] + float(rad[small].max())
        counts = np.atleast_1d(tree.query_ball_point(pos[big], reach, return_length=True))
        scan = 4 * counts >= small.size
        listed = np.flatnonzero(~scan & (counts > 0))
        lists = tree.query_ball_point(pos[big[listed]], reach[listed], return_sorted=False) if listed.size else []
        found = dict(zip(listed.tolist(), lists, strict=True))
        if scan.any():
            ordered = small[tree.indices]
            pos_ord = np.ascontiguousarray(pos[ordered].T)  # (3, n): a column per body, rows for the passes
            rad_ord = rad[ordered]
        for k, b in enumerate(big.tolist()):
            if k in found:
                idx = small[np.asarray(found[k], dtype=np.int64)]
                if near_big is not None:
                    idx = idx[near_big(b, np.ascontiguousarray(pos[idx].T), rad[idx])]
            elif scan[k]:
                keep = np.zeros(len(ordered), dtype=bool)
                for blk in _blocks(len(ordered), 16):
                    if near_big is not None:
                        keep[blk] = near_big(b, pos_ord[:, blk], rad_ord[blk])
                    else:
                        d2 = sum((pos_ord[c, blk] - pos[b, c]) ** 2 for c in range(3))
                        keep[blk] = d2 <= (reach[k] * (1.0 + 1e-12) + tol) ** 2
                idx = ordered[keep]
            else:
                continue
            if idx.size:
                parts.append(np.column_stack([np.full(idx.size, b, dtype=np.int64), idx]))
    if big.size >= 2:
        if big.size <= 2048:
            ii, jj = np.triu_indices(big.size, 1)
            parts.append(np.column_stack([big[ii], big[jj]]))
        else:
            parts.append(big[cKDTree(pos[big]).query_pairs(2.0 * float(rad[big].max()), output_type="ndarray")])
    if not parts:
        return np.zeros((0, 2), dtype=np.int64)
    pairs = np.concatenate(parts).astype(np.int64)
    d = row_norms(pos[pairs[:, 0]] - pos[pairs[:, 1]])
    return pairs[d < rad[pairs[:, 0]] + rad[pairs[:, 1]]]


def edge_directions(shape) -> np.ndarray:
    """(k, 3) unit edge directions of a shape (body frame), parallel edges once."""
    v = shape.vertices
    loops = shape.faces
    starts = np.concatenate([lp for lp in loops])
    ends = np.concatenate([np.roll(lp, -1) for lp in loops])
    e = v[ends] - v[starts]
    e /= np.linalg.norm(e, axis=1, keepdims=True)
    lead = np.take_along_axis(e, np.argmax(np.abs(e) > 1e-9, axis=1)[:, None], axis=1)
    e *= np.sign(lead)
    return np.unique(np.round(e, 9), axis=0)


def _interval_overlap(a_lo, a_hi, b_lo, b_hi):
    """Overlap of projection intervals (> 0: they overlap) and the thinner one's length."""
    return np.minimum(a_hi - b_lo, b_hi - a_lo), np.minimum(a_hi - a_lo, b_hi - b_lo)


def _sat_depth(shape_a, shape_b, ca, cb, ra, rb, edges_a, edges_b):
    """Penetration depth of P pairs by the separating-axis test (<= 0: apart), over the thinner body's
    thickness along the axis of least overlap. ca, cb: (P, 3) centres; ra, rb: (P, 3, 3) rotations."""
    va, vb = shape_a.vertices, shape_b.vertices
    best = np.full(len(ca), np.inf)
    thin = np.ones(len(ca))

    def take(ov, th):
        ov = np.where(np.isnan(ov), np.inf, ov)
        k = np.argmin(ov, axis=1)
        o = np.take_along_axis(ov, k[:, None], axis=1)[:, 0]
        better = o < best
        best[better] = o[better]
        thin[better] = np.take_along_axis(th, k[:, None], axis=1)[better, 0]

    # Face normals of A, in A's frame (then of B in B's frame): the other body's vertices moved there.
    for s1, s2, c1, c2, r1, r2 in ((shape_a, shape_b, ca, cb, ra, rb), (shape_b, shape_a, cb, ca, rb, ra)):
        n1 = s1.face_normals
        lo1 = (s1.vertices @ n1.T).min(axis=0)
        rel_rot = np.einsum("pji,pjk->pik", r1, r2)
        t = np.einsum("pji,pj->pi", r1, c2 - c1)
        x = s2.vertices @ rel_rot.transpose(0, 2, 1) + t[:, None, :]
        proj = x @ n1.T
        take(*_interval_overlap(lo1, s1.face_offsets, proj.min(axis=1), proj.max(axis=1)))
    # The line of centres, and the cross products of edge directions.
    wa = va @ ra.transpose(0, 2, 1) + ca[:, None, :]
    wb = vb @ rb.transpose(0, 2, 1) + cb[:, None, :]
    axes = (cb - ca)[:, None, :]
    if len(edges_a) * len(edges_b) <= MAX_EDGE_AXES:
        ea = np.einsum("pij,kj->pki", ra, edges_a)
        eb = np.einsum("pij,kj->pki", rb, edges_b)
        cross = np.cross(ea[:, :, None, :], eb[:, None, :, :]).reshape(len(ca), -1, 3)
        axes = np.concatenate([axes, cross], axis=1)
    length = np.linalg.norm(axes, axis=2, keepdims=True)
    with np.errstate(invalid="ignore", divide="ignore"):
        axes = np.where(length > 1e-9, axes / length, np.nan)
    axes_t = np.ascontiguousarray(axes.transpose(0, 2, 1))
    pa = wa @ axes_t
    pb = wb @ axes_t
    take(*_interval_overlap(pa.min(axis=1), pa.max(axis=1), pb.min(axis=1), pb.max(axis=1)))
    return best, thin


def _expand_parts(shapes, a):
    """The bodies with each compound grain replaced by its convex parts: (convex shapes, the
    arrays of the parts, the body each part belongs to), or owner None where all are convex."""
    if not any(is_compound(s) for s in shapes):
        return shapes, a, None
    convex, part, pos, quat, owner = expand_bodies(shapes, a["shape"], a["position"], a["orientation"])
    n = len(a["shape"])
    out = {key: np.asarray(v)[owner] for key, v in a.items() if isinstance(v, np.ndarray) and len(v) == n}
    out.update(shape=part, position=pos, orientation=quat)
    return convex, out, owner


def _rotations(q: np.ndarray) -> np.ndarray:
    """(3, 3, P) rotation matrices of (P, 4) xyzw unit quaternions, the pair along the last axis (where numpy's
    elementwise products and matrix products over a few rows run fast); the first cut and :func:`_apart`
    take them (the test itself takes :func:`~polydem.quaternions.quat_to_matrix`'s)."""
    x, y, z, w = np.ascontiguousarray(q.T)
    xx, yy, zz = x * x, y * y, z * z
    xy, xz, yz, wx, wy, wz = x * y, x * z, y * z, w * x, w * y, w * z
    return np.array(
        [
            [1.0 - 2.0 * (yy + zz), 2.0 * (xy - wz), 2.0 * (xz + wy)],
            [2.0 * (xy + wz), 1.0 - 2.0 * (xx + zz), 2.0 * (yz - wx)],
            [2.0 * (xz - wy), 2.0 * (yz + wx), 1.0 - 2.0 * (xx + yy)],
        ]
    )


def _into(r: np.ndarray, v: np.ndarray) -> np.ndarray:
    """(3, P) ``R^T v`` of (3, 3, P) rotations and (3, P) vectors: world vectors in the bodies' frames."""
    return r[0] * v[0] + r[1] * v[1] + r[2] * v[2]


def _apart(sa, sb, d, ra, rb, tol):
    """Which of P pairs :func:`_sat_depth` finds apart for sure: separated by more than ``tol`` [m] (P,)
    along the line of their centres or a face normal of either body, axes that test always takes. Its
    depth is then at most that axis's overlap, negative, and the pair is no initial overlap; the rest
    take the whole test. Cheaper than it (the support of each body along the axis, without its world
    vertices and edge axes), and computed otherwise: ``tol`` (one, or one per pair) covers the rounding of
    both. ``d``: (3, P)
    centre of B less centre of A [m]; ra, rb: (3, 3, P) rotations (:func:`_rotations`)."""
    length = np.sqrt(d[0] * d[0] + d[1] * d[1] + d[2] * d[2])
    # The test drops an axis of length 1e-9 or less; this one is only trusted well above that.
    line = length > 2e-9
    e = d / np.where(line, length, 1.0)
    pa = sa.vertices @ _into(ra, e)  # (V, P): A's vertices along e, from its centre
    pb = sb.vertices @ _into(rb, e)
    ov = np.minimum(pa.max(axis=0) - pb.min(axis=0) - length, pb.max(axis=0) + length - pa.min(axis=0))
    apart = line & (ov < -tol)
    rest = np.flatnonzero(~apart)
    # Face normals of A in A's frame (then of B in B's): the other body's support along each.
    for s1, s2, r1, r2, sign in ((sa, sb, ra, rb, 1.0), (sb, sa, rb, ra, -1.0)):
        if not rest.size:
            break
        n1 = s1.face_normals
        lo1 = (s1.vertices @ n1.T).min(axis=0)
        r1r, r2r = r1[:, :, rest], r2[:, :, rest]
        t = n1 @ _into(r1r, sign * d[:, rest])  # (F, P): the other's centre along each normal
        rel_rot = sum(r1r[c][:, None] * r2r[c][None] for c in range(3))  # (3, 3, P): R1^T R2
        m = (n1 @ rel_rot.reshape(3, -1)).reshape(len(n1), 3, -1)  # the normals in the other's frame (F, 3, P)
        sep = np.zeros(len(rest), dtype=bool)
        for f in range(len(n1)):
            proj = s2.vertices @ m[f]  # (V, P)
            ov = np.minimum(s1.face_offsets[f] - (t[f] + proj.min(axis=0)), t[f] + proj.max(axis=0) - lo1[f])
            sep |= ov < -(tol if np.ndim(tol) == 0 else tol[rest])
        apart[rest[sep]] = True
        rest = rest[~sep]
    return apart


def _deepest_of_each_pair(rel: np.ndarray, key: np.ndarray) -> np.ndarray:
    """The records to keep of overlaps found in this order (``rel``: their depths, ``key``: their pair of
    bodies, a pair of grains met part by part having several): per pair its deepest (the first of those as
    deep), the pairs in the order of their first record (indices into the arrays)."""
    if len(np.unique(key)) == len(key):
        return np.arange(len(key))
    order = np.lexsort((np.arange(len(key)), -rel, key))
    starts = np.flatnonzero(np.r_[True, key[order][1:] != key[order][:-1]])
    deepest, first = order[starts], np.minimum.reduceat(order, starts)
    return deepest[np.argsort(first)]


def _pair_overlaps(shapes, body_label, a) -> OverlapRecords:
    """Body pairs (one free at least) that overlap (records of :class:`OverlapRecords`, the body the free one).
    A compound grain is tested part by part (its own parts are not tested against each other); a pair of
    grains is one record, the deepest of its parts' (the first of those as deep)."""
    shapes, a, owner = _expand_parts(shapes, a)
    n = len(a["kind"])
    if n < 2:
        return OverlapRecords.none()
    rad = np.array([s.radius for s in shapes])[a["shape"]]
    sid = a["shape"].astype(np.int64)
    # The big bodies' candidates (a container's slabs: most of a pile) are cut down to those near their faces
    # before they are pairs: a superset of the first cut below, whose arithmetic the margin covers.
    scale = float(np.abs(a["position"]).max()) + float(rad.max())
    margin = 1e-9 * scale

    def near_big(b, pos_t, rad_idx):
        sh = shapes[int(sid[b])]
        normals = sh.face_normals @ quat_to_matrix(a["orientation"][b]).T  # world normals, a row each
        gap = normals @ pos_t
        gap -= (normals @ a["position"][b] + sh.face_offsets)[:, None]
        return gap.max(axis=0) < rad_idx + margin

    pairs = _candidate_pairs(a["position"], rad, near_big, margin)
    free = a["kind"] == KIND_FREE
    pairs = pairs[free[pairs[:, 0]] | free[pairs[:, 1]]]
    if owner is not None:
        pairs = pairs[owner[pairs[:, 0]] != owner[pairs[:, 1]]]
    else:
        owner = np.arange(n)
    if not len(pairs):
        return OverlapRecords.none()
    group = sid[pairs[:, 0]] * len(shapes) + sid[pairs[:, 1]]
    groups = np.unique(group)
    if len(groups) > 8:  # the rows of each group in their order, without a pass over all pairs per group
        by_group = np.argsort(group, kind="stable")
        bounds = np.searchsorted(group[by_group], groups, side="left").tolist() + [len(group)]
    edges = {}
    found = []  # per block: rel, depth, the free body, the other (grains: owners)
    # The SAT's rounding grows with the coordinates: its margin with the scene's (1e-12 of its extent: a pair
    # apart by less than that takes the whole test).
    tol = 2e-12 * scale
    for gi, g in enumerate(groups.tolist()):
        sa, sb = shapes[g // len(shapes)], shapes[g % len(shapes)]
        for s in (g // len(shapes), g % len(shapes)):
            if s not in edges:
                edges[s] = edge_directions(shapes[s])
        ea, eb = edges[g // len(shapes)], edges[g % len(shapes)]
        n_axes = 1 + (len(ea) * len(eb) if len(ea) * len(eb) <= MAX_EDGE_AXES else 0)
        per_pair = max(len(sb.vertices) * sa.num_faces, len(sa.vertices) * sb.num_faces)
        per_pair = max(per_pair, (len(sa.vertices) + len(sb.vertices)) * n_axes)
        rows = pairs[group == g] if len(groups) <= 8 else pairs[by_group[bounds[gi] : bounds[gi + 1]]]
        # Most candidates (a small body beside a container slab) are apart along a face normal of
        # one body even when the other is replaced by its bounding sphere: a cheap first cut.
        # (The first cut takes some 9 + faces floats a pair, _apart up to faces x vertices.)
        per_cut = max(9 + sa.num_faces + sb.num_faces, sa.num_faces * len(sb.vertices), sb.num_faces * len(sa.vertices))
        for blk in _blocks(len(rows), per_cut):
            i, j = rows[blk, 0], rows[blk, 1]
            d = np.ascontiguousarray((a["position"][j] - a["position"][i]).T)  # (3, P)
            ra = _rotations(a["orientation"][i])
            gap = (sa.face_normals @ _into(ra, d) - sa.face_offsets[:, None]).max(axis=0)
            near = np.flatnonzero(gap < sb.radius)
            if near.size:
                rb = _rotations(a["orientation"][j[near]])
                gap = (sb.face_normals @ _into(rb, -d[:, near]) - sb.face_offsets[:, None]).max(axis=0)
                keep = gap < sa.radius
                near, rb = near[keep], rb[:, :, keep]
            if not near.size:
                continue
            i, j, d, ra = i[near], j[near], d[:, near], ra[:, :, near]
            # Then the pairs apart along an axis of the test for sure (most of a loose pile's): the rest take it.
            rest = np.flatnonzero(~_apart(sa, sb, d, ra, rb, tol))
            if not rest.size:
                continue
            i, j = i[rest], j[rest]
            ra = quat_to_matrix(a["orientation"][i])
            rb = quat_to_matrix(a["orientation"][j])
            for sub in _blocks(len(i), 4 * per_pair):
                ii, jj = i[sub], j[sub]
                depth, thin = _sat_depth(sa, sb, a["position"][ii], a["position"][jj], ra[sub], rb[sub], ea, eb)
                rel = depth / thin
                h = np.flatnonzero(rel > INITIAL_OVERLAP_WARNING)
                if h.size:
                    first = free[ii[h]]
                    b1 = owner[np.where(first, ii[h], jj[h])]
                    b2 = owner[np.where(first, jj[h], ii[h])]
                    found.append((rel[h], depth[h], b1, b2))
    if not found:
        return OverlapRecords.none()
    rel, depth, b1, b2 = (np.concatenate(c) for c in zip(*found, strict=True))
    keep = _deepest_of_each_pair(rel, b1 * len(owner) + b2)
    return pair_records(rel[keep], depth[keep], b1[keep], b2[keep], body_label)


def pair_records(rel, depth, b1, b2, body_label) -> OverlapRecords:
    """:class:`OverlapRecords` of overlapping body pairs: per pair its depth over the thinner body's thickness
    (``rel``), its depth [m], the free body (``b1``, the record's body) and the other (``b2``)."""

    def words(k):
        return (
            f"into {body_label(int(b2[k]))}",
            "the thinner one's thickness",
            f"move the two apart by at least {float(depth[k]):.3g} m",
        )

    return OverlapRecords(rel, depth, b1, words, b2)


def check_initial_overlaps(scene, a, pair_overlaps: OverlapRecords | None = None) -> list[str]:
    """Free bodies of ``scene`` that start behind a plane wall or inside another body (see :meth:`Scene.validate`);
    ``a`` holds its body arrays. ``pair_overlaps``: the body pairs' records found already (on the device, from a
    simulation's first broad phase: :mod:`polydem.overlap_check`), else they are searched here.

    Plane walls: the exact depth of the body's lowest vertex behind the plane, over the body's
    thickness along the normal. Body pairs: candidates from a k-d tree on the centres (bounding
    spheres that meet, one body free), then the separating-axis test over both bodies' face
    normals, the line of centres and, for bodies with few edge directions, the cross products
    of their edges: the smallest overlap of the projections is the penetration depth (an upper
    bound where edge axes are skipped), taken over the thinner body's thickness along that axis.
    """
    shapes = list(scene.shapes.values())
    if pair_overlaps is None:
        pair_overlaps = _pair_overlaps(shapes, scene.body_label, a)
    records = OverlapRecords.join([_plane_overlaps(scene.planes, scene.plane_keys, shapes, a), pair_overlaps])
    return report_overlaps(
        scene,
        records,
        f"initial overlaps of more than {INITIAL_OVERLAP_WARNING:.0%} of a body's thickness, pushed apart at the start",
        "move the bodies apart",
    )


def report_overlaps(scene, records, head: str, fix: str) -> list[str]:
    """Initial overlaps (:class:`OverlapRecords`, or a list of ``(share of the basis, depth [m], body, where,
    basis, fix)``): a SceneError for the deepest beyond INITIAL_OVERLAP_ERROR, else one warning
    ``"<count> <head>: <the three deepest>; <fix>"`` (plane walls, pairs of bodies and mesh walls alike; of
    records as deep, to 12 decimals of their share, the lowest body first, then the lowest of what it overlaps:
    the same message whatever order a search found them in, on the host or a device)."""
    if not isinstance(records, OverlapRecords):
        records = OverlapRecords.of_tuples(records)
    if not len(records):
        return []
    order = np.lexsort((records.other, records.body, -np.round(records.rel, 12)))
    deep = int(np.count_nonzero(records.rel > INITIAL_OVERLAP_ERROR))
    if deep:
        k = int(order[0])
        rel, depth, i = float(records.rel[k]), float(records.depth[k]), int(records.body[k])
        what, basis, fix_deep = records.words(k)
        more = f" ({deep - 1} more bodies start this deep)" if deep > 1 else ""
        share = "wholly" if rel >= 1.0 else f"{rel:.0%} of {basis}"
        raise scene.error(
            f"{scene.body_label(i)} starts {depth:.3g} m {what} ({share}): the contact would throw it out at a "
            f"high speed{more}; {fix_deep}",
            f"bodies[{i}].position",
        )
    top = [int(k) for k in order[:3]]
    shown = "; ".join(
        f"{scene.body_label(int(records.body[k]))} {float(records.depth[k]):.3g} m {records.words(k)[0]} "
        f"({float(records.rel[k]):.1%})"
        for k in top
    )
    more = f", and {len(records) - 3} more" if len(records) > 3 else ""
    return [f"{len(records)} {head}: {shown}{more}; {fix}"]
