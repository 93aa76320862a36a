"""Is a tapped pile of cubes that packs past the densest random packing ordering? From the checkpoints of
tapping.py runs (``--stop-after``/``--resume`` leave one per call): the packing fraction, the cubic order in the
box's frame and in the frame the grains align with best (:func:`polydem.measures.cubic_frame`), and the
coordination number split by contact type (face-face contacts grow as grains stack face to face), in
tapping.py's measuring box. Runs on the CPU (the checkpoint's state is loaded into a simulation of the same
scene and advanced one step to find its contacts).

    python benchmarks/validation/tap_order.py benchmarks/results/validation/taps/tap_cube_s1_t4.38.npz ...

Each checkpoint needs the tapping.py JSON its run wrote beside it (the same name with .json): it holds the
options the scene is rebuilt from. ``--out`` writes the rows as JSON.
"""

from __future__ import annotations

import argparse
import inspect
import json
import sys
import warnings
from pathlib import Path

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE))


def analyse(checkpoint: str, device: str) -> dict:
    import numpy as np
    import tapping
    import warp as wp

    wp.config.quiet = True
    from polydem import Simulation, measures
    from polydem.checkpoint import load_checkpoint

    args = json.loads(Path(checkpoint).with_suffix(".json").read_text())["args"]
    wanted = set(inspect.signature(tapping.build).parameters) - {"grains", "width_d", "d"}
    sc = tapping.build(args["grains"], args["width"], d=args["grain"], **{k: args[k] for k in wanted if k in args})
    with warnings.catch_warnings():
        warnings.filterwarnings("ignore", message=r".*initial overlaps")  # the grains at rest overlap a little
        sim = Simulation(sc, device=device)
    load_checkpoint(sim, checkpoint)
    sim.step(1)
    grains = measures.Grains.from_simulation(sim)
    box = tapping.measuring_region(args["width"] * args["grain"], args["grain"], args.get("margin", 2.0))(grains)
    inside = grains.free & box.contains(grains.position)
    found = sim.contacts()
    z = measures.coordination(measures.Grains.from_simulation(sim, bodies=inside), found,
                              measures.classify_contacts(sim, found))  # fmt: skip
    row = {"checkpoint": str(checkpoint), "time": sim.time, "grains_in_box": int(inside.sum()),
           "packing_fraction": measures.packing_fraction(grains, box), "coordination": z.z,
           "coordination_by_kind": z.z_by_kind}  # fmt: skip
    if args.get("shape", "cube") == "cube":
        best, frame = measures.cubic_frame(grains, box)
        row.update(cubic_order=measures.cubic_order(grains, box), cubic_order_best=best,
                   best_frame_tilt_deg=float(np.degrees(np.arccos(min(1.0, np.abs(frame[:, 2]).max())))))  # fmt: skip
    return row


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("checkpoints", nargs="+")
    ap.add_argument("--device", default="cpu")
    ap.add_argument("--out", default=None)
    args = ap.parse_args(argv)
    rows = []
    for cp in args.checkpoints:
        row = analyse(cp, args.device)
        rows.append(row)
        kinds = ", ".join(f"{k} {v:.2f}" for k, v in row["coordination_by_kind"].items())
        order = ""
        if "cubic_order" in row:
            order = (f"  cubic order {row['cubic_order']:+.3f} (box), {row['cubic_order_best']:.3f} (best frame, "
                     f"its nearest axis {row['best_frame_tilt_deg']:.0f} deg from vertical)")  # fmt: skip
        print(f"{cp}: t {row['time']:.3f} s, phi {row['packing_fraction']:.4f}, z {row['coordination']:.2f} "
              f"({kinds}){order}")  # fmt: skip
    if args.out:
        Path(args.out).write_text(json.dumps({"rows": rows}, indent=1) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
