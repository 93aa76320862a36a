"""The overlap of grains on a large tilted mesh floor in mixed precision, with the floor's cells joined into one
and one per triangle, against float64 with one cell per triangle (CPU).

A floor of ``--size`` m (``--cells`` squares a side, jittered by 0.2 of a square) tilted by 0.4 rad, and
12 cubes and rocks (of tests/test_meshwall.py) pressed 1e-6 to 1e-4 m into it within 0.3 m of its middle,
where a joined cell's far corners are farthest from the contact. Prints the largest relative error of the
overlap volumes of each run.

    python benchmarks/joined_cells_precision.py --size 8
"""

import argparse
import sys
from pathlib import Path

import numpy as np
import warp as wp

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))
from test_meshwall import base_scene, floor_grid, lowest  # noqa: E402

from polydem import Simulation  # noqa: E402


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--size", type=float, default=8.0)
    ap.add_argument("--cells", type=int, default=40)
    args = ap.parse_args()
    wp.config.quiet = True
    v, f = floor_grid(args.cells, size=args.size, jitter=0.2)
    c, s = np.cos(0.4), np.sin(0.4)
    turn = np.array([[1.0, 0.0, 0.0], [0.0, c, -s], [0.0, s, c]])
    v, up = v @ turn.T, turn @ np.array([0.0, 0.0, 1.0])
    volumes = {}
    for precision in ("float64", "mixed"):
        for join in (False, True):
            sc = base_scene(precision)
            sc.add_mesh_wall((v, f), "m", thickness=0.05)
            rng = np.random.default_rng(2)
            for k in range(12):
                q = rng.normal(size=4)
                q /= np.linalg.norm(q)
                at = turn @ np.array([rng.uniform(-0.3, 0.3), rng.uniform(-0.3, 0.3), 0.0])
                shape = "rock" if k % 2 else "cube"
                depth = 10 ** rng.uniform(-6, -4)
                sc.add_body(shape, "m", position=at + up * (-lowest(sc.shapes[shape], q, up) - depth), orientation=q)
            cts = Simulation(sc, device="cpu", join_flat_cells=join).contacts()
            volumes[precision, join] = cts["volume"][np.argsort(cts["body_a"])]
    ref = volumes["float64", False]
    for (precision, join), vol in volumes.items():
        err = np.abs(vol / ref - 1.0)
        print(f"{precision:>8} {'joined' if join else 'one cell per triangle':>22}: largest error {err.max():.2e}")


if __name__ == "__main__":
    main()
