"""Cost of a compound grain's contact against a convex pair contact.

Scenes (``--bodies`` N grains, hertz law, restitution 0.5, friction 0.5, gravity), each grain resting
face down at its equilibrium depth on its own fixed cube of 1 cm, with a random yaw, on a grid 4.5 cm
apart (no grain touches another grain):

* ``pair``: a convex cube of 1 cm (the reference);
* ``pair-in-compound-kernel``: the same convex cubes, in a scene that also holds a compound shape
  (unused by any body): what the kernels built for compound grains cost a convex pair;
* ``split2``: the cube cut in two slabs (2 parts, both on the base: 2 part pairs, 2 touching);
* ``split8``: the cube cut in 2 x 2 x 2 cells (8 part pairs, 4 touching);
* ``L3``: an L of three 1 cm cells as two parts that overlap (a 2-cell bar and a 2-cell bar sharing
  the corner cell), flat on a base cube under its corner cell (2 part pairs);
* ``split2-on-split2``: the 2-part cube on a fixed 2-part cube (4 part pairs).

Each is timed twice in one run: as above, and with every free grain lifted 5 mm (out of contact,
nothing else changed). The cost of a contact is the difference of the median step times over N.

    python benchmarks/compound_contact_cost.py --device cpu --bodies 400
    python benchmarks/compound_contact_cost.py --device cuda:0 --bodies 100000

Prints a table and writes JSON to ``--out`` (benchmarks/results/issue13/compound_contact_cost_<device>_<N>.json).
"""

import argparse
import json
from pathlib import Path

import numpy as np
import warp as wp
from wall_contact_cost import time_steps

from polydem import CompoundShape, ConvexShape, Scene, Simulation
from polydem.compound import place

EDGE = 0.01
SPACING = 0.045
KINDS = ("pair", "pair-in-compound-kernel", "split2", "split8", "L3", "split2-on-split2")


def split2():
    h = EDGE
    return CompoundShape(
        [place(ConvexShape.box(h / 2, h, h), (-h / 4, 0, 0)), place(ConvexShape.box(h / 2, h, h), (h / 4, 0, 0))]
    )


def split8():
    h = EDGE
    offsets = [(sx * h / 4, sy * h / 4, sz * h / 4) for sx in (-1, 1) for sy in (-1, 1) for sz in (-1, 1)]
    return CompoundShape([place(ConvexShape.box(h / 2), o) for o in offsets])


def l3():
    h = EDGE
    return CompoundShape(
        [place(ConvexShape.box(2 * h, h, h), (h / 2, 0, 0)), place(ConvexShape.box(h, 2 * h, h), (0, h / 2, 0))]
    )


def build(kind, n, lift, precision, seed=1):
    sc = Scene(gravity=(0.0, 0.0, -9.81), dt="auto", precision=precision)
    sc.add_material("m", density=2500.0, law="hertz", k=1.0e8, restitution=0.5, friction=0.5)
    grain = {"split2": split2, "split8": split8, "L3": l3, "split2-on-split2": split2}.get(kind)
    sc.add_shape("grain", grain() if grain else ConvexShape.box(EDGE))
    sc.add_shape("base", split2() if kind == "split2-on-split2" else ConvexShape.box(EDGE))
    if kind == "pair-in-compound-kernel":
        sc.add_shape("unused", split2())
    side = int(np.ceil(np.sqrt(n)))
    rng = np.random.default_rng(seed)
    shape = sc.shapes["grain"]
    weight = 2500.0 * shape.volume * 9.81
    area = EDGE**2  # each grain rests on the top face of its base cube (the L on its corner cell)
    depth = (weight / (1.0e8 * area)) ** 2 / area  # hertz: W'(V) A = weight, W' = k V^0.5
    # The grain's input origin (the corner cell's centre for the L) sits over the base.
    for k in range(n):
        i, j = divmod(k, side)
        x, y = (i - (side - 1) / 2) * SPACING, (j - (side - 1) / 2) * SPACING
        yaw = rng.uniform(0, 2 * np.pi)
        q = (0.0, 0.0, np.sin(yaw / 2), np.cos(yaw / 2))
        sc.add_body("base", "m", position=(x, y, -0.5 * EDGE), orientation=q, kind="fixed")
        sc.add_body("grain", "m", position=(x, y, 0.5 * EDGE - depth + lift), orientation=q)
    return sc


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--device", default="cpu")
    ap.add_argument("--bodies", type=int, default=400)
    ap.add_argument("--steps", type=int, default=50)
    ap.add_argument("--repeats", type=int, default=5)
    ap.add_argument("--precision", default="mixed")
    ap.add_argument("--kinds", default=",".join(KINDS))
    ap.add_argument("--out", default=None)
    args = ap.parse_args()
    wp.config.quiet = True
    rows = []
    for kind in args.kinds.split(","):
        res = {}
        for lifted in (False, True):
            sim = Simulation(build(kind, args.bodies, 0.005 if lifted else 0.0, args.precision), device=args.device)
            t = time_steps(sim, args.steps, args.repeats)
            res[lifted] = (t, int((sim.contacts()["volume"] > 0).sum()))
        (t_on, contacts), (t_off, _) = res[False], res[True]
        row = {"kind": kind, "step_s": t_on, "step_lifted_s": t_off, "contacts": contacts,
               "per_contact_s": (t_on - t_off) / max(contacts, 1)}  # fmt: skip
        rows.append(row)
        print(
            f"{kind:>24}: step {t_on * 1e3:9.4f} ms, lifted {t_off * 1e3:9.4f} ms, {contacts} contacts, "
            f"{row['per_contact_s'] * 1e9:9.1f} ns per contact"
        )
    ref = next((r for r in rows if r["kind"] == "pair"), None)
    if ref:
        for r in rows:
            r["per_contact_vs_pair"] = r["per_contact_s"] / ref["per_contact_s"]
            r["step_vs_pair"] = r["step_s"] / ref["step_s"]
            print(
                f"{r['kind']:>24}: {r['per_contact_vs_pair']:.2f} x a convex pair contact, "
                f"step {r['step_vs_pair']:.2f} x"
            )
    out = Path(
        args.out
        or f"benchmarks/results/issue13/compound_contact_cost_{args.device.replace(':', '')}_{args.bodies}.json"
    )
    out.parent.mkdir(parents=True, exist_ok=True)
    meta = {"device": args.device, "warp": wp.__version__, "bodies": args.bodies, "steps": args.steps,
            "repeats": args.repeats, "precision": args.precision}  # fmt: skip
    out.write_text(json.dumps({"meta": meta, "rows": rows}, indent=1))
    print(f"wrote {out}")


if __name__ == "__main__":
    main()
