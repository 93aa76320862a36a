"""Tuning sweep of the pair kernel: register cap and block size, float32, 1% depth.

python benchmarks/tune_pair_kernel.py --device cuda:0
"""

import argparse
import json
import os

import numpy as np
import warp as wp
from pair_kernel import HERE, make_pairs, shape_library, time_kernel

from polydem.shapeset import ShapeSet


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--device", default=None)
    ap.add_argument("--pairs", type=int, default=1 << 20)
    ap.add_argument("--shapes", default="cube,rock20")
    ap.add_argument("--registers", default="0,64,96,128")
    ap.add_argument("--blocks", default="64,128,256")
    ap.add_argument("--out", default=os.path.join(HERE, "results", "tune_pair_kernel.json"))
    args = ap.parse_args()
    wp.config.quiet = True
    dev = wp.get_device(args.device)
    lib = shape_library()
    rows = []
    print(f"{'shape':<10}{'regs':>6}{'block':>7}{'Mpairs/s':>10}", flush=True)
    for name in args.shapes.split(","):
        shape = lib[name]
        shapes = ShapeSet([shape], device=dev)
        pa, pb = make_pairs(shape, args.pairs, 0.01, np.random.default_rng(1), dev)
        for regs in (int(r) for r in args.registers.split(",")):
            for block in (int(b) for b in args.blocks.split(",")):
                t, _ = time_kernel(shapes, pa, pb, 10, max_registers=regs or None, block_dim=block)
                rows.append({"shape": name, "max_registers": regs, "block_dim": block, "pairs_per_second": len(pa) / t})
                print(f"{name:<10}{regs:>6}{block:>7}{len(pa) / t / 1e6:>10.1f}", flush=True)
    os.makedirs(os.path.dirname(args.out), exist_ok=True)
    with open(args.out, "w") as f:
        json.dump({"device": dev.name, "rows": rows}, f, indent=1)


if __name__ == "__main__":
    main()
