"""Discharge of cubes from the conical hopper of scenes/hopper.toml, and Beverloo's law.

Beverloo, Leniger and van de Velde (1961, Chem. Eng. Sci. 15, 260) found that the mass flow rate
through a circular orifice of diameter D does not depend on the fill height and follows
W = C rho_b sqrt(g) (D - k d)^(5/2), d the grain size, k about 1.5 for spheres. Here for every
orifice of ``--orifices`` (mm; the meshes scenes/meshes/hopper_D{mm}.stl, see
scenes/meshes/make_meshes.py) and every grain count of ``--grains``:

1. fill: the grains of scenes/hopper.toml (cubes of d = 1 cm edge, hertz, e = 0.3, mu = 0.5 on
   each other, 0.4 on the steel) fall from a column into the hopper onto a gate, a plane wall
   across the orifice, for ``--fill-time`` (0.6 s: the pile has come to rest);
2. discharge: the gate is moved out of reach (its offset set far below: the same wall, no longer
   met) and the run goes on for ``--discharge-time`` seconds, counting every ``--sample`` seconds
   the grains whose centre lies below the orifice plane (z < -d);
3. the rate: a straight line through the discharged mass between 20% and 70% of what left in the
   run (``polydem.analysis.discharge_rate``: after the start-up, before the hopper runs low).

Then Beverloo's law is fitted over the orifices, once with n = 5/2 (C and k) and once with a free
exponent (C, k and n; ``polydem.analysis.fit_beverloo``), per grain count, to show how the fit
converges as the hopper holds more grains above the orifice.

    python benchmarks/hopper_discharge.py --device cpu --grains 600 --discharge-time 0.8
    python benchmarks/hopper_discharge.py --device cuda:0 --grains 2000,4000 --discharge-time 1.5

Prints a table per grain count and writes JSON to ``--out``.
"""

import argparse
import json
import time
from pathlib import Path

import numpy as np
import warp as wp

from polydem import Scene, Simulation
from polydem.analysis import discharge_rate, fit_beverloo

ROOT = Path(__file__).resolve().parents[1]
SCENE = ROOT / "scenes" / "hopper.toml"
EDGE = 0.01


def hopper_scene(orifice_mm, grains, seed, precision):
    import tomllib

    data = tomllib.loads(SCENE.read_text())
    data["walls"][0]["file"] = f"meshes/hopper_D{orifice_mm}.stl"
    data["walls"][0]["thickness"] = 0.03  # the cone is a shell with nothing behind it: no thin part
    # The gate: a plane across the orifice (removed at the end of the fill).
    data["walls"].append({"type": "plane", "point": [0.0, 0.0, 0.0], "normal": [0.0, 0.0, 1.0], "material": "steel"})
    em = data["emitters"][0]
    em["count"] = grains
    em["seed"] = seed
    # A column tall enough for the grains: 8 x 8 cells of 1.9 cm per layer.
    layers = int(np.ceil(grains / 64)) + 2
    em["region"] = {"min": [-0.08, -0.08, 0.18], "max": [0.08, 0.08, 0.18 + 0.0191 * layers]}
    data["simulation"]["precision"] = precision
    data.pop("output", None)
    return Scene.from_dict(data, file=SCENE, base_dir=SCENE.parent)


def run_one(orifice_mm, grains, args):
    scene = hopper_scene(orifice_mm, grains, args.seed, args.precision)
    t0 = time.perf_counter()
    sim = Simulation(scene, device=args.device)
    build_s = time.perf_counter() - t0
    mass = float(np.asarray(sim.model.body_mass, dtype=np.float64)[0])
    steps_fill = int(round(args.fill_time / sim.dt))
    t0 = time.perf_counter()
    sim.step(steps_fill)
    # Open the gate: move the plane out of reach (the floor is plane 0, the gate plane 1).
    offsets = sim.model.plane_offset.numpy()
    offsets[1] = -1.0e6
    sim.model.plane_offset.assign(offsets)
    chunk = max(1, int(round(args.sample / sim.dt)))
    times, out = [0.0], [0]
    t_open = sim.time
    below = -EDGE
    while sim.time - t_open < args.discharge_time:
        sim.step(chunk)
        z = sim.state()["body_position"][:, 2]
        times.append(sim.time - t_open)
        out.append(int(np.sum(z < below)))
    wp.synchronize_device(sim.device)
    run_s = time.perf_counter() - t0
    record = {
        "orifice_m": orifice_mm / 1000.0,
        "grains": grains,
        "grain_mass_kg": mass,
        "times_s": times,
        "discharged": out,
        "dt_s": sim.dt,
        "build_s": build_s,
        "run_s": run_s,
        "steps": sim.steps_done,
    }
    try:
        rate = discharge_rate(times, np.array(out) * mass)
        record["rate"] = rate.to_dict()
    except ValueError as err:
        record["rate"] = None
        record["why_no_rate"] = str(err)
    return record


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--device", default="cpu")
    ap.add_argument("--grains", default="600", help="comma-separated grain counts")
    ap.add_argument("--orifices", default="50,60,70,90", help="orifice diameters in mm (meshes hopper_D{mm}.stl)")
    ap.add_argument("--fill-time", type=float, default=0.6)
    ap.add_argument("--discharge-time", type=float, default=0.8)
    ap.add_argument("--sample", type=float, default=0.02)
    ap.add_argument("--seed", type=int, default=1)
    ap.add_argument("--precision", default="mixed")
    ap.add_argument("--out", default=None)
    args = ap.parse_args()
    wp.config.quiet = True
    grains = [int(g) for g in args.grains.split(",")]
    orifices = [int(o) for o in args.orifices.split(",")]
    runs, fits = [], []
    for n in grains:
        print(f"{n} grains")
        rows = []
        for o in orifices:
            r = run_one(o, n, args)
            runs.append(r)
            rows.append(r)
            rate = r["rate"]
            if rate:
                print(
                    f"  D = {o} mm: W = {rate['slope']:.4f} +- {rate['stderr']:.4f} kg/s "
                    f"({rate['slope'] / r['grain_mass_kg']:.0f} grains/s, window {rate['t0']:.2f}-{rate['t1']:.2f} s), "
                    f"{r['discharged'][-1]} out, {r['steps']} steps in {r['run_s']:.1f} s"
                )
            else:
                print(f"  D = {o} mm: no rate ({r['why_no_rate']})")
        ok = [r for r in rows if r["rate"]]
        entry = {"grains": n}
        if len(ok) >= 3:
            D = np.array([r["orifice_m"] for r in ok])
            W = np.array([r["rate"]["slope"] for r in ok])
            entry["fixed_n"] = fit_beverloo(D, W, EDGE, n=2.5).to_dict()
            f = entry["fixed_n"]
            print(f"  Beverloo, n = 5/2: C = {f['C']:.3g} +- {f['C_err']:.2g}, k = {f['k']:.3f} +- {f['k_err']:.3f}, "
                  f"rms residual {f['rms_relative_residual']:.3f}")  # fmt: skip
        if len(ok) >= 4:
            try:
                entry["free_n"] = fit_beverloo(D, W, EDGE).to_dict()
                f = entry["free_n"]
                print(f"  Beverloo, free n: n = {f['n']:.2f} +- {f['n_err']:.2f}, k = {f['k']:.2f} "
                      f"+- {f['k_err']:.2f}, rms residual {f['rms_relative_residual']:.3f}")  # fmt: skip
            except (RuntimeError, ValueError) as err:
                entry["free_n"] = None
                print(f"  Beverloo, free n: no fit ({err})")
        fits.append(entry)
    tag = args.device.replace(":", "")
    out = Path(args.out or ROOT / f"benchmarks/results/issue13/hopper_discharge_{tag}.json")
    out.parent.mkdir(parents=True, exist_ok=True)
    meta = {k: v for k, v in vars(args).items()}
    meta["warp"] = wp.__version__
    out.write_text(json.dumps({"meta": meta, "runs": runs, "fits": fits}, indent=1))
    print(f"wrote {out}")


if __name__ == "__main__":
    main()
