"""Initial overlaps: free bodies that start behind a plane wall or inside another body."""

from __future__ import annotations

import numpy as np

from polydem.compound import expand_bodies, is_compound
from polydem.quaternions import quat_conjugate, quat_rotate, quat_to_matrix
from polydem.scene.bodies import KIND_FREE

# Initial overlaps, as a fraction of the thinner body's thickness along the separating axis.
INITIAL_OVERLAP_WARNING = 0.01
INITIAL_OVERLAP_ERROR = 0.5

_BLOCK = 1 << 22  # floats per block of the vectorised overlap tests (32 MiB)
_MAX_EDGE_AXES = 4096  # edge-direction pairs tested per body pair; beyond, face normals only


def _blocks(n: int, per_item: int):
    step = max(1, _BLOCK // max(1, per_item))
    for start in range(0, n, step):
        yield slice(start, min(n, start + step))


def _plane_overlaps(planes, plane_keys, shapes, a) -> list[tuple]:
    """(relative depth, depth, body, where, of what, fix) of free bodies reaching behind a plane wall."""
    free = np.flatnonzero(a["kind"] == KIND_FREE)
    if not planes or not free.size:
        return []
    sid = a["shape"][free]
    reach = np.array([s.radius for s in shapes])[sid]
    out = []
    for plane, key in zip(planes, plane_keys, strict=True):
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
                for h in np.flatnonzero(rel > INITIAL_OVERLAP_WARNING).tolist():
                    normal = ", ".join(f"{x:.3g}" for x in nrm)
                    out.append(
                        (
                            float(rel[h]),
                            float(-low[h]),
                            int(free[pick[h]]),
                            f"behind the plane wall {key}",
                            "its thickness",
                            f"move it by at least {-low[h]:.3g} m along the wall's normal [{normal}], to the side it "
                            "points to, or move the wall",
                        )
                    )
    return out


def _candidate_pairs(pos: np.ndarray, rad: np.ndarray) -> np.ndarray:
    """(K, 2) body pairs whose bounding spheres meet, from k-d trees on the centres.

    Bodies more than 4 times the median radius (container slabs, drums, boulders) would make one
    tree's search radius huge, so they search the tree of the others one by one instead.
    """
    from scipy.spatial import cKDTree

    n = len(pos)
    if n < 2:
        return np.zeros((0, 2), dtype=np.int64)
    big_mask = rad > 4.0 * float(np.median(rad))
    small, big = np.flatnonzero(~big_mask), np.flatnonzero(big_mask)
    parts = []
    tree = cKDTree(pos[small]) if small.size else None
    if small.size >= 2:
        parts.append(small[tree.query_pairs(2.0 * float(rad[small].max()), output_type="ndarray")])
    if big.size and small.size:
        found = tree.query_ball_point(pos[big], rad[big] + float(rad[small].max()), return_sorted=False)
        counts = np.fromiter((len(x) for x in found), dtype=np.int64, count=len(big))
        if counts.sum():
            others = np.concatenate([np.asarray(x, dtype=np.int64) for x in found if len(x)])
            parts.append(np.column_stack([np.repeat(big, counts), small[others]]))
    if big.size >= 2:
        if big.size <= 2048:
            ii, jj = np.triu_indices(big.size, 1)
            parts.append(np.column_stack([big[ii], big[jj]]))
        else:
            parts.append(big[cKDTree(pos[big]).query_pairs(2.0 * float(rad[big].max()), output_type="ndarray")])
    if not parts:
        return np.zeros((0, 2), dtype=np.int64)
    pairs = np.concatenate(parts).astype(np.int64)
    d = np.linalg.norm(pos[pairs[:, 0]] - pos[pairs[:, 1]], axis=1)
    return pairs[d < rad[pairs[:, 0]] + rad[pairs[:, 1]]]


def _edge_directions(shape) -> np.ndarray:
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
    if len(edges_a) * len(edges_b) <= _MAX_EDGE_AXES:
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


def _pair_overlaps(shapes, body_label, a) -> list[tuple]:
    """(relative depth, depth, body, where, of what, fix) of body pairs (one free at least) that overlap.
    A compound grain is tested part by part (its own parts are not tested against each other)."""
    shapes, a, owner = _expand_parts(shapes, a)
    n = len(a["kind"])
    if n < 2:
        return []
    rad = np.array([s.radius for s in shapes])[a["shape"]]
    pairs = _candidate_pairs(a["position"], rad)
    free = a["kind"] == KIND_FREE
    pairs = pairs[free[pairs[:, 0]] | free[pairs[:, 1]]]
    if owner is not None:
        pairs = pairs[owner[pairs[:, 0]] != owner[pairs[:, 1]]]
    else:
        owner = np.arange(n)
    if not len(pairs):
        return []
    sid = a["shape"].astype(np.int64)
    group = sid[pairs[:, 0]] * len(shapes) + sid[pairs[:, 1]]
    edges = {}
    out = []
    seen = {}  # body pair -> the deepest record kept (a compound pair meets part by part)
    for g in np.unique(group).tolist():
        sa, sb = shapes[g // len(shapes)], shapes[g % len(shapes)]
        for s in (g // len(shapes), g % len(shapes)):
            if s not in edges:
                edges[s] = _edge_directions(shapes[s])
        ea, eb = edges[g // len(shapes)], edges[g % len(shapes)]
        n_axes = 1 + (len(ea) * len(eb) if len(ea) * len(eb) <= _MAX_EDGE_AXES else 0)
        per_pair = max(len(sb.vertices) * sa.num_faces, len(sa.vertices) * sb.num_faces)
        per_pair = max(per_pair, (len(sa.vertices) + len(sb.vertices)) * n_axes)
        rows = pairs[group == g]
        # Most candidates (a small body beside a container slab) are apart along a face normal of
        # one body even when the other is replaced by its bounding sphere: a cheap first cut.
        for blk in _blocks(len(rows), 9 + sa.num_faces + sb.num_faces):
            i, j = rows[blk, 0], rows[blk, 1]
            d = a["position"][j] - a["position"][i]
            gap = (quat_rotate(quat_conjugate(a["orientation"][i]), d) @ sa.face_normals.T - sa.face_offsets).max(
                axis=1
            )
            near = np.flatnonzero(gap < sb.radius)
            if near.size:
                d_local = quat_rotate(quat_conjugate(a["orientation"][j[near]]), -d[near])
                gap = (d_local @ sb.face_normals.T - sb.face_offsets).max(axis=1)
                near = near[gap < sa.radius]
            if not near.size:
                continue
            i, j = i[near], j[near]
            ra = quat_to_matrix(a["orientation"][i])
            rb = quat_to_matrix(a["orientation"][j])
            for sub in _blocks(len(i), 4 * per_pair):
                ii, jj = i[sub], j[sub]
                depth, thin = _sat_depth(sa, sb, a["position"][ii], a["position"][jj], ra[sub], rb[sub], ea, eb)
                rel = depth / thin
                for h in np.flatnonzero(rel > INITIAL_OVERLAP_WARNING).tolist():
                    b1, b2 = (int(ii[h]), int(jj[h])) if free[ii[h]] else (int(jj[h]), int(ii[h]))
                    b1, b2 = int(owner[b1]), int(owner[b2])
                    if (b1, b2) in seen and seen[(b1, b2)] >= rel[h]:
                        continue
                    seen[(b1, b2)] = float(rel[h])
                    out.append(
                        (
                            float(rel[h]),
                            float(depth[h]),
                            b1,
                            f"into {body_label(b2)}",
                            "the thinner one's thickness",
                            f"move the two apart by at least {depth[h]:.3g} m",
                        )
                    )
    if len(seen) < len(out):  # keep the deepest record of each body pair
        best = {}
        for r in out:
            key = (r[2], r[3])
            if key not in best or r[0] > best[key][0]:
                best[key] = r
        out = list(best.values())
    return out


def check_initial_overlaps(scene, a) -> list[str]:
    """Free bodies of ``scene`` that start behind a plane wall or inside another body (see :meth:`Scene.validate`);
    ``a`` holds its body arrays.

    Plane walls: the exact depth of the body's lowest vertex behind the plane, over the body's
    thickness along the normal. Body pairs: candidates from a k-d tree on the centres (bounding
    spheres that meet, one body free), then the separating-axis test over both bodies' face
    normals, the line of centres and, for bodies with few edge directions, the cross products
    of their edges: the smallest overlap of the projections is the penetration depth (an upper
    bound where edge axes are skipped), taken over the thinner body's thickness along that axis.
    """
    shapes = list(scene.shapes.values())
    records = _plane_overlaps(scene.planes, scene.plane_keys, shapes, a) + _pair_overlaps(shapes, scene.body_label, a)
    return report_overlaps(
        scene,
        records,
        f"initial overlaps of more than {INITIAL_OVERLAP_WARNING:.0%} of a body's thickness, pushed apart at the start",
        "move the bodies apart",
    )


def report_overlaps(scene, records, head: str, fix: str) -> list[str]:
    """Initial overlaps ``(share of the basis, depth [m], body, where, basis, fix)``: a SceneError for the
    deepest beyond INITIAL_OVERLAP_ERROR, else one warning ``"<count> <head>: <the three deepest>; <fix>"``
    (plane walls, pairs of bodies and mesh walls alike)."""
    if not records:
        return []
    records.sort(key=lambda r: -r[0])
    deep = [r for r in records if r[0] > INITIAL_OVERLAP_ERROR]
    if deep:
        rel, depth, i, what, basis, fix_deep = deep[0]
        more = f" ({len(deep) - 1} more bodies start this deep)" if len(deep) > 1 else ""
        share = "wholly" if rel >= 1.0 else f"{rel:.0%} of {basis}"
        raise scene.error(
            f"{scene.body_label(i)} starts {depth:.3g} m {what} ({share}): the contact would throw it out at a "
            f"high speed{more}; {fix_deep}",
            f"bodies[{i}].position",
        )
    shown = "; ".join(f"{scene.body_label(i)} {d:.3g} m {what} ({rel:.1%})" for rel, d, i, what, _, _ in records[:3])
    more = f", and {len(records) - 3} more" if len(records) > 3 else ""
    return [f"{len(records)} {head}: {shown}{more}; {fix}"]
