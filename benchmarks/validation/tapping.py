"""Tapped packings of cubes: the packing fraction after each tap (VALIDATION.md, random packings).

Baker and Kudrolli (2010, Phys. Rev. E 82, 061304) measured plastic dice: cubes pack at 0.54 +- 0.01 in
their loosest stable random state (fluidized) and at 0.67 +- 0.01 in their densest (vibrated). Here cubes
are poured into a square box of ``--width`` grain sizes and tapped ``--taps`` times at ``--gamma``
(scenes/tapping.toml's protocol, :func:`polydem.protocols.tap`); the packing fraction is measured exactly
in a box two grain sizes in from the walls, the floor and the top of the pile.

    python benchmarks/validation/tapping.py --device cpu --grains 160 --taps 3      # a small check
    python benchmarks/validation/tapping.py --device cuda:0 --grains 10000 --taps 20
"""

from __future__ import annotations

import argparse
import json
import math
import sys
import time
from pathlib import Path

HERE = Path(__file__).resolve().parent
RESULTS = HERE.parent / "results" / "validation"


SHAPES = ("cube", "tetrahedron")


def grain_shape(name: str, d: float):
    """The grain of edge ``d`` [m]: a cube or a regular tetrahedron (Baker and Kudrolli's two Platonic solids
    with published loosest and densest packings)."""
    import polydem

    if name == "cube":
        return polydem.ConvexShape.box(d)
    if name == "tetrahedron":
        return polydem.ConvexShape.tetrahedron(d)
    raise SystemExit(f"--shape must be one of {', '.join(SHAPES)}, got {name!r}")


def measuring_region(w: float, d: float, margin: float = 2.0):
    """The box the packing fraction is measured in, as a function of the grains: ``margin`` grain sizes ``d`` in
    from the walls of a box ``w`` wide and from the floor, up to ``margin`` below the pile's top (its highest
    centre)."""
    from polydem.measures import Box

    m = margin * d

    def region(g):
        top = float(g.position[g.free][:, 2].max())
        if top - m <= m or w <= 2 * m:
            raise SystemExit(f"the pile (top centre {top:.4g} m) in a box {w:.4g} m wide leaves no room to measure "
                             f"{margin} grain sizes in from its walls, floor and top: give more grains or a smaller "
                             "--margin")  # fmt: skip
        return Box((-0.5 * w + m, -0.5 * w + m, m), (0.5 * w - m, 0.5 * w - m, top - m))

    return region


def build(grains: int, width_d: int, *, d: float, gamma: float, frequency: float, start: float, period: float,
          taps: int, mu: float, seed: int, shape: str = "cube"):  # fmt: skip
    import polydem

    grain = grain_shape(shape, d)
    w = width_d * d
    cell = 1.1 * 2.0 * grain.radius
    across = int((w - 0.04 * d) // cell)
    height = 1.02 * math.ceil(grains / across**2) * cell + d
    sc = polydem.Scene(gravity=(0.0, 0.0, -9.81), name="tapping")
    sc.add_material("grain", density=2500.0, k=1e9, restitution=0.3, friction=mu, law="hertz")
    sc.add_motion("taps", frequency, gamma=gamma, start=start, period=period, count=taps)
    sc.add_shape(shape, grain)
    sc.add_box_container((0.0, 0.0, 0.5 * height), (w, w, height), "grain", motion="taps")
    lo, hi = (-0.5 * w + 0.02 * d,) * 2 + (0.5 * d,), (0.5 * w - 0.02 * d,) * 2 + (height - 0.5 * d,)
    sc.emit(shape, "grain", grains, (lo, hi), seed=seed)
    return sc


class _Stop(Exception):
    """Raised from the record callback once the wall-time budget is spent."""


def describe(sim, region, shape: str, contacts: bool) -> dict:
    """The measures beside the packing fraction at a record: the cubic order of the grains in the measuring
    region (cubes only: it tells the densest random packing from alignment with the box), and in the frame they
    align with best, and, with ``contacts``, their coordination number without rattlers (contacts with the
    walls counted) split by contact type."""
    from polydem import measures

    grains = measures.Grains.from_simulation(sim)
    box = region(grains)
    inside = grains.free & box.contains(grains.position)
    out = {"grains_in_box": int(inside.sum())}
    if shape == "cube":
        out["cubic_order"] = measures.cubic_order(grains, box)
        out["cubic_order_best"] = measures.cubic_frame(grains, box)[0]  # in the frame the grains align with best
    if contacts:
        found = sim.contacts()
        kinds = measures.classify_contacts(sim, found)  # face-face contacts tell local alignment from random
        z = measures.coordination(measures.Grains.from_simulation(sim, bodies=inside), found, kinds)
        out["coordination"] = z.z
        out["coordination_by_kind"] = z.z_by_kind
        out["rattler_fraction"] = z.rattler_fraction
    return out


def add_pile_arguments(ap) -> None:
    """The options of the pour this script and anneal.py share: device, grains, box width, grain edge, shape."""
    ap.add_argument("--device", default="cpu")
    ap.add_argument("--grains", type=int, default=160)
    ap.add_argument("--width", type=int, default=8, help="box width in grain sizes")
    ap.add_argument("--grain", type=float, default=0.01, help="the grain's edge [m]")
    ap.add_argument("--shape", default="cube", choices=SHAPES)
    ap.add_argument("--margin", type=float, default=2.0, help="measure this many grain sizes in from walls and top")


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    add_pile_arguments(ap)
    ap.add_argument("--taps", type=int, default=3)
    ap.add_argument("--gamma", type=float, default=3.0)
    ap.add_argument("--frequency", type=float, default=30.0)
    ap.add_argument("--start", type=float, default=0.8, help="first tap [s], after the pour")
    ap.add_argument("--period", type=float, default=0.3)
    ap.add_argument("--mu", type=float, default=0.5)
    ap.add_argument("--seed", type=int, default=1)
    ap.add_argument("--coordination", action="store_true", help="record the coordination number at each tap")
    ap.add_argument("--stop-after", type=float, default=None, help="stop after the first tap past this wall time [s]")
    ap.add_argument("--resume", default=None, help="go on from this checkpoint (.npz) of the same options")
    ap.add_argument("--out", default=None)
    args = ap.parse_args()
    t0 = time.perf_counter()  # --stop-after counts the build and the compilation too

    import warp as wp

    wp.config.quiet = True
    from polydem import Simulation
    from polydem.checkpoint import load_checkpoint, read_checkpoint, save_checkpoint
    from polydem.protocols import tap

    d = args.grain
    sc = build(args.grains, args.width, d=d, gamma=args.gamma, frequency=args.frequency, start=args.start,
               period=args.period, taps=args.taps, mu=args.mu, seed=args.seed, shape=args.shape)  # fmt: skip
    sim = Simulation(sc, device=args.device)
    records = []
    if args.resume:
        load_checkpoint(sim, args.resume)  # the taps already made are skipped: tap() starts at sim.time
        records = list((read_checkpoint(args.resume).run or {}).get("records", []))  # they come first
    w = args.width * d

    region = measuring_region(w, d, args.margin)
    tag = "" if args.shape == "cube" else f"{args.shape}_"
    path = Path(args.out) if args.out else RESULTS / f"tapping_{tag}{args.grains}_{args.device.replace(':', '')}.json"
    path.parent.mkdir(parents=True, exist_ok=True)
    checkpoint = path.with_suffix(".npz")

    def save(complete: bool = False, stopped: bool = False) -> dict:
        # Written after every tap: a run killed at a time limit keeps the taps it made ("complete" false).
        out = {"args": vars(args), "dt": sim.dt, "wall_s": time.perf_counter() - t0, "records": records,
               "complete": complete, "stopped": stopped,
               "checkpoint": checkpoint.name if stopped else None}  # fmt: skip
        path.write_text(json.dumps(out, indent=1) + "\n")
        return out

    def record(r) -> None:
        row = {"tap": r.tap, "time": r.time, "packing_fraction": r.packing_fraction, "fastest": r.fastest}
        row.update(describe(sim, region, args.shape, args.coordination))
        # A resumed run measures again at the checkpoint's time when that fell on a step: keep the new record.
        records[:] = [x for x in records if x["tap"] != row["tap"]]
        records.append(row)
        shown = ("cubic_order", "cubic_order_best", "coordination")
        extra = "".join(f"  {k} {v:.4f}" for k, v in row.items() if k in shown)
        print(f"tap {r.tap:3d}  t {r.time:7.3f} s  packing fraction {r.packing_fraction:.4f}  fastest grain "
              f"{r.fastest:.2e} m/s{extra}", flush=True)  # fmt: skip
        save()
        if args.stop_after is not None and time.perf_counter() - t0 > args.stop_after:
            raise _Stop

    try:
        tap(sim, "taps", region, on_record=record)
        stopped = False
    except _Stop:
        stopped = True
        # Taken just before the next tap: a run resumed from it makes that tap next, and keeps these records.
        save_checkpoint(sim, checkpoint, run={"records": records})
    out = save(complete=not stopped, stopped=stopped)
    resume = f"; stopped, resume with --resume {checkpoint}" if stopped else ""
    print(f"wrote {path} ({out['wall_s']:.1f} s){resume}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
