"""How long one warp of the pair kernel takes, and what its 32 pairs' differences cost it (latency at small sizes).

Below about 1e4 grains the step is the pair kernel's slowest warp (BENCHMARKS.md 27b: at 1e3 cubes the pair kernel
is 0.17 of the graph's 0.20 ms a step): a warp runs its 32 threads in lock step, so it takes as long as the union
of their paths through the clipping loops. This script times launches of the engine's overlap kernel (the pair
kernel's geometry, ``benchmarks/pair_kernel.py``) that are one wave or less, with CUDA events:

* ``one``: a single touching pair (one thread of one warp);
* ``same32``: 32 copies of that pair in one warp (the same path: the warp's own latency);
* ``diff32``: 32 different touching pairs in one warp (their paths' union);
* ``sortedN``: packedN's pairs sorted by the kind of contact (how many corners of each lie in the other);
* ``worksortedN``: packedN's pairs sorted by their path through the clipping (the active faces of each body, then the
  polygon vertices read: the measuring variant's word), and with ``--throughput M`` the same for M pairs, many
  waves (``throughputM`` against ``throughputM_worksorted``): whether warps of like paths would be faster;
* ``packedN`` / ``spreadN``: N different touching pairs, packed 32 to a warp or one to a warp (the other 31 lanes
  far apart, leaving at the bounding-sphere test); ``spreadN_lanesL``: one pair every L lanes.

With ``--setup-only`` each case is timed again with the kernel stopped after the pairs' set-up (the culling of faces
and planes, the flat contact, the apex and the frame; make_geometry's ``setup_only``): the part of a pair's latency
that clipping its faces on several lanes would leave.

    python benchmarks/pair_latency.py --device cuda:0
"""

import argparse
import json
import os
import sys

import numpy as np
import warp as wp
from pair_kernel import make_pairs, rotate, shape_library, time_kernel

from polydem.shapeset import ShapeSet

HERE = os.path.dirname(os.path.abspath(__file__))
sys.path.insert(0, HERE)
from _meta import run_meta  # noqa: E402


def event_time(shapes, pa, pb, pose_scalar, repeats, count_work=False, setup_only=False):
    """Median GPU milliseconds of the overlap kernel over the pairs (pa, pb), by CUDA events (the CPU: its wall
    time), and how many touch; with ``count_work`` (the measuring variant) also each pair's path word; with
    ``setup_only`` the variant that stops after each pair's set-up."""
    seconds, outs = time_kernel(shapes, pa, pb, max(repeats, 1), pose_scalar=pose_scalar, events=True,
                                count_work=count_work, setup_only=setup_only)  # fmt: skip
    touching = int((outs[0] > 0).sum())
    if count_work:
        return 1e3 * seconds, touching, outs[-1]
    return 1e3 * seconds, touching


def spread(pa, pb, lanes):
    """The pairs one to a warp: lane 0 of each warp a pair of (pa, pb), the other lanes copies of it moved far apart."""
    n = len(pa)
    far_b = pb.copy()
    far_b[:, :3] += 1000.0
    out_a = np.repeat(pa, lanes, axis=0)
    out_b = np.repeat(far_b, lanes, axis=0)
    out_b[::lanes] = pb
    assert len(out_a) == n * lanes
    return out_a, out_b


def inside_counts(shape, pa, pb):
    """Per pair, how many of B's vertices lie inside A and how many of A's inside B (the contact's kind: a corner
    in a face, edges crossing, faces on faces), from the poses (xyz, xyzw)."""
    verts = np.asarray(shape.vertices, dtype=np.float64)
    normals = np.asarray(shape.face_normals, dtype=np.float64)
    offsets = np.array([normals[f] @ verts[loop[0]] for f, loop in enumerate(shape.faces)])

    def count(p_in, p_of):
        # p_of's vertices in p_in's frame, against p_in's planes
        n, k = len(p_in), len(verts)
        q_of = np.repeat(p_of[:, 3:], k, axis=0)
        q_in = np.repeat(p_in[:, 3:], k, axis=0)
        v = rotate(q_of, np.tile(verts, (n, 1))) + np.repeat(p_of[:, :3] - p_in[:, :3], k, axis=0)
        local = rotate(q_in * np.array([-1, -1, -1, 1]), v)
        inside = (local @ normals.T <= offsets[None]).all(axis=1)
        return inside.reshape(n, k).sum(axis=1)

    return count(pa, pb), count(pb, pa)


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--device", default="cuda:0")
    ap.add_argument("--shapes", default="cube,rock20")
    ap.add_argument("--depth", type=float, default=0.01, help="depth of the touching pairs (fraction of the size)")
    ap.add_argument("--sizes", default="256,1024", help="N of packedN and spreadN")
    ap.add_argument("--repeats", type=int, default=20)
    ap.add_argument("--lanes", default="32", help="lanes per pair of spreadN (32: one pair to a warp)")
    ap.add_argument("--throughput", type=int, default=0, help="M: also M touching pairs, shuffled and by path")
    ap.add_argument(
        "--setup-only", action="store_true",
        help="also time each case with the kernel stopped after the pairs' set-up (make_geometry's setup_only)",
    )  # fmt: skip
    ap.add_argument("--out", default=os.path.join(HERE, "results", "issue27", "pair_latency.json"))
    args = ap.parse_args()
    wp.config.quiet = True
    dev = wp.get_device(args.device)
    lib = shape_library()
    rows = []
    for name in args.shapes.split(","):
        shape = lib[name]
        rng = np.random.default_rng(7)
        sizes = [int(s) for s in args.sizes.split(",")]
        n_max = max(max(sizes), 32)
        pa, pb = make_pairs(shape, 2 * n_max, args.depth, rng, dev)
        pa, pb = pa[:n_max], pb[:n_max]  # the touching half
        shapes = ShapeSet([shape], device=dev, precision="float32")
        cases = {
            "one": (pa[:1], pb[:1]),
            "same32": (np.repeat(pa[:1], 32, axis=0), np.repeat(pb[:1], 32, axis=0)),
            "diff32": (pa[:32], pb[:32]),
        }
        kind_b, kind_a = inside_counts(shape, pa, pb)
        _, _, work = event_time(shapes, pa, pb, wp.float64, 1, count_work=True)
        faces_1, faces_2, steps = (work >> 1) & 255, (work >> 9) & 255, work >> 17
        by_work = np.lexsort((steps, faces_2, faces_1))
        pct = [np.percentile(x, [5, 50, 95]).tolist() for x in (faces_1, faces_2, steps)]
        print(f"{name}: active faces of body 1 {pct[0]}, of body 2 {pct[1]}, vertices read {pct[2]} "
              "(5th, 50th, 95th percentile)")  # fmt: skip
        for n in sizes:
            cases[f"packed{n}"] = (pa[:n], pb[:n])
            order = np.lexsort((kind_a[:n], kind_b[:n]))  # the same kinds of contact side by side
            cases[f"sorted{n}"] = (pa[:n][order], pb[:n][order])
            keep = by_work[by_work < n]  # the first n pairs, in the order of their paths
            cases[f"worksorted{n}"] = (pa[keep], pb[keep])
            kinds, counts = np.unique(np.stack([kind_b[:n], kind_a[:n]], 1), axis=0, return_counts=True)
            print(
                f"{name}: kinds of contact (B's corners in A, A's in B): count "
                + ", ".join(f"{tuple(k)}: {c}" for k, c in zip(kinds.tolist(), counts.tolist(), strict=True))
            )
            for lanes in [int(x) for x in args.lanes.split(",")]:
                cases[f"spread{n}" if lanes == 32 else f"spread{n}_lanes{lanes}"] = spread(pa[:n], pb[:n], lanes)
        if args.throughput:
            m = args.throughput
            reps = -(-m // len(pa))  # the touching pairs again, as many times as it takes
            big_a, big_b = np.tile(pa, (reps, 1))[:m], np.tile(pb, (reps, 1))[:m]
            big_work = np.tile(work, reps)[:m]
            w_order = np.lexsort((big_work >> 17, (big_work >> 9) & 255, (big_work >> 1) & 255))
            shuffle = np.random.default_rng(3).permutation(m)
            cases[f"throughput{m}"] = (big_a[shuffle], big_b[shuffle])
            cases[f"throughput{m}_worksorted"] = (big_a[w_order], big_b[w_order])
        for case, (a, b) in cases.items():
            ms, touching = event_time(shapes, a, b, wp.float64, args.repeats)
            row = {"shape": name, "case": case, "threads": len(a), "touching": touching, "ms": ms}
            setup = ""
            if args.setup_only:
                row["setup_ms"] = event_time(shapes, a, b, wp.float64, args.repeats, setup_only=True)[0]
                setup = f", set-up alone {1e3 * row['setup_ms']:8.1f} us ({row['setup_ms'] / ms:.0%})"
            rows.append(row)
            print(f"{name:8s} {case:12s} threads {row['threads']:7d} touching {touching:5d}: {1e3 * ms:8.1f} us{setup}")
    record = {"meta": run_meta(dev), "args": vars(args), "rows": rows}
    os.makedirs(os.path.dirname(args.out), exist_ok=True)
    with open(args.out, "w") as f:
        json.dump(record, f, indent=1)
    print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
