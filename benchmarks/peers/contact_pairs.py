"""Fixed contact pairs for comparing contact geometry with other codes: polydem's side.

Pairs of cubes and of 20-vertex rocks (edge / size 1 m) in random orientations, along random lines of
centres, pushed 0.1%, 1% and 10% of the size past first touch (the pair-kernel benchmark's
``make_pairs``: first touch by bisection on the float64 kernel). For every pair this writes both
bodies' world vertices and polydem's exact energy-model quantities from ``polydem.overlap`` in
float64 (and float32, to show its rounding): overlap volume V, area vector S_A (the gradient of V
under translation of A), unit normal S_A/|S_A| from A into B, overlap centroid, contact point.

    python benchmarks/peers/contact_pairs.py                  # -> results/peers/pairs.json
    yade -n -j 1 -x benchmarks/peers/yade_pairs.py            # Yade's geometry of the same pairs
    python benchmarks/peers/compare.py                        # the comparison
"""

import argparse
import json
import os
import sys

import numpy as np

HERE = os.path.dirname(os.path.abspath(__file__))
BENCH = os.path.dirname(HERE)
OUT_DIR = os.path.join(BENCH, "results", "peers")


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--per-case", type=int, default=8, help="touching pairs per shape and depth")
    ap.add_argument("--depths", default="0.001,0.01,0.1")
    ap.add_argument("--out", default=os.path.join(OUT_DIR, "pairs.json"))
    args = ap.parse_args()

    import warp as wp

    wp.config.quiet = True
    wp.config.log_level = wp.LOG_WARNING
    sys.path.insert(0, BENCH)
    import pair_kernel  # benchmarks/pair_kernel.py: the pose generator

    import polydem

    shapes = {"cube": polydem.ConvexShape.box(1.0), "rock20": polydem.ConvexShape.rock(n_points=20, size=1.0, seed=1)}
    pairs = []
    for name, shape in shapes.items():
        verts = np.asarray(shape.vertices)
        for depth in (float(d) for d in args.depths.split(",")):
            rng = np.random.default_rng(2024)
            pa, pb = pair_kernel.make_pairs(shape, 2 * args.per_case, depth, rng, "cpu")
            pa, pb = pa[: args.per_case], pb[: args.per_case]  # the touching half
            res = {
                p: polydem.overlap(shape, pa, shape, pb, frame="body", device="cpu", precision=p)
                for p in ("float64", "float32")
            }
            for i in range(args.per_case):
                r64 = res["float64"]
                r32 = res["float32"]
                wa = pair_kernel.rotate(np.repeat(pa[i : i + 1, 3:], len(verts), axis=0), verts) + pa[i, :3]
                wb = pair_kernel.rotate(np.repeat(pb[i : i + 1, 3:], len(verts), axis=0), verts) + pb[i, :3]
                pairs.append(
                    {
                        "shape": name,
                        "size": 2.0 * shape.radius,
                        "depth": depth,
                        "pose_a": pa[i].tolist(),
                        "pose_b": pb[i].tolist(),
                        "world_vertices_a": wa.tolist(),
                        "world_vertices_b": wb.tolist(),
                        "volume": float(r64.volume[i]),
                        "area_vector": r64.area_vector[i].tolist(),
                        "normal": r64.normal[i].tolist(),
                        "centroid": r64.centroid[i].tolist(),
                        "contact_point": r64.contact_point[i].tolist(),
                        "enclosed": bool(r64.enclosed[i]),
                        "float32": {
                            "volume": float(r32.volume[i]),
                            "area_vector": r32.area_vector[i].tolist(),
                            "normal": r32.normal[i].tolist(),
                        },
                    }
                )
    os.makedirs(os.path.dirname(os.path.abspath(args.out)), exist_ok=True)
    with open(args.out, "w") as f:
        json.dump({"pairs": pairs}, f)
    print(f"wrote {args.out}: {len(pairs)} pairs", flush=True)


if __name__ == "__main__":
    main()
