"""Set-up cost of a triangle-mesh wall: triangles per second and peak memory per triangle (issue 24).

    python benchmarks/meshwall_setup.py --label new
    PYTHONPATH=/tmp/oldroot python benchmarks/meshwall_setup.py --label old   # a copy of another polydem

The mesh is an icosphere of radius 1 m (1,280 to 327,680 triangles: every cell is also cut by the planes
of the triangles that share only a vertex with it, the costly case) behind which a 2 cm cube's default
thickness is built. Each size and stage runs in a fresh process, so that its peak resident memory is its
own: the growth of the peak over the process's memory just before the call, per triangle. Stages:

* build: ``build_cells`` alone (where it returns packed arrays, not the list of per-cell shapes);
* cells: ``build_cells`` and the list of per-cell shapes (``MeshCells.cells``), what the Model packs;
* model: ``Model(scene)`` on the CPU: the scene's checks, the cells, the packed shapes and the BVH.

Sizes stop at the first whose predicted time (4 times the last size's) passes ``--budget`` seconds.
Wall and CPU times are both kept: on a shared machine the CPU time is the steadier. Results: a table on
stdout and JSON benchmarks/results/issue24/meshwall_setup_LABEL.json.
"""

import argparse
import json
import os
import platform
import subprocess
import sys
import time

HERE = os.path.dirname(os.path.abspath(__file__))
SIZES = {1280: 3, 5120: 4, 20480: 5, 81920: 6, 327680: 7}

CHILD = r"""
import json, resource, sys, time
import numpy as np, trimesh
stage, sub = sys.argv[1], int(sys.argv[2])
mesh = trimesh.creation.icosphere(subdivisions=sub, radius=1.0)
v, f = np.asarray(mesh.vertices), np.asarray(mesh.faces)
import polydem
from polydem import ConvexShape, Scene
from polydem.meshwall import build_cells
if stage == "model":
    import warp as wp
    wp.config.quiet = True
    wp.init()
    from polydem.model import Model
    sc = Scene(gravity=(0.0, 0.0, -9.81), dt="auto")
    sc.add_material("m", density=2500.0, k=1e8, restitution=0.5, friction=0.5, law="hertz")
    sc.add_shape("cube", ConvexShape.box(0.02))
    sc.add_body("cube", "m", position=(0.0, 0.0, 1.5))
    sc.add_mesh_wall((v, f), "m")
def rss():
    with open("/proc/self/statm") as fh:
        return int(fh.read().split()[1]) * resource.getpagesize()
before = rss()
t0, c0 = time.perf_counter(), time.process_time()
if stage in ("cells", "build"):
    cells = build_cells(v, f, 2.0 * ConvexShape.box(0.02).radius)
    # (a list of cells from a polydem that builds them as such; packed arrays, made into one on demand)
    n_cells = cells.num_cells if stage == "build" and hasattr(cells, "num_cells") else len(cells.cells)
else:
    model = Model(sc, device="cpu")
    n_cells = sum(len(mc.cells) for mc in model.mesh_cells)
wall, cpu = time.perf_counter() - t0, time.process_time() - c0
peak = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss * 1024
print(json.dumps({"wall_s": wall, "cpu_s": cpu, "peak_growth_bytes": max(0, peak - before), "cells": n_cells,
                  "polydem": polydem.__file__}))
"""


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--label", required=True, help="name of this polydem in the results (old, new, ...)")
    ap.add_argument("--stages", default="build,cells,model")
    ap.add_argument("--budget", type=float, default=60.0, help="most seconds a size is predicted to take")
    ap.add_argument("--largest", type=int, default=327680)
    ap.add_argument("--out", default=None)
    args = ap.parse_args()
    out = args.out or os.path.join(HERE, "results", "issue24", f"meshwall_setup_{args.label}.json")
    record = {
        "meta": {
            "label": args.label,
            "python": platform.python_version(),
            "machine": platform.platform(),
            "cpu_count": os.cpu_count(),
            "load_average_start": os.getloadavg(),
            "command": " ".join([os.path.basename(sys.executable), *sys.argv]),
            "date": time.strftime("%Y-%m-%dT%H:%M:%S%z"),
        },
        "results": {},
    }
    print(f"{'stage':<6} {'triangles':>9} {'cells':>7} {'wall s':>8} {'cpu s':>8} {'tri/s (cpu)':>11} {'B/tri':>7}")
    for stage in args.stages.split(","):
        rows = record["results"][stage] = []
        last = 0.0
        for n, sub in SIZES.items():
            if n > args.largest or (rows and 4.0 * last > args.budget):
                print(
                    f"{stage:<6} {n:>9} skipped: about {4.0 * last:.0f} s predicted, over the {args.budget:g} s budget"
                )
                rows.append({"triangles": n, "skipped": f"predicted {4.0 * last:.0f} s"})
                continue
            proc = subprocess.run([sys.executable, "-c", CHILD, stage, str(sub)], capture_output=True, text=True)
            if proc.returncode != 0:
                print(proc.stderr[-2000:])
                return 1
            r = json.loads(proc.stdout.strip().splitlines()[-1])
            r.update(triangles=n, triangles_per_s=n / r["cpu_s"], bytes_per_triangle=r["peak_growth_bytes"] / n)
            rows.append(r)
            last = r["wall_s"]
            print(
                f"{stage:<6} {n:>9} {r['cells']:>7} {r['wall_s']:>8.2f} {r['cpu_s']:>8.2f} "
                f"{r['triangles_per_s']:>11.0f} {r['bytes_per_triangle']:>7.0f}",
                flush=True,
            )
    record["meta"]["load_average_end"] = os.getloadavg()
    os.makedirs(os.path.dirname(out), exist_ok=True)
    with open(out, "w") as fh:
        json.dump(record, fh, indent=1)
    print(f"wrote {out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
