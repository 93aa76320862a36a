"""Cost of a grain's contact with a triangle-mesh wall, against a plane wall and a convex pair contact.

Scenes (``--bodies`` N cubes of 1 cm, hertz law, restitution 0.5, friction 0.5, gravity), each cube
resting face down at its equilibrium depth with a random yaw, on a square grid 3 cm apart (no
cube touches another):

* ``plane``: on a plane wall (tested per body in the gather kernel);
* ``mesh2``: on a mesh floor of 2 triangles; ``meshT``: on a mesh floor of about ``--triangles``
  triangles, or with ``--triangle-edge E`` of squares E cube edges wide cut into two triangles (a
  jittered grid: the floor grows with N, so a fixed count gives larger triangles for larger N);
* ``pair``: each on its own fixed cube (a convex pair contact through the broad phase and the pair
  kernel), no wall;
* ``compound`` (when ``--compound`` and compound grains exist): an L of two cube parts on a fixed
  cube.

Each scene is timed twice in the same run: as above, and with every free cube lifted 5 mm (out of
contact, nothing else changed). The cost of a contact is the difference of the median step times
over N: what the contacts add to a step, the geometry, the law, friction and the gather of their
wrench. On CUDA the step is a captured graph; on the CPU the host loop.

    python benchmarks/wall_contact_cost.py --device cpu --bodies 400
    python benchmarks/wall_contact_cost.py --device cuda:0 --bodies 100000
    python benchmarks/wall_contact_cost.py --device cuda:0 --bodies 10000 --kinds meshT,pair --triangle-edge 2 \
        --mesh-paths walk,list      # the two ways to a mesh-wall contact, side by side
    python benchmarks/wall_contact_cost.py --device cuda:0 --bodies 10000 --kinds meshT,pair --triangle-edge 2 \
        --cells joined,triangles    # the flat floor as one cell, and one cell per triangle (as a curved mesh)

Prints a table and writes JSON to ``--out`` (benchmarks/results/issue13/wall_contact_cost_<device>_<N>.json).
"""

import argparse
import json
import statistics
import time
from pathlib import Path

import numpy as np
import warp as wp

from polydem import ConvexShape, Scene, Simulation

EDGE = 0.01
SPACING = 0.03


def floor_mesh(size, n, seed=0):
    xs = np.linspace(-size / 2, size / 2, n + 1)
    x, y = np.meshgrid(xs, xs, indexing="ij")
    v = np.column_stack([x.ravel(), y.ravel(), np.zeros(x.size)])
    inner = (np.abs(v[:, 0]) < size / 2 - 1e-12) & (np.abs(v[:, 1]) < size / 2 - 1e-12)
    # Up to 0.2 of a square: 0.3 (BENCHMARKS.md 22, 23) turned a few triangles over (1 at 1e4 cubes, 19 at 1e5).
    v[inner, :2] += np.random.default_rng(seed).uniform(-0.2, 0.2, (inner.sum(), 2)) * size / n
    idx = np.arange((n + 1) ** 2).reshape(n + 1, n + 1)
    a, b, c, d = idx[:-1, :-1].ravel(), idx[1:, :-1].ravel(), idx[1:, 1:].ravel(), idx[:-1, 1:].ravel()
    return v, np.concatenate([np.column_stack([a, b, c]), np.column_stack([a, c, d])])


def build(kind, n, triangles, lift, precision, seed=1, triangle_edge=None):
    sc = Scene(gravity=(0.0, 0.0, -9.81), dt="auto", precision=precision)
    sc.add_material("m", density=2500.0, law="hertz", k=1.0e8, restitution=0.5, friction=0.5)
    sc.add_shape("cube", ConvexShape.box(EDGE))
    side = int(np.ceil(np.sqrt(n)))
    size = side * SPACING
    rng = np.random.default_rng(seed)
    weight = 2500.0 * EDGE**3 * 9.81
    # Equilibrium depth of a face contact under the hertz law: W'(V) A = weight, W' = k V^0.5.
    depth = (weight / (1.0e8 * EDGE**2)) ** 2 / EDGE**2
    if kind == "plane":
        sc.add_plane((0, 0, 0), (0, 0, 1), "m")
    elif kind == "mesh2":
        sc.add_mesh_wall(floor_mesh(size + SPACING, 1), "m")
    elif kind == "meshT":
        cells = max(1, int(round(np.sqrt(triangles / 2))))
        if triangle_edge:
            cells = max(1, int(round((size + SPACING) / (triangle_edge * EDGE))))
        sc.add_mesh_wall(floor_mesh(size + SPACING, cells), "m")
    elif kind == "pair":
        sc.add_shape("base", ConvexShape.box(EDGE))
    for k in range(n):
        i, j = divmod(k, side)
        x, y = (i - (side - 1) / 2) * SPACING, (j - (side - 1) / 2) * SPACING
        yaw = rng.uniform(0, 2 * np.pi)
        q = (0.0, 0.0, np.sin(yaw / 2), np.cos(yaw / 2))
        z = 0.5 * EDGE - depth + lift
        if kind == "pair":
            sc.add_body("base", "m", position=(x, y, -0.5 * EDGE), orientation=q, kind="fixed")
        sc.add_body("cube", "m", position=(x, y, z), orientation=q)
    return sc


def time_steps(sim, steps, repeats):
    sim.step(steps)  # warm-up: compile, capture
    wp.synchronize_device(sim.device)
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        sim.step(steps)
        wp.synchronize_device(sim.device)
        times.append((time.perf_counter() - t0) / steps)
    return statistics.median(times)


def candidate_counts(sim):
    """Through the candidate list: the (body, cell) candidates a free body and those whose overlap is not empty (the
    clippings a step does, and those that count), or None (the walk)."""
    cand = sim.stepper.mesh_candidates
    if cand is None:
        return None
    c = cand.candidates
    total = int(c.total.numpy()[0])
    overlapping = int((c.volume.numpy()[:total] > 0.0).sum())
    free = int((sim.model.body_flags_np == 0).sum())
    return {"candidates_per_body": total / free, "overlapping_per_body": overlapping / free}


def kernel_profile(scene, device, mesh_candidates, join, steps):
    """GPU milliseconds per step of each kernel (Warp's activity timing; the host loop, no graph), largest first."""
    sim = Simulation(scene, device=device, use_graph=False, mesh_candidates=mesh_candidates, join_flat_cells=join)
    sim.step(steps)  # warm-up: compile, grow the buffers
    wp.synchronize_device(sim.device)
    wp.timing_begin(cuda_filter=wp.TIMING_KERNEL | wp.TIMING_MEMCPY | wp.TIMING_MEMSET)
    sim.step(steps)
    totals = {}
    for r in wp.timing_end():
        name = r.name.split("make_")[-1] if r.name else r.filter
        totals[name] = totals.get(name, 0.0) + r.elapsed / steps
    return dict(sorted(totals.items(), key=lambda kv: -kv[1]))


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--device", default="cpu")
    ap.add_argument("--bodies", type=int, default=400)
    ap.add_argument("--triangles", type=int, default=2048)
    ap.add_argument(
        "--triangle-edge", type=float, default=None, help="squares of this many cube edges (overrides --triangles)"
    )
    ap.add_argument("--steps", type=int, default=50)
    ap.add_argument("--repeats", type=int, default=5)
    ap.add_argument("--precision", default="mixed")
    ap.add_argument("--kinds", default="plane,mesh2,meshT,pair")
    ap.add_argument(
        "--mesh-paths",
        default="default",
        help="the mesh kinds' contacts through: 'walk' (a thread per body), 'list' (the (body, cell) candidate "
        "list), 'default' (the device's default); several comma-separated: a row each, in the same run",
    )
    ap.add_argument(
        "--cells",
        default="joined",
        help="the mesh kinds' cells: 'joined' (a flat patch's cells joined where convex together, the default), "
        "'triangles' (one per triangle, as on a curved mesh); both comma-separated: a row each, in the same run",
    )
    ap.add_argument("--profile", action="store_true", help="CUDA: each kernel's GPU time per step, in contact")
    ap.add_argument("--out", default=None)
    args = ap.parse_args()
    paths = {"walk": False, "list": True, "default": None}
    mesh_paths = args.mesh_paths.split(",")
    if not mesh_paths or any(p not in paths for p in mesh_paths):
        ap.error(f"--mesh-paths takes walk, list or default (comma-separated), got {args.mesh_paths!r}")
    cell_kinds = args.cells.split(",")
    if not cell_kinds or any(c not in ("joined", "triangles") for c in cell_kinds):
        ap.error(f"--cells takes joined or triangles (comma-separated), got {args.cells!r}")
    wp.config.quiet = True
    rows = []
    runs = [
        (k, p, c)
        for k in args.kinds.split(",")
        for p in (mesh_paths if k.startswith("mesh") else [None])
        for c in (cell_kinds if k.startswith("mesh") else ["joined"])
    ]
    for kind, path, cells in runs:
        join = cells == "joined"
        res = {}
        for lifted in (False, True):
            scene = build(kind, args.bodies, args.triangles, 0.005 if lifted else 0.0, args.precision,
                          triangle_edge=args.triangle_edge)  # fmt: skip
            sim = Simulation(
                scene, device=args.device, mesh_candidates=paths[path] if path else None, join_flat_cells=join
            )
            if kind == "meshT":
                row_triangles = len(scene.mesh_walls[0].triangles)
                row_cells = sim.model.mesh_cells[0].num_cells
            t = time_steps(sim, args.steps, args.repeats)
            c = sim.contacts()
            res[lifted] = (t, len(c["volume"]), candidate_counts(sim))
        (t_on, contacts, counts), (t_off, _, _) = res[False], res[True]
        row = {
            "kind": (kind if path in (None, "default") else f"{kind}/{path}") + ("" if join else "/tri"),
            "mesh_path": path,
            "cells": cells if kind.startswith("mesh") else None,
            "step_s": t_on,
            "step_lifted_s": t_off,
            "contacts": contacts,
            "per_contact_s": (t_on - t_off) / max(contacts, 1),
        }
        if counts:
            row.update(counts)
        if kind == "meshT":
            row["triangles"] = row_triangles
            row["mesh_cells"] = row_cells
            side = int(np.ceil(np.sqrt(args.bodies)))
            row["triangle_edge_in_cube_edges"] = (side * SPACING + SPACING) / np.sqrt(row_triangles / 2) / EDGE
        if args.profile and wp.get_device(args.device).is_cuda:
            scene = build(kind, args.bodies, args.triangles, 0.0, args.precision, triangle_edge=args.triangle_edge)
            row["kernel_ms_per_step"] = kernel_profile(
                scene, args.device, paths[path] if path else None, join, args.steps
            )
            for name, ms in list(row["kernel_ms_per_step"].items())[:8]:
                print(f"{'':>12}{ms:9.4f} ms  {name[:90]}")
        rows.append(row)
        print(
            f"{row['kind']:>14}: step {t_on * 1e3:9.4f} ms, lifted {t_off * 1e3:9.4f} ms, {contacts} contacts, "
            f"{row['per_contact_s'] * 1e9:9.1f} ns per contact"
            + (f"; a body's cells: {counts['candidates_per_body']:.2f} listed, {counts['overlapping_per_body']:.2f} "
               "overlapping" if counts else "")
        )  # fmt: skip
    ref = next((r for r in rows if r["kind"] == "pair"), None)
    if ref:
        for r in rows:
            r["per_contact_vs_pair"] = r["per_contact_s"] / ref["per_contact_s"]
            print(f"{r['kind']:>14}: {r['per_contact_vs_pair']:.2f} x a convex pair contact")
    out = Path(
        args.out or f"benchmarks/results/issue13/wall_contact_cost_{args.device.replace(':', '')}_{args.bodies}.json"
    )
    out.parent.mkdir(parents=True, exist_ok=True)
    meta = {"device": args.device, "warp": wp.__version__, "bodies": args.bodies, "triangles": args.triangles,
            "triangle_edge": args.triangle_edge,
            "steps": args.steps, "repeats": args.repeats, "precision": args.precision,
            "mesh_paths": mesh_paths, "cells": cell_kinds}  # fmt: skip
    out.write_text(json.dumps({"meta": meta, "rows": rows}, indent=1))
    print(f"wrote {out}")


if __name__ == "__main__":
    main()
