"""One line (or a few) of time_to_settle.py --profile-steps' record: the step's wall time, its graphs' GPU time and the
costliest kernels (graphs off), for the round scripts (latency_round.sh, ab_round.sh).

    python benchmarks/profile_summary.py RUN.json [--top 8] [--one-line]
"""

import argparse
import json
import sys


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("record", help="time_to_settle.py's --out JSON")
    ap.add_argument("--top", type=int, default=8, help="kernels to list")
    ap.add_argument("--one-line", action="store_true", help="the kernels on the same line, names shortened")
    args = ap.parse_args(argv)
    try:
        with open(args.record) as f:
            r = json.load(f)["runs"][0]["profile"]
    except Exception as e:  # the run was cut before it wrote its profile
        sys.exit(f"   no profile: {e!r}")
    graphs = sum((r.get("graphs_ms_per_step") or {}).values())
    kernels = sorted((r.get("kernels_ms_per_step") or {}).items(), key=lambda kv: -kv[1])[: args.top]
    head = f"   wall {r['wall_ms_per_step']:.4f} ms a step; graphs' GPU {graphs:.4f} ms a step"
    if args.one_line:
        print(head + "; " + "; ".join(f"{name.split('__')[-1][:28]} {ms:.4f}" for name, ms in kernels))
        return
    print(head)
    for name, ms in kernels:
        print(f"   {ms:8.4f} ms  {name}")


if __name__ == "__main__":
    main()
