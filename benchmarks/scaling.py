"""Weak and strong scaling of a decomposed run (polydem.distributed) over MPI ranks, one GPU per rank.

The pile of benchmarks/settle.py (cubes of 1 cm in columns of 10 in an open box, settling), with its
footprint made of one square per rank side by side along x, so that each rank's slab has the same
shape whatever the number of ranks (weak scaling: ``--bodies-per-rank``), or one fixed pile
(strong scaling: ``--bodies``, the footprint of ``--aspect``). Launch one process per rank:

    mpiexec -n 2 python benchmarks/scaling.py --device cuda --bodies-per-rank 1000000
    mpiexec -n 2 python benchmarks/scaling.py --device cuda --bodies 10000000 --aspect 2
    mpiexec -n 2 python benchmarks/scaling.py --device cpu --bodies-per-rank 2000

Per run: the scene is built on every rank; ``--warmup`` steps (kernel compiles, CUDA graphs, the
first partitions) are not timed; then ``--steps`` steps are timed, with each rank's time split into
``compute`` (its Simulation's step), ``exchange`` (packing, sending, receiving and unpacking the
ghosts, which includes waiting for the neighbours' messages), ``wait`` (the step's agreement: one
allreduce of the error flag and the largest move) and ``partition`` (repartitions in the window).
With ``--baseline`` (one rank only) the same pile is also stepped by a plain Simulation (the
undivided production path: CUDA graph chunks), the reference for the efficiency.
``--overlap on`` (default) sends the ghosts while each step runs (DistributedSimulation(overlap=True)), ``off``
after it; ``both`` times windows of ``--steps`` off, on, off, on in one run (the same pile, the same ranks) and
reports each window and the medians. ``--exchange host`` (default) sends the ghosts' rows through host memory
over MPI, ``nccl`` from GPU to GPU with NCCL (DistributedSimulation(exchange="nccl"): nccl4py, a GPU per rank),
``both`` alternates them too (with ``--overlap both``: the four modes, twice each).
Rank 0 prints a table and writes JSON to ``--out``.
"""

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np
import warp as wp

sys.path.insert(0, str(Path(__file__).resolve().parent))
from settle import make_scene, scene_options  # noqa: E402

from polydem import Simulation  # noqa: E402
from polydem.distributed import DistributedSimulation, world  # noqa: E402
from polydem.distributed.root import device_for_rank  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--device", default="cuda")
    ap.add_argument("--bodies-per-rank", type=int, default=None)
    ap.add_argument("--bodies", type=int, default=None, help="a fixed pile (strong scaling)")
    ap.add_argument("--aspect", type=float, default=None, help="footprint x:y (default: the number of ranks)")
    ap.add_argument("--warmup", type=int, default=200)
    ap.add_argument("--steps", type=int, default=200)
    ap.add_argument("--precision", default="float32")
    ap.add_argument("--baseline", action="store_true", help="also time a plain Simulation (one rank only)")
    ap.add_argument("--split", action="store_true", help="synchronise after each step's kernels to split the time")
    ap.add_argument("--overlap", choices=("on", "off", "both"), default="on")
    ap.add_argument("--exchange", choices=("host", "nccl", "both"), default="host")
    ap.add_argument("--out", default=None)
    args = ap.parse_args()
    wp.config.quiet = True
    comm = world()
    rank, size = comm.Get_rank(), comm.Get_size()
    n = args.bodies if args.bodies is not None else (args.bodies_per_rank or 100000) * size
    aspect = args.aspect if args.aspect is not None else float(size)
    t0 = time.perf_counter()
    scene, info = make_scene(n, scene_options(aspect=aspect, precision=args.precision))
    build_scene = time.perf_counter() - t0
    device = device_for_rank(args.device if args.device != "cuda" else "cuda:0", comm)
    t0 = time.perf_counter()
    exchanges = {"host": ["host"], "nccl": ["nccl"], "both": ["host", "nccl"]}[args.exchange]
    overlaps = {"on": [True], "off": [False], "both": [False, True]}[args.overlap]
    ds = DistributedSimulation(scene, device=device, comm=comm, overlap=overlaps[0], exchange=exchanges[0])
    ds.sync_timers = args.split
    build = time.perf_counter() - t0
    ds.step(args.warmup)
    modes = [(o, e) for e in exchanges for o in overlaps]
    for overlap, exchange in modes[1:]:  # the other modes' kernels and graphs too, before any window
        ds.set_overlap(overlap)
        ds.set_exchange(exchange)
        ds.step(min(args.warmup, 20))
    wp.synchronize()
    if len(modes) > 1:
        modes = modes * 2
    parts0 = ds.partitions
    windows = []
    for overlap, exchange in modes:
        if ds.overlap != overlap or ds.exchange != exchange:
            ds.set_overlap(overlap)
            ds.set_exchange(exchange)
            ds.step(5)  # untimed: the graphs of the mode (captured again when it changes)
        for k in ds.timers:
            ds.timers[k] = 0.0
        comm.Barrier()
        t0 = time.perf_counter()
        ds.step(args.steps)
        wp.synchronize()
        comm.Barrier()
        windows.append({"overlap": overlap, "exchange": exchange, "split": ds.split, "wall_s": time.perf_counter() - t0,
                        "timers_s": dict(ds.timers)})  # fmt: skip
    wall = windows[-1]["wall_s"]
    owned, local = ds.balance()
    mine = {
        "rank": rank,
        "device": str(ds.device),
        "timers_s": dict(ds.timers),
        "windows": windows,
        "owned": int(ds.owned.sum()),
        "local": len(ds.local_index),
        "build_s": build,
        "scene_s": build_scene,
    }
    ranks = comm.gather(mine, root=0)
    baseline = None
    if args.baseline and size == 1:
        sim = Simulation(make_scene(n, scene_options(aspect=aspect, precision=args.precision))[0], device=device)
        sim.step(args.warmup)
        wp.synchronize()
        t1 = time.perf_counter()
        sim.step(args.steps)
        wp.synchronize()
        baseline = {"step_ms": 1e3 * (time.perf_counter() - t1) / args.steps}
    if rank != 0:
        return
    step_ms = 1e3 * wall / args.steps

    # The window's wall time is the same on every rank (barriers at both ends): rank 0's.
    def mode_name(w):
        return f"{'on' if w['overlap'] else 'off'}/{w['exchange']}"

    by_mode = {}
    for w in ranks[0]["windows"]:
        by_mode.setdefault(mode_name(w), []).append(1e3 * w["wall_s"] / args.steps)
    medians = {k: float(np.median(v)) for k, v in by_mode.items()}
    record = {
        "meta": {**vars(args), "warp": wp.__version__, "ranks": size, "bodies": scene.num_bodies, "grains": n},
        "scene": info,
        "step_ms": step_ms,
        "step_ms_by_mode": by_mode,
        "step_ms_median_by_mode": medians,
        "body_steps_per_s": scene.num_bodies * args.steps / wall,
        "partitions_in_window": ds.partitions - parts0,
        "ranks": ranks,
        "baseline": baseline,
    }
    print(
        f"{size} ranks, {n} grains ({aspect:g}:1 footprint), {args.steps} steps: {step_ms:.3f} ms/step, "
        f"{record['body_steps_per_s']:.3g} body-steps/s, {record['partitions_in_window']} partitions in the window"
    )
    for r in ranks:
        t = r["timers_s"]
        per = {k: f"{1e3 * v / args.steps:.3f}" for k, v in t.items()}
        print(
            f"  rank {r['rank']} on {r['device']}: owns {r['owned']}, holds {r['local']} ({r['local'] - r['owned']} "
            f"ghosts); ms/step compute {per['compute']}, exchange {per['exchange']}, wait {per['wait']}, "
            f"partition {per['partition']}; built in {r['build_s']:.1f} s"
        )
    for mode, v in by_mode.items():
        split = [w["split"] for r in ranks for w in r["windows"] if mode_name(w) == mode]
        print(f"  overlap/exchange {mode}: ms/step by window {', '.join(f'{x:.3f}' for x in v)}, median "
              f"{medians[mode]:.3f} (ranks split: {sum(split)} of {len(split)})")  # fmt: skip
    if baseline is not None:
        print(f"  plain Simulation: {baseline['step_ms']:.3f} ms/step")
    tag = str(args.device).replace(":", "")
    kind = f"strong{n}" if args.bodies is not None else f"weak{n // size}"
    out = Path(args.out or ROOT / f"benchmarks/results/issue14/scaling_{tag}_{kind}_r{size}.json")
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(json.dumps(record, indent=1, default=float))
    print(f"wrote {out}")


if __name__ == "__main__":
    main()
