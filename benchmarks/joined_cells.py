"""The shipped mesh-wall scenes with their flat patches' cells joined (the default) and with one cell per
triangle: the cells, the set-up and the step time, in the same run.

Each scene runs ``--warmup`` seconds of simulated time (the grains fall onto the walls), then ``--steps``
steps are timed ``--repeats`` times (median). On CUDA the step is a captured graph; on the CPU the host
loop. The set-up time is that of ``Simulation(...)`` (the scene's cells are built once, then joined).

    python benchmarks/joined_cells.py --device cpu --scenes hopper --warmup 0.05 --steps 50
    python benchmarks/joined_cells.py --device cuda:0 --scenes hopper,tapped_cup,mixer,heap

Prints a table and writes JSON to ``--out`` (benchmarks/results/issue27/joined_cells_<device>.json).
"""

import argparse
import json
import time
from pathlib import Path

import warp as wp
from wall_contact_cost import time_steps

from polydem import Scene, Simulation

ROOT = Path(__file__).resolve().parents[1]


def run(name, device, join, warmup, steps, repeats):
    scene = Scene.from_toml(ROOT / "scenes" / f"{name}.toml")
    t0 = time.perf_counter()
    sim = Simulation(scene, device=device, join_flat_cells=join)
    setup = time.perf_counter() - t0
    sim.step(max(1, round(warmup / sim.dt)))
    step = time_steps(sim, steps, repeats)
    walls = (sim.contacts()["body_b"] < 0).sum()
    return {
        "scene": name,
        "cells": "joined" if join else "triangles",
        "triangles": sum(len(mc.faces) for mc in sim.model.mesh_cells),
        "mesh_cells": sum(mc.num_cells for mc in sim.model.mesh_cells),
        "bodies": sim.num_bodies,
        "wall_contacts": int(walls),
        "setup_s": setup,
        "step_s": step,
    }


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--device", default="cpu")
    ap.add_argument("--scenes", default="hopper,tapped_cup,mixer,heap")
    ap.add_argument("--warmup", type=float, default=0.2, help="simulated seconds before the timing")
    ap.add_argument("--steps", type=int, default=200)
    ap.add_argument("--repeats", type=int, default=5)
    ap.add_argument("--out", default=None)
    args = ap.parse_args()
    wp.config.quiet = True
    rows = []
    for name in args.scenes.split(","):
        pair = [run(name, args.device, join, args.warmup, args.steps, args.repeats) for join in (False, True)]
        for r in pair:
            r["step_vs_triangles"] = r["step_s"] / pair[0]["step_s"]
            rows.append(r)
            print(
                f"{name:>11} {r['cells']:>9}: {r['mesh_cells']:6d} cells of {r['triangles']} triangles, "
                f"set-up {r['setup_s']:6.2f} s, step {r['step_s'] * 1e3:8.4f} ms ({r['step_vs_triangles']:.3f}x), "
                f"{r['wall_contacts']} wall contacts"
            )
    out = Path(args.out or f"benchmarks/results/issue27/joined_cells_{args.device.replace(':', '')}.json")
    out.parent.mkdir(parents=True, exist_ok=True)
    meta = {"device": args.device, "warp": wp.__version__, "warmup_s": args.warmup, "steps": args.steps,
            "repeats": args.repeats}  # fmt: skip
    out.write_text(json.dumps({"meta": meta, "rows": rows}, indent=1))
    print(f"wrote {out}")


if __name__ == "__main__":
    main()
