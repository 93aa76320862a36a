"""Start-up time of the polydem command: --help, validate and info, median and minimum of N runs.

    python benchmarks/startup.py                                   # the polydem on PATH
    python benchmarks/startup.py --polydem /old/venv/bin/polydem --polydem polydem   # several installs, alternated

Each command runs as a fresh process, as a user starts it, so the figure includes Python's own
start and every import the command makes. Installs given together are run in turn within each
repetition, so that a change in the machine's load falls on all of them alike: compare them within
one run. Results: a table on stdout and JSON benchmarks/results/startup.json (machine, command line).
"""

import argparse
import json
import os
import shutil
import statistics
import subprocess
import sys
import time

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
from _meta import run_meta  # noqa: E402

HERE = os.path.dirname(os.path.abspath(__file__))
SCENE = os.path.join(HERE, "..", "scenes", "cube_drop.toml")
COMMANDS = {"--help": ["--help"], "validate": ["validate", SCENE, "--quiet"], "info": ["info"]}


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--polydem", action="append", help="a polydem executable (repeat to compare installs)")
    ap.add_argument("--repeats", type=int, default=7)
    ap.add_argument("--out", default=os.path.join(HERE, "results", "startup.json"))
    args = ap.parse_args()
    exes = args.polydem or [shutil.which("polydem") or "polydem"]
    times = {exe: {name: [] for name in COMMANDS} for exe in exes}
    for _ in range(args.repeats):
        for name, argv in COMMANDS.items():
            for exe in exes:
                t0 = time.perf_counter()
                proc = subprocess.run([exe, *argv], capture_output=True)
                times[exe][name].append(time.perf_counter() - t0)
                if proc.returncode != 0:
                    print(f"{exe} {' '.join(argv)} exited {proc.returncode}: {proc.stderr.decode()[-300:]}")
                    return 1
    record = {"meta": run_meta(None), "load_average": os.getloadavg(), "results": {}}
    print(f"{'polydem':<40} {'command':<9} {'median s':>9} {'min s':>7}  (load average {os.getloadavg()[0]:.1f})")
    for exe in exes:
        record["results"][exe] = {}
        for name, ts in times[exe].items():
            med, low = statistics.median(ts), min(ts)
            record["results"][exe][name] = {"median_s": med, "min_s": low, "runs": ts}
            print(f"{exe[-40:]:<40} {name:<9} {med:>9.3f} {low:>7.3f}")
    os.makedirs(os.path.dirname(args.out), exist_ok=True)
    with open(args.out, "w") as fh:
        json.dump(record, fh, indent=1)
    print(f"wrote {args.out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
