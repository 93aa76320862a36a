"""What splitting the step costs on one device, and how early the split step's first part is done.

A decomposed run (polydem.distributed, ``overlap=True``) splits each rank's step in two parts
(Simulation.advance_split): the first computes the contacts and forces of the bodies the rank sends and their
rows as the step will leave them (kernels/ghosts.py launch_step_rows), the second the rest; the ghost
exchange runs on the host while the second part runs on the GPU. This script measures, on one device and
without MPI, both sides of that trade for the pile of benchmarks/settle.py (a 2:1 footprint, as one of two
ranks): the whole step (``Simulation.advance(1)``, as the run steps without the overlap) against the split step
with the rows of the bodies within the halo of a cut through the middle of the pile (as the rank would send),
in alternating windows (off, on, off, on) with a device synchronisation after each step, and within the split
step the time at which the rows are ready (the event the exchange waits on) against the step's end: the
time the exchange can hide behind.

    python benchmarks/split_step.py --device cuda:0 --bodies 1000000
"""

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np
import warp as wp

sys.path.insert(0, str(Path(__file__).resolve().parent))
from _meta import activity_ms_per_step, run_meta  # noqa: E402
from polydem.kernels.ghosts import launch_step_rows  # noqa: E402
from settle import make_scene, scene_options  # noqa: E402

from polydem import Simulation  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--device", default="cuda:0")
    ap.add_argument("--bodies", type=int, default=1000000)
    ap.add_argument("--precision", default="float32")
    ap.add_argument("--warmup", type=int, default=200, help="steps before the windows (as benchmarks/scaling.py)")
    ap.add_argument("--steps", type=int, default=200, help="steps per window")
    ap.add_argument("--windows", type=int, default=2, help="windows per mode")
    ap.add_argument("--profile", type=int, default=0, help="also time each kernel and graph on the GPU for N steps")
    ap.add_argument(
        "--part-times",
        type=int,
        default=0,
        help="also time, with events, when each part of N split steps ends (from the step's launch)",
    )
    ap.add_argument(
        "--pipelined",
        action="store_true",
        help="also time windows with no synchronisation after each step (the split waits for its rows "
        "only, as a decomposed run's exchange does): the GPU's own cost of the split",
    )
    ap.add_argument("--out", default=None)
    args = ap.parse_args()
    wp.config.quiet = True
    scene, info = make_scene(args.bodies, scene_options(aspect=2.0, precision=args.precision))
    sim = Simulation(scene, device=args.device)
    sim.step(args.warmup)
    m, st = sim.model, sim.current_state
    x = st.body_q.numpy()[:, 0].astype(np.float64)
    free = m.body_flags_np == 0
    cut = float(np.median(x[free]))
    halo = 3.0 * sim.settings.radius_max  # DistributedSimulation's default: 2 r_max + a margin of r_max
    send = free & (x < cut) & (x > cut - halo)
    index = np.flatnonzero(send)
    rows = wp.empty((len(index), 14), dtype=m.scalar, device=sim.device)
    host = wp.empty((len(index), 14), dtype=m.scalar, device="cpu", pinned=sim.device.is_cuda)
    idx = wp.array(index.astype(np.int32), dtype=int, device=sim.device)

    def between():
        launch_step_rows(model=m.bodies, gravity=m.gravity, dt=sim.dt, bodies=st.bodies, damping=st.body_damping,
                         index=idx, rows=rows)  # fmt: skip
        wp.copy(host, rows)

    def window(split, steps, sync=True):
        ready = []
        t0 = time.perf_counter()
        for _ in range(steps):
            t1 = time.perf_counter()
            if split:
                event = sim.advance_split(between, key="rows")
                if event is not None:
                    wp.synchronize_event(event)
                ready.append(time.perf_counter() - t1)
            else:
                sim.advance(1)
            if sync:
                wp.synchronize_device(sim.device)
        wp.synchronize_device(sim.device)
        return time.perf_counter() - t0, ready

    def part_times(steps):
        """Per step, when each part ended and when the whole step did, from the step's launch [ms] (events)."""
        main = wp.get_stream(sim.device)
        start = wp.Event(sim.device, enable_timing=True)
        marks = [wp.Event(sim.device, enable_timing=True) for _ in sim.stepper.SPLIT_PARTS]
        end = wp.Event(sim.device, enable_timing=True)
        split_rows, whole_rows = [], []
        for split in (True, False):
            sim.split_at(send if split else None)
            window(split, 3)
            for _ in range(steps):
                main.record_event(start)
                if split:
                    sim.advance_split(between, key="rows", marks=marks)
                else:
                    sim.advance(1)
                    main.record_event(end)
                wp.synchronize_device(sim.device)
                if split:
                    split_rows.append([wp.get_event_elapsed_time(start, e) for e in marks])
                else:
                    whole_rows.append(wp.get_event_elapsed_time(start, end))
        med = np.median(np.array(split_rows), axis=0)
        return {"split_part_end_ms": dict(zip(sim.stepper.SPLIT_PARTS, map(float, med), strict=True)),
                "whole_end_ms": float(np.median(whole_rows))}  # fmt: skip

    modes = [False, True] * args.windows
    for split in (True, False):  # the graphs of both modes, captured before any window
        sim.split_at(send if split else None)
        window(split, 3)
    results = []
    for split in modes:
        sim.split_at(send if split else None)
        window(split, 3)  # untimed: the mode's graphs captured again
        wall, ready = window(split, args.steps)
        results.append({"split": split, "step_ms": 1e3 * wall / args.steps,
                        "rows_ready_ms_median": float(1e3 * np.median(ready)) if ready else None})  # fmt: skip
    pipelined = []
    if args.pipelined:
        for split in modes:
            sim.split_at(send if split else None)
            window(split, 3)
            wall, _ = window(split, args.steps, sync=False)
            pipelined.append({"split": split, "step_ms": 1e3 * wall / args.steps})
    parts = part_times(args.part_times) if args.part_times and sim.device.is_cuda else {}
    profile = {}
    if args.profile and sim.device.is_cuda:
        # Warp's activity timing: each graph launch's GPU time, then (graphs off) each kernel's and copy's.
        for graphs in (True, False):
            sim.use_graph = graphs
            for split in (False, True):
                sim.split_at(send if split else None)
                window(split, 3)
                filt = wp.TIMING_GRAPH if graphs else wp.TIMING_KERNEL | wp.TIMING_MEMCPY
                key = f"{'graphs' if graphs else 'kernels'}_{'split' if split else 'whole'}"
                profile[key] = activity_ms_per_step(lambda: window(split, args.profile), args.profile, filt)  # noqa: B023
        sim.use_graph = True
    whole = float(np.median([r["step_ms"] for r in results if not r["split"]]))
    split_ms = float(np.median([r["step_ms"] for r in results if r["split"]]))
    ready_ms = float(np.median([r["rows_ready_ms_median"] for r in results if r["split"]]))
    record = {
        "meta": run_meta(sim.device),
        "args": vars(args),
        "scene": info,
        "bodies": scene.num_bodies,
        "sent_bodies": len(index),
        "candidate_pairs": sim.current_contacts.count(),
        "windows": results,
        "whole_step_ms_median": whole,
        "split_step_ms_median": split_ms,
        "rows_ready_ms_median": ready_ms,
        "split_over_whole": split_ms / whole,
        "hideable_ms": split_ms - ready_ms,
        "profile_ms_per_step": profile,
        "pipelined_windows": pipelined,
        "part_times": parts,
    }
    print(
        f"{scene.num_bodies} bodies ({len(index)} sent, {record['candidate_pairs']} candidate pairs) on "
        f"{sim.device.name}: whole step {whole:.3f} ms, split step {split_ms:.3f} ms ({split_ms / whole:.3f}x); "
        f"rows ready {ready_ms:.3f} ms into the split step: {split_ms - ready_ms:.3f} ms of the step left to hide "
        f"the exchange behind"
    )
    for r in results:
        name = "split" if r["split"] else "whole"
        print(f"  {name}: {r['step_ms']:.3f} ms/step, rows ready {r['rows_ready_ms_median']}")
    for r in pipelined:
        print(f"  pipelined {'split' if r['split'] else 'whole'}: {r['step_ms']:.3f} ms/step")
    if parts:
        ends = ", ".join(f"{k} {v:.3f}" for k, v in parts["split_part_end_ms"].items())
        print(f"  part ends from the launch [ms]: {ends}; the whole step ends at {parts['whole_end_ms']:.3f}")
    for key, sums in profile.items():
        top = ", ".join(f"{name[-40:]} {ms:.4f}" for name, ms in list(sums.items())[:12])
        print(f"  {key}: total {sum(sums.values()):.4f} ms/step GPU; {top}")
    tag = str(args.device).replace(":", "")
    out = Path(args.out or ROOT / f"benchmarks/results/issue27/split_step_{tag}_{args.bodies}.json")
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(json.dumps(record, indent=1, default=float))
    print(f"wrote {out}")


if __name__ == "__main__":
    main()
