"""Random packings of cubes by friction annealing: the packing fraction against the friction of the fill
(VALIDATION.md, random packings).

Baker and Kudrolli (2010, Phys. Rev. E 82, 061304) found plastic dice at 0.54 +- 0.01 in their loosest
stable random packing (fluidized, then let settle) and 0.67 +- 0.01 in their densest (vibrated). In simulation
the friction during the fill sets where a packing lands between the two: cubes poured into a square box of
``--width`` grain sizes fill at each friction of ``--mu-fill`` (:func:`polydem.protocols.anneal`), come to
rest, get their final friction ``--mu`` and settle again; the packing fraction is measured exactly in a box
two grain sizes in from the walls, the floor and the top of the pile (as benchmarks/validation/tapping.py
measures). A fill at ``--mu`` itself is the plain pour.

    python benchmarks/validation/anneal.py --device cpu --grains 160 --mu-fill 0,0.5,1.0      # a small check
    python benchmarks/validation/anneal.py --device cuda:0 --grains 5000 --width 24 --mu-fill 0,0.25,0.5,1.0
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

from tapping import RESULTS, add_pile_arguments, build, describe, measuring_region


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    add_pile_arguments(ap)
    ap.add_argument("--mu", type=float, default=0.5, help="the final friction")
    ap.add_argument("--mu-fill", default="0,0.5,1.0", help="frictions of the fill, comma-separated")
    ap.add_argument("--fill-time", type=float, default=2.0, help="the longest a fill may take to settle [s]")
    ap.add_argument("--settle-time", type=float, default=0.5, help="the longest the final settling may take [s]")
    ap.add_argument("--seed", type=int, default=1)
    ap.add_argument("--coordination", action="store_true", help="record the final coordination number")
    ap.add_argument("--out", default=None)
    args = ap.parse_args()

    import warp as wp

    wp.config.quiet = True
    from polydem import Simulation
    from polydem.protocols import anneal

    d = args.grain
    w = args.width * d

    region = measuring_region(w, d, args.margin)

    tag = "" if args.shape == "cube" else f"{args.shape}_"
    path = Path(args.out) if args.out else RESULTS / f"anneal_{tag}{args.grains}_{args.device.replace(':', '')}.json"
    path.parent.mkdir(parents=True, exist_ok=True)
    rows = []
    t0 = time.perf_counter()

    def save(dt: float) -> dict:
        # Written after every fill: a run stopped at a time limit keeps the fills it finished.
        out = {"args": vars(args), "dt": dt, "wall_s": time.perf_counter() - t0, "rows": rows}
        path.write_text(json.dumps(out, indent=1) + "\n")
        return out

    for mu_fill in (float(x) for x in args.mu_fill.split(",")):
        # The tapping scene without taps (none before the end of the run): the same pour, the same box.
        sc = build(args.grains, args.width, d=d, gamma=1.0, frequency=30.0, start=1e9, period=1.0, taps=1,
                   mu=args.mu, seed=args.seed, shape=args.shape)  # fmt: skip
        sim = Simulation(sc, device=args.device)
        t1 = time.perf_counter()
        fill, final = anneal(sim, mu_fill, args.mu, args.fill_time, args.settle_time, box=region)
        row = {
            "mu_fill": mu_fill,
            "fill": {"time": fill.time, "settled": fill.settled, "packing_fraction": fill.packing_fraction},
            "final": {"time": final.time, "settled": final.settled, "packing_fraction": final.packing_fraction},
            "wall_s": time.perf_counter() - t1,
        }
        row["final"].update(describe(sim, region, args.shape, args.coordination))
        rows.append(row)
        print(f"mu_fill {mu_fill:5.2f}: filled at t {fill.time:6.3f} s (settled {fill.settled}) packing fraction "
              f"{fill.packing_fraction:.4f}; at mu {args.mu:g}: t {final.time:6.3f} s (settled {final.settled}) "
              f"{final.packing_fraction:.4f}  ({row['wall_s']:.0f} s)", flush=True)  # fmt: skip
        out = save(sim.dt)
    print(f"wrote {path} ({out['wall_s']:.1f} s)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
