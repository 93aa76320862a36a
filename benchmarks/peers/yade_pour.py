"""Yade's Polyhedra module on the peers' pour (see pour_scene.py): time per body-step.

Runs inside Yade (Debian/Ubuntu: ``apt-get install yade``), not in polydem's virtual environment:

    python benchmarks/peers/pour_scene.py export --grains 1000
    yade -n -j 1 -x benchmarks/peers/yade_pour.py --grains 1000       # one thread
    yade -n -j 2 -x benchmarks/peers/yade_pour.py --grains 1000       # OpenMP, two threads

Every cube and wall is a Yade ``Polyhedra`` built from the exported world vertices (so the poses are
exactly polydem's), walls fixed. Contacts: ``Ig2_Polyhedra_Polyhedra_PolyhedraGeom`` (the overlap
polyhedron from CGAL), ``Law2_PolyhedraGeom_PolyhedraPhys_Volumetric``: a normal force proportional
to the overlap volume, ``F = kn V`` (``volumePower`` 1), and Coulomb friction (``ks = kn * poisson``,
friction angle atan(0.5)). This is not polydem's law (hertz, force ``k sqrt(V) |S_A|`` along the
gradient of V), so kn is matched to the same design point instead: a face contact carrying 20
column weights overlaps by 1% of a cube, ``kn = F_design / V_design`` (``young = 2 kn``, since Yade
takes ``1/kn = 1/Y1 + 1/Y2``). Yade's law has no restitution; ``NewtonIntegrator(damping=...)``
(non-viscous local damping, default 0.3 here) dissipates instead. Same step as polydem.

Protocol: ``--warmup`` steps, then ``--steps`` timed (``O.run(n, True)``); the final poses and
Yade's own overlap volumes are written to ``results/peers/yade_pour_<N>_j<threads>.json``.
"""

import argparse
import json
import math
import os
import sys
import time

from yade import Bo1_Polyhedra_Aabb as BoundPolyhedra
from yade import (
    ForceResetter,
    Ig2_Polyhedra_Polyhedra_PolyhedraGeom,
    InsertionSortCollider,
    InteractionLoop,
    Ip2_PolyhedraMat_PolyhedraMat_PolyhedraPhys,
    Law2_PolyhedraGeom_PolyhedraPhys_Volumetric,
    NewtonIntegrator,
    O,
    PolyhedraMat,
    Vector3,
    polyhedra_utils,
)


def _script_dir():
    # Yade runs the script through execfile: __file__ is Yade's launcher, the script is in argv.
    for a in sys.argv:
        if a.endswith(".py") and os.path.exists(a):
            return os.path.dirname(os.path.abspath(a))
    return os.path.join(os.getcwd(), "benchmarks", "peers")


HERE = _script_dir()
OUT_DIR = os.path.normpath(os.path.join(HERE, "..", "results", "peers"))
sys.path.insert(0, os.path.dirname(HERE))
from _meta import run_meta  # noqa: E402


def _yade_version():
    try:
        import yade.config

        return str(yade.config.version)
    except Exception:
        return ""


def quiet_yade_log():
    # Polyhedra_support's "do_intersect: Unhandled switch case" warning comes once per pair and step
    # in a pile (millions of lines); keep errors only.
    try:
        from yade import log

        log.setLevel("Default", log.ERROR)
    except Exception:
        pass


def main(argv):
    quiet_yade_log()
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--grains", type=int, default=1000)
    ap.add_argument("--scene", default=None, help="exported pour (default results/peers/pour_<N>.json)")
    ap.add_argument("--warmup", type=int, default=1250)
    ap.add_argument("--steps", type=int, default=500)
    ap.add_argument("--damping", type=float, default=0.3, help="NewtonIntegrator local damping")
    ap.add_argument("--verlet", type=float, default=None, help="collider Verlet distance [m] (default polydem's skin)")
    ap.add_argument("--out", default=None)
    args = ap.parse_args(argv)
    path = args.scene or os.path.join(OUT_DIR, f"pour_{args.grains}.json")
    with open(path) as f:
        sc = json.load(f)

    if args.verlet is None:
        # polydem's default skin: a fifth of the bounding radius of a cube.
        args.verlet = 0.2 * 0.5 * math.sqrt(3.0) * sc["edge"]
    design = sc["design"]
    kn = design["design_force_N"] / design["design_overlap_volume_m3"]  # N/m^3
    mat = PolyhedraMat()
    mat.density = sc["density"]
    mat.young = 2.0 * kn
    mat.poisson = 1.0  # ks = kn
    mat.frictionAngle = math.atan(sc["material"]["friction"])
    O.materials.append(mat)

    t0 = time.perf_counter()
    for w in sc["walls"]:
        O.bodies.append(polyhedra_utils.polyhedra(mat, v=[Vector3(*p) for p in w["world_vertices"]], fixed=True))
    first = len(O.bodies)
    for verts in sc["cubes"]["world_vertices"]:
        O.bodies.append(polyhedra_utils.polyhedra(mat, v=[Vector3(*p) for p in verts]))
    t_build = time.perf_counter() - t0
    cubes = list(range(first, len(O.bodies)))

    g = sc["gravity"]
    O.engines = [
        ForceResetter(),
        InsertionSortCollider([BoundPolyhedra()], verletDist=args.verlet),
        InteractionLoop(
            [Ig2_Polyhedra_Polyhedra_PolyhedraGeom()],
            [Ip2_PolyhedraMat_PolyhedraMat_PolyhedraPhys()],
            [Law2_PolyhedraGeom_PolyhedraPhys_Volumetric()],
        ),
        NewtonIntegrator(damping=args.damping, gravity=Vector3(*g)),
    ]
    O.dt = sc["dt"]
    threads = O.numThreads if hasattr(O, "numThreads") else None

    t0 = time.perf_counter()
    O.run(args.warmup, True)
    t_warm = time.perf_counter() - t0
    t0 = time.perf_counter()
    O.run(args.steps, True)
    wall = time.perf_counter() - t0

    n = len(cubes)
    vols = []
    for i in O.interactions:
        if i.isReal and i.geom is not None and getattr(i.geom, "penetrationVolume", 0.0) == i.geom.penetrationVolume:
            if i.geom.penetrationVolume > 0.0:
                vols.append(float(i.geom.penetrationVolume))
    final_pos = []
    final_q = []
    for b in cubes:
        st = O.bodies[b].state
        # The body frame of a Yade polyhedron is its own principal frame, not polydem's; compare.py
        # therefore uses the world vertices, written below, rather than the pose.
        final_pos.append([float(st.pos[k]) for k in range(3)])
        axis, angle = st.ori.toAxisAngle()
        s = math.sin(0.5 * angle)
        final_q.append([float(axis[0] * s), float(axis[1] * s), float(axis[2] * s), math.cos(0.5 * angle)])
    world_vertices = []
    for b in cubes:
        body = O.bodies[b]
        st = body.state
        world_vertices.append([[float(c) for c in (st.pos + st.ori * v)] for v in body.shape.v])

    result = {
        "code": "yade",
        "version": _yade_version(),
        "module": "Polyhedra (Ig2_Polyhedra_Polyhedra_PolyhedraGeom, Law2_PolyhedraGeom_PolyhedraPhys_Volumetric)",
        "device": "CPU",
        "threads": threads,
        "grains": n,
        "dt": O.dt,
        "kn_N_per_m3": kn,
        "damping": args.damping,
        "verlet_distance_m": args.verlet,
        "warmup_steps": args.warmup,
        "steps": args.steps,
        "build_s": t_build,
        "warmup_s": t_warm,
        "wall_s": wall,
        "step_s": wall / args.steps,
        "body_steps_per_s": n * args.steps / wall,
        "contacts": len(vols),
        "max_overlap_volume_fraction_own": (max(vols) / sc["cube_volume"]) if vols else 0.0,
        "final": {"position": final_pos, "orientation_xyzw": final_q, "world_vertices": world_vertices},
        "meta": {**run_meta(), "command": "yade " + " ".join(sys.argv)},
    }
    out = args.out or os.path.join(OUT_DIR, f"yade_pour_{n}_j{threads}.json")
    with open(out, "w") as f:
        json.dump(result, f)
    print(
        f"yade Polyhedra: {n} cubes, {threads} thread(s), {args.steps} steps after {args.warmup}: "
        f"{1e3 * wall / args.steps:.2f} ms/step, {n * args.steps / wall:.0f} body-steps/s, {len(vols)} contacts, "
        f"largest overlap {100 * result['max_overlap_volume_fraction_own']:.2f}% of a cube; wrote {out}",
        flush=True,
    )


if __name__ == "__main__":
    # Yade passes the script's own arguments after the script name.
    argv = sys.argv[1:]
    if argv and argv[0].endswith(".py"):
        argv = argv[1:]
    main(argv)
    O.exitNoBacktrace() if hasattr(O, "exitNoBacktrace") else None
