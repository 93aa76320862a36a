"""Diagnose the deepest contacts of a settling run: are they physical or a kernel error?

python benchmarks/diagnose_overlap.py --device cuda:0 --n 1000000 --steps 3725
"""

import argparse
import sys
import types

import numpy as np
import warp as wp
from settle import make_scene

import polydem


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--device", default=None)
    ap.add_argument("--n", type=int, default=1000)
    ap.add_argument("--steps", type=int, default=3725)
    ap.add_argument("--no-graph", action="store_true")
    a = ap.parse_args()
    wp.config.quiet = True
    args = types.SimpleNamespace(
        edge=0.01, layers=10, density=2500.0, load_factor=20.0, overlap=0.01, friction=0.5, restitution=0.5,
        margin=0.03, gap=[0.002, 0.02], spin=0.0, walls="box", seed=0,
    )  # fmt: skip
    scene, info = make_scene(a.n, args)
    sim = polydem.Simulation(scene, device=a.device, use_graph=None if not a.no_graph else False)
    cube_v = scene.shapes[scene.shape_names[scene.body_shape[0]]].volume
    done = 0
    while done < a.steps:
        sim.step(min(500, a.steps - done))
        done = min(done + 500, a.steps)
        c = sim.contacts()
        v = c["volume"] / cube_v
        print(f"step {done}: {len(v)} contacts, max overlap {v.max():.3%}, >5%: {(v > 0.05).sum()}", flush=True)
    st = sim.state()
    c = sim.contacts()
    order = np.argsort(c["volume"])[::-1][:5]
    shapes = scene.shape_names
    for k in order:
        ia, ib = int(c["body_a"][k]), int(c["body_b"][k])
        pa = np.concatenate([st["body_position"][ia], st["body_orientation"][ia]])
        pb = np.concatenate([st["body_position"][ib], st["body_orientation"][ib]])
        sa = scene.shapes[shapes[scene.body_shape[ia]]]
        sb = scene.shapes[shapes[scene.body_shape[ib]]]
        ref = polydem.overlap(sa, pa, sb, pb, frame="body", device=a.device, precision="float64")
        print(
            f"pair {ia}-{ib} kinds {scene.body_kind[ia]},{scene.body_kind[ib]}: V sim {c['volume'][k] / cube_v:.3%}, "
            f"V f64 {ref.volume[0] / cube_v:.3%}, normal {c['normal'][k].round(3)}, pos a {pa[:3].round(5)}, "
            f"quat a {pa[3:].round(4)}, vel a {st['body_velocity'][ia].round(4)}",
            flush=True,
        )
    sys.stdout.flush()


if __name__ == "__main__":
    main()
