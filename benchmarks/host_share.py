"""The host's share of a small pile's step: Simulation.step's checks and copies against the bare graph launches.

``Simulation.step(n)`` runs its steps in chunks of CHUNK_STEPS (the last step alone, so that the copy taken before it
is what contacts() reports), and around each chunk the host copies the state for a redo, reads the overflow, rebuild,
finiteness and speed flags back (each a synchronisation) and renews the tree; ``run_until_settled`` adds the settle
measures every CHUNK_STEPS steps. While the host does that the GPU has nothing queued. ``Simulation.advance(n)`` only
launches the captured steps. This script pours time_to_settle.py's pile (4 dt_rec, the volume rule's k) for
``--warmup`` seconds of simulated time, then times, alternating, ``--chunks`` chunks of CHUNK_STEPS steps each way
(and the settle measures alone), and reports the milliseconds a step and the host's share:
(step - advance) / step. On the CPU the kernels run on the host's thread: the difference is the host's own time.

    python benchmarks/host_share.py --device cuda:0 --sizes 1000,10000
"""

import argparse
import json
import os
import statistics
import sys
import time

import warp as wp

HERE = os.path.dirname(os.path.abspath(__file__))
sys.path.insert(0, HERE)
from _meta import run_meta  # noqa: E402
from time_to_settle import default_pour  # noqa: E402

from polydem.simulation import CHUNK_STEPS  # noqa: E402


def timed(sim, run, steps):
    """Wall milliseconds a step of ``run()``, which takes ``steps`` steps, the device synchronised around it."""
    wp.synchronize_device(sim.device)
    t0 = time.perf_counter()
    run()
    wp.synchronize_device(sim.device)
    return 1e3 * (time.perf_counter() - t0) / steps


def measure(n, args, device):
    sim = default_pour(n, device, args.shapes)
    sim.step(max(1, round(args.warmup / sim.dt)))
    steps = args.chunks * CHUNK_STEPS
    rows = {"step": [], "advance": [], "settle_measures": []}
    for _ in range(args.repeats):
        rows["step"].append(timed(sim, lambda: sim.step(steps), steps))
        rows["advance"].append(timed(sim, lambda: sim.advance(steps), steps))
        # advance() does not count its steps: keep the cadence of step()'s chunks and the time right
        sim.steps_done += steps
        sim.time += steps * sim.dt
        rows["settle_measures"].append(timed(sim, lambda: [sim.settle_measures() for _ in range(args.chunks)], steps))
    med = {k: statistics.median(v) for k, v in rows.items()}
    return {
        "bodies": n,
        "shapes": args.shapes,
        "dt": sim.dt,
        "steps_a_window": steps,
        "ms_per_step": med,
        "all_ms_per_step": rows,
        "host_share_of_step": (med["step"] - med["advance"]) / med["step"],
        "settle_measures_share": med["settle_measures"] / (med["step"] + med["settle_measures"]),
    }


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--device", default="cuda:0")
    ap.add_argument("--sizes", default="1000,10000")
    ap.add_argument("--shapes", default="cube", help="cube or mixed")
    ap.add_argument("--warmup", type=float, default=0.2, help="simulated seconds of pour before the timing")
    ap.add_argument("--chunks", type=int, default=8, help="chunks of CHUNK_STEPS steps a timed window")
    ap.add_argument("--repeats", type=int, default=5, help="windows each way, alternating")
    ap.add_argument("--out", default=os.path.join(HERE, "results", "issue27", "host_share.json"))
    args = ap.parse_args()
    wp.config.quiet = True
    dev = wp.get_device(args.device)
    record = {"meta": run_meta(dev), "args": vars(args), "rows": []}
    print(f"{'bodies':>8} {'step ms':>9} {'advance':>9} {'host share':>11} {'settle measures':>16}")
    for n in [int(float(s)) for s in args.sizes.split(",")]:
        r = measure(n, args, dev)
        record["rows"].append(r)
        m = r["ms_per_step"]
        print(f"{n:>8} {m['step']:9.4f} {m['advance']:9.4f} {r['host_share_of_step']:11.1%} "
              f"{r['settle_measures_share']:16.1%}", flush=True)  # fmt: skip
    os.makedirs(os.path.dirname(args.out), exist_ok=True)
    with open(args.out, "w") as f:
        json.dump(record, f, indent=1)
    print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
