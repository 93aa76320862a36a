"""Energy budget: which part of the model makes the energy balance err, and at what order in dt.

The exact dynamics keep ``total = kinetic + contact + gravity + dissipated`` constant
(``Simulation.energy()``). This script runs three scenes with one source of error switched on at a
time and reports the energy error ``(total(t) - total(0)) / released`` at the end of the run
(``end``) and its largest magnitude during it (``max``), where ``released`` is the initial kinetic
energy plus the gravitational energy released by the end (what flowed through the contacts), at
dt = auto, dt/2 and dt/4, and the observed order ``log2(err(dt) / err(dt/2))`` (and of dt/2 to
dt/4) of the end value. The same for the first-order modified energy of symplectic Euler,
``H + dt/2 sum (v.F + w.tau)`` (``mod_*``; see tests/test_simulation.py), which takes out the O(dt)
swing of H inside a contact that the raw total shows.

Scenes (``--scenes``):

* ``cube_drop``: the first impact of ``scenes/cube_drop.toml`` (0.1 m cube, hertz k = 1e10): the
  cube starts 1 mm above the plane at the speed of its 0.15 m fall, 1.72 m/s, and is followed for
  ``--impact-time`` (the impact and its rebound);
* ``default``: the packaged default scene (``polydem.default_scene``) with ``--default-count``
  bodies (40) for ``--default-time`` (0.1 s: they drop onto the floor and each other);
* ``pile``: ``--pile-count`` 1 cm cubes (27) poured into a 6 cm box, settling for ``--pile-time``.

Sources (``--sources``), each a variant of the scene's material (the scene's own is ``shipped``):

* ``linear`` / ``hertz``: the integrator alone: e = 1, no friction, the linear law (k chosen for
  the same reference stiffness as the scene's hertz k, :func:`polydem.scene.checks.reference_stiffness`)
  or the hertz law;
* ``friction``: hertz, e = 1, mu = 0.5 (cube_drop: with 0.5 m/s sideways, so that it slides);
* ``hysteresis``: hertz, e = 0.5, no friction;
* ``coplanar`` (cube_drop only): hertz, e = 1, no friction, the cube tilted by ``--tilt`` rad about
  x (against the flat ``hertz`` run: the face-to-plane contact found coplanar or not);
* ``shipped``: the scene's own material (e < 1 and friction together).

``--precision float64`` runs the same in float64, once the simulator offers it; a refusal
(SceneError) is reported and the precision skipped.

Output: a table on stdout, JSON ``benchmarks/results/energy_budget_<device>.json``.

    python benchmarks/energy_budget.py --device cpu                 # about 4 minutes on 2 cores
    python benchmarks/energy_budget.py --device cuda:0 --default-count 300 --pile-count 1000
    python benchmarks/energy_budget.py --precision float32,float64
"""

import argparse
import copy
import json
import math
import os
import time
import tomllib
import warnings

import numpy as np
import warp as wp
from _meta import run_meta

from polydem import Scene, SceneError, Simulation
from polydem.default_scene import default_scene_path
from polydem.scene import quat_from_axis_angle
from polydem.scene.checks import reference_stiffness

HERE = os.path.dirname(os.path.abspath(__file__))
ROOT = os.path.dirname(HERE)
RESULTS = os.path.join(HERE, "results")

SOURCES = ("linear", "hertz", "friction", "hysteresis", "coplanar", "shipped")
DT_FACTORS = (1.0, 0.5, 0.25)


def log(*args):
    print(*args, flush=True)


# ---------------------------------------------------------------------------------------------
# Scenes (as scene-file dicts, so that a source only edits the material table)


def cube_drop_dict():
    """scenes/cube_drop.toml, the cube 1 mm above the plane at its impact speed."""
    with open(os.path.join(ROOT, "scenes", "cube_drop.toml"), "rb") as fh:
        data = tomllib.load(fh)
    body = data["bodies"][0]
    drop = body["position"][2] - 0.05  # fall height of the bottom face [m]
    body["position"] = [0.0, 0.0, 0.051]
    body["velocity"] = [0.0, 0.0, -math.sqrt(2.0 * 9.81 * drop)]
    data.pop("output", None)
    return data


def default_dict(count):
    """The packaged default scene with ``count`` bodies (its emitter fills the box from the bottom)."""
    with default_scene_path().open("rb") as fh:
        data = tomllib.load(fh)
    data["emitters"][0]["count"] = count
    data["emitters"][0]["fill"] = "bottom"
    data.pop("output", None)
    return data


def pile_dict(count):
    """``count`` 1 cm cubes, randomly turned, poured into a 6 cm box (hertz, e = 0.5, mu = 0.5)."""
    side = 0.06
    return {
        "simulation": {"name": "pile", "dt": "auto", "gravity": [0.0, 0.0, -9.81]},
        "materials": {"stone": {"density": 2500.0, "law": "hertz", "k": 4.69e8, "restitution": 0.5, "friction": 0.5}},
        "shapes": {"cube": {"type": "box", "size": 0.01}},
        "walls": [
            {
                "type": "box",
                "center": [0.0, 0.0, side],
                "inner_size": [side, side, 2.0 * side],
                "wall_thickness": 0.01,
                "material": "stone",
                "open_top": True,
            }
        ],
        "emitters": [
            {
                "shape": "cube",
                "material": "stone",
                "count": count,
                "region": {"min": [-side / 2, -side / 2, 0.0], "max": [side / 2, side / 2, 2.0 * side]},
                "fill": "bottom",
                "orientation": "random",
                "seed": 1,
            }
        ],
    }


def variant(base, source, args):
    """The scene dict of ``base`` with one source of error on; None where it does not apply."""
    data = copy.deepcopy(base)
    (name, mat), *rest = data["materials"].items()
    if rest:
        raise ValueError("one material expected")
    if source == "shipped":
        return data
    if source == "coplanar" and data["simulation"]["name"] != "cube_drop":
        return None
    mat.update(restitution=1.0, friction=0.0)
    if source == "linear":
        # The same reference stiffness (a face contact at 0.1% of the size) as the hertz k.
        volume = {"cube_drop": 0.1**3, "default": 0.02**3}.get(data["simulation"]["name"], 0.01**3)
        k_ref = float(reference_stiffness("hertz", mat["k"], 1.5, volume))
        area, depth = volume ** (2.0 / 3.0), 1e-3 * volume ** (1.0 / 3.0)
        mat.update(law="linear", k=k_ref * depth / area)
    elif source == "friction":
        mat["friction"] = 0.5
        if data["simulation"]["name"] == "cube_drop":
            data["bodies"][0]["velocity"][0] = 0.5
    elif source == "hysteresis":
        mat["restitution"] = 0.5
    elif source == "coplanar":
        data["bodies"][0]["orientation"] = list(quat_from_axis_angle((1.0, 0.0, 0.0), args.tilt))
    return data


# ---------------------------------------------------------------------------------------------
# Runs


def modified_energy(sim, e):
    """H + dt/2 sum (v.F + w.tau) over the free bodies (tests/test_simulation.py)."""
    m = sim.model
    free = m.body_flags_np == 0
    mass = m.body_mass[free].astype(np.float64)
    st = sim.current_state
    v = st.body_v.numpy()[free].astype(np.float64)
    w = st.body_w.numpy()[free].astype(np.float64)
    f = st.body_f.numpy()[free].astype(np.float64) + mass[:, None] * np.asarray(m.gravity, dtype=np.float64)
    tau = st.body_t.numpy()[free].astype(np.float64)
    return e["total"] + 0.5 * sim.dt * (np.sum(f * v) + np.sum(tau * w))


def run_one(data, precision, dt_factor, duration, samples, device):
    """Energy error of one run (dict), or {"skipped": reason}."""
    data = copy.deepcopy(data)
    data["simulation"]["precision"] = precision
    try:
        scene = Scene.from_dict(data)
        if dt_factor != 1.0:
            scene.dt = scene.time_step().dt * dt_factor
        sim = Simulation(scene, device)
    except SceneError as exc:
        return {"skipped": str(exc)}
    steps = max(1, round(duration / sim.dt))
    every = max(1, steps // samples)
    e0 = sim.energy()
    h0 = modified_energy(sim, e0)
    low_gravity = e0["gravity"]
    worst = worst_mod = 0.0
    t0 = time.perf_counter()
    done = 0
    while done < steps:
        n = min(every, steps - done)
        sim.step(n)
        done += n
        e = sim.energy()
        low_gravity = min(low_gravity, e["gravity"])
        d, dm = e["total"] - e0["total"], modified_energy(sim, e) - h0
        worst = d if abs(d) > abs(worst) else worst
        worst_mod = dm if abs(dm) > abs(worst_mod) else worst_mod
    wall = time.perf_counter() - t0
    released = e0["kinetic"] + max(0.0, e0["gravity"] - low_gravity)
    return {
        "dt": sim.dt,
        "steps": steps,
        "released": released,
        "end": d / released,
        "max": worst / released,
        "mod_end": dm / released,
        "mod_max": worst_mod / released,
        "dissipated": e["dissipated"] / released,
        "wall_s": wall,
    }


def order(a, b):
    """Observed order log2(|a| / |b|) of an error at dt and dt/2 (None where either is 0)."""
    if not a or not b:
        return None
    return math.log2(abs(a) / abs(b))


def fmt(x, spec="+.2e"):
    return "-" if x is None else format(x, spec)


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--device", default=None, help="Warp device (default: Warp's default)")
    ap.add_argument("--scenes", default="cube_drop,default,pile", help="comma-separated: cube_drop, default, pile")
    ap.add_argument("--sources", default=",".join(SOURCES), help="comma-separated: " + ", ".join(SOURCES))
    ap.add_argument("--precision", default="float32", help="comma-separated: float32, float64")
    ap.add_argument("--impact-time", type=float, default=3e-3, help="cube_drop: simulated time [s]")
    ap.add_argument("--default-count", type=int, default=40, help="default scene: bodies")
    ap.add_argument("--default-time", type=float, default=0.1, help="default scene: simulated time [s]")
    ap.add_argument("--pile-count", type=int, default=27, help="pile: cubes")
    ap.add_argument("--pile-time", type=float, default=0.1, help="pile: simulated time [s]")
    ap.add_argument("--tilt", type=float, default=1e-3, help="coplanar: tilt of the cube [rad]")
    ap.add_argument("--samples", type=int, default=40, help="energy samples per run")
    ap.add_argument("--out", default=None, help="JSON (default benchmarks/results/energy_budget_<device>.json)")
    args = ap.parse_args()

    wp.config.quiet = True
    wp.init()
    # The variants are deliberately unlike the scenes' materials (e = 1, no friction, a linear law):
    # their scene and run warnings (soft contacts, tunnelling) are not this benchmark's subject.
    warnings.simplefilter("ignore", UserWarning)
    device = wp.get_device(args.device)
    out = args.out or os.path.join(RESULTS, f"energy_budget_{device.alias.replace(':', '')}.json")
    os.makedirs(os.path.dirname(os.path.abspath(out)), exist_ok=True)
    record = {"meta": run_meta(device), "config": {k: v for k, v in vars(args).items() if k != "out"}, "runs": []}
    bases = {
        "cube_drop": (cube_drop_dict, args.impact_time),
        "default": (lambda: default_dict(args.default_count), args.default_time),
        "pile": (lambda: pile_dict(args.pile_count), args.pile_time),
    }
    log(f"energy budget on {device.name} ({device.alias}); JSON -> {out}")
    header = (
        f"{'scene':10s} {'source':11s} {'prec':7s} {'dt':>9s} | {'end dt':>9s} {'dt/2':>9s} {'dt/4':>9s} {'order':>11s}"
        f" | {'mod end dt':>10s} {'dt/2':>9s} {'dt/4':>9s} {'order':>11s} | {'max |err|':>9s} {'dissip.':>7s}"
    )
    log(header)
    t_all = time.perf_counter()
    for scene_name in [s.strip() for s in args.scenes.split(",") if s.strip()]:
        build, duration = bases[scene_name]
        base = build()
        for source in [s.strip() for s in args.sources.split(",") if s.strip()]:
            data = variant(base, source, args)
            if data is None:
                continue
            for precision in [p.strip() for p in args.precision.split(",") if p.strip()]:
                runs = [run_one(data, precision, f, duration, args.samples, device) for f in DT_FACTORS]
                row = {"scene": scene_name, "source": source, "precision": precision, "runs": runs}
                if any("skipped" in r for r in runs):
                    row["skipped"] = next(r["skipped"] for r in runs if "skipped" in r)
                    log(f"{scene_name:10s} {source:11s} {precision:7s} skipped: {row['skipped']}")
                else:
                    for key in ("end", "mod_end"):
                        row[f"order_{key}"] = [order(runs[i][key], runs[i + 1][key]) for i in range(2)]
                    o, om = row["order_end"], row["order_mod_end"]
                    log(
                        f"{scene_name:10s} {source:11s} {precision:7s} {runs[0]['dt']:9.3g} | "
                        + " ".join(f"{r['end']:+9.2e}" for r in runs)
                        + f" {fmt(o[0], '+5.1f')},{fmt(o[1], '+5.1f')} | "
                        + " ".join(f"{r['mod_end']:+{10 if i == 0 else 9}.2e}" for i, r in enumerate(runs))
                        + f" {fmt(om[0], '+5.1f')},{fmt(om[1], '+5.1f')} | "
                        + f"{max(abs(r['max']) for r in runs[:1]):9.2e} {runs[0]['dissipated']:7.3f}"
                    )
                record["runs"].append(row)
                tmp = out + ".tmp"
                with open(tmp, "w") as fh:
                    json.dump(record, fh, indent=1)
                os.replace(tmp, out)
    log(f"done in {time.perf_counter() - t_all:.0f} s")


if __name__ == "__main__":
    main()
