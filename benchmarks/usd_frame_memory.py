"""Host memory a USD frame takes while it is written (issue 27: the output of a 1e8-body run must not hold a
frame twice in host memory).

Two ways to record the same settle pile (benchmarks/settle.py's scene) into a .usdc file, each in its own
process: ``UsdRecorder.record(sim.time, **Simulation.state())`` (float64 copies on the host, converted there)
and ``UsdRecorder.record_simulation(sim)`` (the frame made on the device in the file's types,
:mod:`polydem.kernels.export`). For each: the process's resident memory is sampled every 0.2 ms by a thread
while the second frame is recorded (the first allocates what stays: the device frame, the layer's arrays), and
the peak above the resident memory just before it is the frame's transient host memory, in bytes per body,
beside what the file keeps of a frame (positions, half and float quaternions, velocities: 60 bytes a body).

    python benchmarks/usd_frame_memory.py --device cpu --bodies 1000000
    python benchmarks/usd_frame_memory.py --device cuda:0 --bodies 10000000 \
        --out benchmarks/results/usd_frame_memory_h100.json

On the CPU device the simulation's arrays are host memory too: the device path's frame arrays (68 bytes a body)
are then host memory, allocated once by the first frame (not in the peak).
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path

HERE = Path(__file__).resolve().parent
FILE_BYTES = 12 + 8 + 16 + 12 + 12  # positions, quath, quatf, velocities, angular velocities


def rss() -> int:
    with open("/proc/self/statm") as f:
        return int(f.read().split()[1]) * os.sysconf("SC_PAGE_SIZE")


def one(mode: str, device: str, bodies: int) -> dict:
    """Runs in its own process: build the pile, record two frames by ``mode``, sample the second."""
    sys.path.insert(0, str(HERE))
    import settle
    import warp as wp

    wp.config.quiet = True
    from polydem import Simulation
    from polydem.usd import UsdRecorder

    sim = Simulation(settle.make_scene(bodies, settle.scene_options())[0], device=device)
    path = Path(tempfile.mkdtemp()) / "frames.usdc"
    # No save while recording: a save writes the layer out, which is not the frame's conversion.
    rec = UsdRecorder(path, sim, frame_dt=sim.dt, save_interval=1e9, max_unsaved_mb=1e9)

    def frame():
        if mode == "state":
            st = sim.state()
            rec.record(sim.time, st["body_position"], st["body_orientation"], st["body_velocity"],
                       st["body_angular_velocity"])  # fmt: skip
            del st
        else:
            rec.record_simulation(sim)

    frame()
    sim.step(1)
    wp.synchronize()
    base, peak, running = rss(), [0], [True]

    def sample():
        while running[0]:
            peak[0] = max(peak[0], rss())
            time.sleep(0.0002)

    thread = threading.Thread(target=sample)
    thread.start()
    t0 = time.perf_counter()
    frame()
    seconds = time.perf_counter() - t0
    running[0] = False
    thread.join()
    rec.close()
    transient = max(peak[0], rss()) - base
    return {"mode": mode, "bodies": bodies, "device": device, "frame_s": seconds, "transient_bytes": transient,
            "transient_bytes_per_body": transient / bodies, "file_bytes_per_body": FILE_BYTES}  # fmt: skip


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--device", default="cpu")
    ap.add_argument("--bodies", type=int, default=1_000_000)
    ap.add_argument("--one", default=None, choices=("state", "device"), help=argparse.SUPPRESS)
    ap.add_argument("--repeat", type=int, default=2, help="runs of each way, alternating")
    ap.add_argument("--out", default=None)
    args = ap.parse_args(argv)
    if args.one:
        print(json.dumps(one(args.one, args.device, args.bodies)))
        return 0
    rows = []
    meta = None
    for mode in ("state", "device") * args.repeat:
        done = subprocess.run([sys.executable, __file__, "--one", mode, "--device", args.device, "--bodies",
                               str(args.bodies)], capture_output=True, text=True, check=True)  # fmt: skip
        row = json.loads(done.stdout.strip().splitlines()[-1])
        rows.append(row)
        per_body = row["transient_bytes_per_body"]
        print(f"{mode:>6}: {row['bodies']} bodies, frame {row['frame_s']:.3f} s, host memory above the start "
              f"{per_body:.1f} B/body (the file keeps {FILE_BYTES} B/body of a frame)")  # fmt: skip
        if args.out:  # after every run: a call cut short keeps what it measured
            if meta is None:
                from _meta import run_meta

                meta = run_meta(None)
            Path(args.out).write_text(json.dumps({"meta": meta, "rows": rows}, indent=1) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
