"""Error of the compound contact (the sum over part pairs) against the exact union, on test shapes.

A compound grain's contact sums the exact overlaps of its parts with the other grain. Where parts of
the grain overlap each other, a region of the other grain inside both counts twice: the volume V
and its gradient S_A are too large there. This script measures by how much, against an independent
float64 reference: the overlap of the other grain (a cube of edge H) with the union of the parts, by
inclusion-exclusion over the convex pieces (part_i ∩ part_j ∩ ... ∩ cube, each the intersection of
their half-spaces, scipy), and S_A as its gradient by central differences.

Contacts are sampled as DEM contacts are: the cube, randomly turned, approaches a random point of
the grain's surface along the surface's normal until the exact overlap is a set fraction of the
cube's volume (1e-4 to 1e-2, log-uniform). For each shape it reports the share of contacts with any
error and the median, 90th percentile and largest relative errors of V and of S_A.

Shapes: ``L-touching`` (an L of a 2-cell bar and a cell: parts only touch, the control),
``L-overlap`` (two 2-cell bars that share the corner cell), ``cross`` (three 3-cell bars through one
cell), ``coacd-T`` (a T-shaped mesh cut by CoACD, whose parts may overlap a little; also reported:
how far the union of its parts is from the mesh).

    python benchmarks/compound_error.py --samples 300

Writes JSON to ``--out`` (benchmarks/results/issue13/compound_error.json).
"""

import argparse
import json
from pathlib import Path

import numpy as np
import trimesh
import warp as wp
from scipy.optimize import linprog
from scipy.spatial import ConvexHull, HalfspaceIntersection

import polydem
from polydem import CompoundShape, ConvexShape
from polydem.compound import place
from polydem.quaternions import quat_to_matrix

H = 0.01


def shapes():
    bar2 = ConvexShape.box(2 * H, H, H)
    out = {
        "L-touching": CompoundShape([place(bar2, (H / 2, 0, 0)), place(ConvexShape.box(H), (0, H, 0))]),
        "L-overlap": CompoundShape([place(bar2, (H / 2, 0, 0)), place(ConvexShape.box(H, 2 * H, H), (0, H / 2, 0))]),
        "cross": CompoundShape([ConvexShape.box(*(3 * H if k == a else H for k in range(3))) for a in range(3)]),
    }
    try:
        t = trimesh.boolean.union(
            [trimesh.creation.box((3 * H, H, H)), trimesh.creation.box((H, 3 * H, H)).apply_translation((0, -H, 0))]
        )
        out["coacd-T"] = CompoundShape.from_mesh(t, decompose="coacd", threshold=0.02, seed=0)
        out["coacd-T"].mesh_volume = t.volume
    except Exception as exc:  # coacd or manifold3d missing
        print(f"coacd-T skipped: {exc}")
    return out


def halfspaces(vertices):
    """(m, 4) rows (n, -d), n.x - d <= 0 inside, of the hull of ``vertices``."""
    eq = ConvexHull(vertices).equations
    return eq


def piece_volume(spaces):
    """Volume of the intersection of half-space sets (0 if it has no interior)."""
    a = np.vstack(spaces)
    norm = np.linalg.norm(a[:, :3], axis=1)
    res = linprog([0, 0, 0, -1], A_ub=np.hstack([a[:, :3], norm[:, None]]), b_ub=-a[:, 3],
                  bounds=[(None, None)] * 3 + [(None, H)], method="highs")  # fmt: skip
    if res.status != 0 or -res.fun <= 1e-12 * H:
        return 0.0, False
    pts = HalfspaceIntersection(a, res.x[:3]).intersections
    try:
        return ConvexHull(pts).volume, True
    except Exception:
        return 0.0, False


def union_overlap(part_spaces, cube_spaces):
    """Exact volume of (union of parts) ∩ cube by inclusion-exclusion over the parts."""
    total = 0.0

    def rec(members, space, sign):
        nonlocal total
        for j in range(members[-1] + 1, len(part_spaces)):
            v, ok = piece_volume([space, part_spaces[j]])
            if ok:
                total += -sign * v
                rec([*members, j], np.vstack([space, part_spaces[j]]), -sign)

    for i, sp in enumerate(part_spaces):
        both = np.vstack([sp, cube_spaces])
        v, ok = piece_volume([both])
        if ok:
            total += v
            rec([i], both, 1.0)
    return total


def world_part_spaces(grain):
    return [halfspaces(v) for v in grain.part_vertices()]


def cube_spaces(pose):
    c = ConvexShape.box(H)
    v = c.vertices @ quat_to_matrix(pose[3:]).T + pose[:3]
    return halfspaces(v)


def exact(grain_spaces, pose, eps=1e-7):
    v = union_overlap(grain_spaces, cube_spaces(pose))
    grad = np.zeros(3)
    for k in range(3):
        # moving the grain by +e equals moving the cube by -e
        p, m = pose.copy(), pose.copy()
        p[k] -= eps
        m[k] += eps
        grad[k] = (union_overlap(grain_spaces, cube_spaces(p)) - union_overlap(grain_spaces, cube_spaces(m))) / (
            2 * eps
        )
    return v, grad


def sample_contacts(grain, n, rng):
    """Cube poses (in the grain's body frame, grain at the origin) at overlaps of 1e-4..1e-2 H^3."""
    surface = grain.to_trimesh()
    spaces = world_part_spaces(grain)
    points, faces = trimesh.sample.sample_surface(surface, 4 * n, seed=int(rng.integers(1 << 30)))
    normals = surface.face_normals[faces]
    poses = []
    for p, nrm in zip(points, normals, strict=True):
        if len(poses) == n:
            break
        q = rng.normal(size=4)
        q /= np.linalg.norm(q)
        target = 10 ** rng.uniform(-4, -2) * H**3
        lo, hi = 0.0, 2.0 * H  # distance of the cube's centre from the point along the normal

        def vol(s, p=p, nrm=nrm, q=q):
            return union_overlap(spaces, cube_spaces(np.concatenate([p + s * nrm, q])))

        if vol(lo) <= target or vol(hi) > 0.0:
            continue
        for _ in range(40):
            mid = 0.5 * (lo + hi)
            if vol(mid) > target:
                lo = mid
            else:
                hi = mid
        poses.append(np.concatenate([p + lo * nrm, q]))
    return np.array(poses)


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--samples", type=int, default=300)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--out", default="benchmarks/results/issue13/compound_error.json")
    args = ap.parse_args()
    wp.config.quiet = True
    rng = np.random.default_rng(args.seed)
    cube = ConvexShape.box(H)
    report = {}
    for name, grain in shapes().items():
        poses = sample_contacts(grain, args.samples, rng)
        spaces = world_part_spaces(grain)
        ident = np.array([0, 0, 0, 0, 0, 0, 1.0])
        got = polydem.overlap(grain, ident, cube, poses, frame="body", device="cpu", precision="float64")
        ex = np.array([exact(spaces, p)[0] for p in poses])
        grads = np.array([exact(spaces, p)[1] for p in poses])
        ev = np.abs(got.volume - ex) / ex
        es = np.linalg.norm(got.area_vector - grads, axis=1) / np.linalg.norm(grads, axis=1)
        row = {
            "parts": grain.num_parts,
            "overlapping_parts": bool(grain.overlapping),
            "contacts": len(poses),
            "share_with_error_above_1e-6": float(np.mean(ev > 1e-6)),
            "volume_rel_error": {
                "median": float(np.median(ev)),
                "p90": float(np.percentile(ev, 90)),
                "max": float(ev.max()),
            },
            "area_vector_rel_error": {
                "median": float(np.median(es)),
                "p90": float(np.percentile(es, 90)),
                "max": float(es.max()),
            },
        }
        if hasattr(grain, "mesh_volume"):
            row["union_vs_mesh_volume"] = grain.volume / grain.mesh_volume - 1.0
        report[name] = row
        print(
            f"{name:>11}: {grain.num_parts} parts, {len(poses)} contacts, "
            f"{row['share_with_error_above_1e-6']:.0%} with error; "
            f"V rel err median {row['volume_rel_error']['median']:.2e} p90 {row['volume_rel_error']['p90']:.2e} "
            f"max {row['volume_rel_error']['max']:.2e}; S_A median {row['area_vector_rel_error']['median']:.2e} "
            f"p90 {row['area_vector_rel_error']['p90']:.2e} max {row['area_vector_rel_error']['max']:.2e}"
            + (f"; union/mesh volume - 1 = {row['union_vs_mesh_volume']:.2e}" if "union_vs_mesh_volume" in row else "")
        )
    out = Path(args.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(
        json.dumps({"meta": {"samples": args.samples, "seed": args.seed, "H": H}, "shapes": report}, indent=1)
    )
    print(f"wrote {out}")


if __name__ == "__main__":
    main()
