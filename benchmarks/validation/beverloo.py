"""Beverloo's discharge law for angular grains: cubes out of a flat-bottomed bin (VALIDATION.md, section 3).

Beverloo, Leniger and van de Velde (1961, Chem. Eng. Sci. 15, 260) measured the mass flow rate of granular
solids through a circular orifice of diameter D in the flat floor of a bin and found it independent of the
fill height (once the bed is a couple of orifice sizes deep) and

    W = C rho_b sqrt(g) (D - k d)^(5/2),

rho_b the bulk density of the bed, d the grain size, C about 0.55-0.65 and k about 1.5 for their
near-spherical seeds. For angular grains k is larger: k of about 2.9 is often quoted from Nedderman,
Tuzun, Savage and Houlsby (Chem. Eng. Sci. 37 (1982) 1597); both are quoted ranges, not refitted here.

The setup is Beverloo's: a square bin with a flat floor, a circular orifice in its centre.

* The floor is a mesh wall made here with trimesh: a square plate with a circular hole of ``--segments``
  (48) sides, each side joined to the bin's edge by two triangles (a fan of 2 x segments triangles: few
  cells over each grain, as a mesh wall clips every cell under a grain in one thread), its top at z = 0,
  solid ``--plate`` (one grain size) deep below it, so the orifice is a sharp-edged hole in a plate one
  grain thick. Its flat part is exactly a plane for the grains (README.md, "Triangle-mesh walls").
* The side walls are four planes, bin width L >= 2.5 D and >= D + 30 d (the conditions quoted by
  Nedderman for a rate that does not depend on the bin): L = max(2.5 D, D + 30 d) per orifice, rounded up to a whole d.
* A gate, a plane at the plate's underside (z = -plate), closes the orifice during the fill (the slide
  gate of an experiment: the grains above the hole rest on it), then is moved out of reach (its offset
  set far below, as benchmarks/hopper_discharge.py does) to start the discharge. A catch floor 0.3 m
  lower collects the grains that left.
* Grains: the cubes of d = 1 cm of scenes/hopper.toml with its materials unchanged (the project's
  material, set independently of this measurement: grain 2500 kg/m^3, hertz k = 3e8, e = 0.3, mu = 0.5,
  steel walls mu = 0.4), dt = "auto", mixed precision.
* Fill: an emitter grid over the bin's whole section (cells one bounding diameter wide, random
  orientations), as tall a column as the grains need, released at once; the run stops filling as soon as
  the pile is at rest (the project's settle measure, ``polydem.settle.SettleCriterion``: kinetic energy
  below ``--settle-kinetic`` (1e-5) of the potential energy released and no grain faster than
  ``--settle-speed`` (5 cm/s), for 0.02 s), at the latest after ``--fill-time``. The grain count is
  derived from the bin and the fill height ``head * D + extra * d`` at a packing fraction of 0.70 (a
  sizing guess only), and printed.
* Bulk density: rho_b = phi * 2500 kg/m^3, phi the exact packing fraction (``polydem.measures``) of the
  bed just before the gate opens, two grain sizes in from the walls, the floor and the top.
* Count: every ``--sample`` s the grains whose centre lies a grain size below the plate (z < -plate - d)
  have passed the orifice. The mean head above the floor, H = (grains above the plate) v / (phi L^2), is
  followed, and the run stops counting before H drops below ``head * D`` (2.5 D; or after
  ``--discharge-time``): the bed stays deep enough for Beverloo's height-independent rate throughout.
* Rate: ``polydem.analysis.discharge_rate`` (a straight line through the discharged mass, here over 20% to
  100% of what left before the stop: past the start-up, and the stop is already before the bed runs low).

Fits (``polydem.analysis.fit_beverloo``) of W / (rho_b sqrt(g)) against D, so C is Beverloo's
dimensionless C: per seed, over the mean of the seeds per orifice, and over every run; each with n = 5/2
(C, k with standard errors) and with n free (C, k, n; needs four orifices).

    python benchmarks/validation/beverloo.py --size tiny                        # CPU smoke run (CI)
    python benchmarks/validation/beverloo.py --size full --device cuda:0 --seeds 1 --first-seed 1 --tag s1
    python benchmarks/validation/beverloo.py --merge benchmarks/results/validation/beverloo_cuda0_s*.json

``--size full`` on one H100 is about 15-40k grains and 50-80k steps per run (see VALIDATION.md section 3
for the commands and their times); run one seed per call and fit them together with ``--merge``.
"""

from __future__ import annotations

import argparse
import json
import math
import sys
import time
import tomllib
from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve().parent
ROOT = HERE.parents[1]
RESULTS = HERE.parent / "results" / "validation"
SCENE = ROOT / "scenes" / "hopper.toml"  # the project's grain and wall materials
G = 9.81
PHI_GUESS = 0.70  # the poured cubes of the first full run (0.67-0.70): only to size the fill (rho_b is measured)

# Per size: orifices D/d, seeds, bin width L = max(wall_factor D, D + wall_extra d), the least head
# (head D) kept during the counting, the extra fill above it (extra d), the fill cap, the longest
# discharge, the sampling interval. "tiny" is a CPU smoke run (CI): a bin one grain wider than the orifice
# on each side and a bed one D deep, far from the law's conditions (it checks the machinery, not Beverloo);
# "full" the literature's conditions.
SIZES = {
    "tiny": {"orifices": "6,7", "seeds": 1, "wall_factor": 1.0, "wall_extra": 2.0, "head": 1.0, "extra": 1.5,
             "fill_time": 0.3, "discharge_time": 0.2, "sample": 0.005},
    "full": {"orifices": "6,7,8,10,12", "seeds": 3, "wall_factor": 2.5, "wall_extra": 30.0, "head": 2.5,
             "extra": 4.0, "fill_time": 1.2, "discharge_time": 0.6, "sample": 0.01},
}  # fmt: skip

PUBLISHED = {
    "C": "0.55-0.65 (Beverloo, Leniger and van de Velde 1961; 0.58 is the value usually quoted)",
    "k_spheres": "about 1.5 (Beverloo 1961, near-spherical seeds)",
    "k_angular": "about 2.9 for angular grains (as quoted from Nedderman, Tuzun, Savage and Houlsby, "
    "Chem. Eng. Sci. 37 (1982) 1597)",
}


# ------------------------------------------------------------------------------------------ geometry


def plate_mesh(half_width: float, radius: float, segments: int):
    """(vertices (2S, 3), triangles (2S, 3)) of a square plate [-a, a]^2 at z = 0 with a circular hole of
    ``radius`` in its centre (a regular polygon of S = ``segments`` sides, S a multiple of 8 so that the
    square's corners lie on its rays), facing +z (counter-clockwise seen from above). Each side of the
    hole is joined to the bin's edge along the same two rays: 2 S triangles."""
    if segments % 8 or segments < 8:
        raise ValueError(f"segments must be a positive multiple of 8 (the square's corners on rays), got {segments}")
    if radius >= half_width:
        raise ValueError(f"the hole (radius {radius:g} m) must be smaller than the plate (half width {half_width:g})")
    ang = 2.0 * np.pi * np.arange(segments) / segments
    u = np.column_stack([np.cos(ang), np.sin(ang)])
    inner = radius * u
    outer = half_width * u / np.max(np.abs(u), axis=1, keepdims=True)  # the ray's point on the square
    xy = np.concatenate([inner, outer])
    verts = np.column_stack([xy, np.zeros(len(xy))])
    i = np.arange(segments)
    j = (i + 1) % segments
    # Quad (inner i, outer i, outer j, inner j) counter-clockwise from above: two triangles.
    tris = np.concatenate([np.column_stack([i, segments + i, segments + j]), np.column_stack([i, segments + j, j])])
    return verts, tris


def bin_width(D: float, d: float, factor: float, extra: float, override: float | None) -> float:
    """The bin's inner width [m]: ``override`` * d where given, else max(factor D, D + extra d) rounded up to d."""
    if override:
        return override * d
    return math.ceil(round(max(factor * D, D + extra * d) / d, 9)) * d


def build(D: float, seed: int, p) -> tuple:
    """The scene for orifice D [m] and emitter seed, and a dict of its geometry."""
    import trimesh

    import polydem

    d = p["d"]
    data = tomllib.loads(SCENE.read_text())
    sim_t = data["simulation"]
    sc = polydem.Scene(gravity=tuple(sim_t["gravity"]), dt=sim_t["dt"], name="beverloo", precision=p["precision"])
    for name, props in data["materials"].items():
        sc.add_material(name, **props)
    grain = next(iter(data["emitters"]))["material"]  # "grain"
    wall = data["walls"][0]["material"]  # "steel"
    density = float(data["materials"][grain]["density"])
    sc.add_shape("cube", polydem.ConvexShape.box(d))

    L = bin_width(D, d, p["wall_factor"], p["wall_extra"], p["width"])
    a = 0.5 * L
    t = p["plate"]
    for n in ((1, 0, 0), (-1, 0, 0), (0, 1, 0), (0, -1, 0)):
        sc.add_plane((-a * n[0], -a * n[1], 0.0), n, wall)
    sc.add_plane((0.0, 0.0, -t - p["catch"]), (0, 0, 1), wall)  # the catch floor
    sc.add_plane((0.0, 0.0, -t), (0, 0, 1), wall)  # the gate: plane 5, opened by moving it away
    verts, tris = plate_mesh(a, 0.5 * D, p["segments"])
    mesh = trimesh.Trimesh(vertices=verts, faces=tris, process=False)
    sc.add_mesh_wall(mesh, wall, thickness=t)

    # The fill: H0 = head D + extra d of bed at PHI_GUESS over the section.
    v = d**3
    fill_height = p["head"] * D + p["extra"] * d
    grains = int(math.ceil(PHI_GUESS * L * L * fill_height / v))
    cell = p["spacing"] * math.sqrt(3.0) * d
    across = int(L // cell)
    layers = math.ceil(grains / across**2)
    z0 = 0.02 * d
    top = z0 + (layers + 1.0) * cell
    sc.emit("cube", grain, grains, ((-a, -a, z0), (a, a, top)), seed=seed, spacing=p["spacing"])
    geom = {"D_m": D, "D_over_d": D / d, "bin_width_m": L, "plate_m": t, "segments": p["segments"],
            "triangles": int(len(tris)), "grains": grains, "fill_height_target_m": fill_height,
            "column_top_m": top, "grain_density": density, "grain_volume_m3": v}  # fmt: skip
    return sc, geom


# ------------------------------------------------------------------------------------------------ run


def run_one(D: float, seed: int, p, device: str) -> dict:
    import warp as wp

    from polydem import Simulation, measures
    from polydem.analysis import discharge_rate
    from polydem.settle import SettleCriterion

    d = p["d"]
    t0 = time.perf_counter()
    sc, geom = build(D, seed, p)
    sim = Simulation(sc, device=device)
    build_s = time.perf_counter() - t0
    L, t, v = geom["bin_width_m"], geom["plate_m"], geom["grain_volume_m3"]
    mass = float(np.asarray(sim.model.body_mass, dtype=np.float64)[0])

    # 1. Fill until at rest (or the cap).
    t0 = time.perf_counter()
    crit = SettleCriterion(kinetic_fraction=p["settle_kinetic"], max_speed=p["settle_speed"], hold=0.02)
    fill = sim.run_until_settled(p["fill_time"], crit)
    wp.synchronize_device(sim.device)
    fill_s = time.perf_counter() - t0
    z = sim.state()["body_position"][:, 2]
    inbin = z > -t
    top = float(np.percentile(z[inbin], 99.0))  # the bed's surface (the top 1% are within its top layer)
    box = measures.Box((-0.5 * L + 2 * d, -0.5 * L + 2 * d, 2 * d), (0.5 * L - 2 * d, 0.5 * L - 2 * d, top - 2 * d))
    near = measures.Box(box.lower - d, box.upper + d).contains(sim.state()["body_position"])
    phi = measures.packing_fraction(measures.Grains.from_simulation(sim, bodies=near), box)
    rho_b = phi * geom["grain_density"]
    n_bin0 = int(inbin.sum())
    head0 = n_bin0 * v / (phi * L * L)
    head_min = p["head"] * D

    # 2. Open the gate (plane 5) and count.
    offsets = sim.model.plane_offset.numpy()
    offsets[5] = -1.0e6
    sim.model.plane_offset.assign(offsets)
    chunk = max(1, int(round(p["sample"] / sim.dt)))
    below = -t - d

    def over_orifice(pos):
        # The surface above the orifice: the highest centre within D/2 of the axis (the crater, if any).
        axis = (np.hypot(pos[:, 0], pos[:, 1]) < 0.5 * D) & (pos[:, 2] > -t)
        return float(pos[axis, 2].max()) if axis.any() else 0.0

    times, out, heads, centre = [0.0], [0], [head0], [over_orifice(sim.state()["body_position"])]
    t_open = sim.time
    stop = "time"
    t1 = time.perf_counter()
    while sim.time - t_open < p["discharge_time"] - 1e-9:
        sim.step(chunk)
        pos = sim.state()["body_position"]
        z = pos[:, 2]
        h = float(np.sum(z > -t)) * v / (phi * L * L)
        times.append(sim.time - t_open)
        out.append(int(np.sum(z < below)))
        heads.append(h)
        centre.append(over_orifice(pos))
        if h < head_min:
            stop = "head"  # this sample's bed is below the least head: leave it out of the rate
            times.pop(), out.pop(), heads.pop(), centre.pop()
            break
        lag = int(round(0.2 / p["sample"]))
        if len(out) > lag and out[-1] == out[-1 - lag]:
            stop = "jammed"  # nothing left in 0.2 s (an arch that did not break)
            break
    wp.synchronize_device(sim.device)
    discharge_s = time.perf_counter() - t1
    rec = {**geom, "seed": seed, "grain_mass_kg": mass, "dt_s": sim.dt,
           "fill": {"settled": bool(fill.settled), "time_s": fill.time, "steps": fill.steps,
                    "largest_speed": fill.largest_speed, "kinetic": fill.kinetic, "released": fill.released},
           "packing_fraction": phi, "rho_b": rho_b, "bed_top_m": top, "head0_m": head0, "head_min_m": head_min,
           "grains_in_bin": n_bin0, "times_s": times, "discharged": out, "head_m": heads,
           "surface_over_orifice_m": centre, "stop": stop, "steps": sim.steps_done,
           "build_s": build_s, "fill_s": fill_s, "discharge_s": discharge_s}  # fmt: skip
    if stop == "jammed":
        rec["rate"] = None
        rec["why_no_rate"] = f"the orifice jammed after {out[-1]} grains"
        return rec
    try:
        rate = discharge_rate(times, np.array(out, dtype=np.float64) * mass, lo=p["lo"], hi=1.0)
        rec["rate"] = rate.to_dict()
        rec["W_norm"] = rate.slope / (rho_b * math.sqrt(G))  # W / (rho_b sqrt g) [m^2.5]
        rec["W_norm_err"] = rate.stderr / (rho_b * math.sqrt(G))
    except ValueError as err:
        rec["rate"] = None
        rec["why_no_rate"] = str(err)
    return rec


# ----------------------------------------------------------------------------------------------- fits


def _fit(D, y, d):
    from polydem.analysis import fit_beverloo

    out = {"points": len(D)}
    try:
        out["n_fixed"] = fit_beverloo(D, y, d, n=2.5).to_dict()
    except (ValueError, RuntimeError) as err:
        out["n_fixed"] = None
        out["n_fixed_why"] = str(err)
    try:
        out["n_free"] = fit_beverloo(D, y, d).to_dict()
    except (ValueError, RuntimeError) as err:
        out["n_free"] = None
        out["n_free_why"] = str(err)
    return out


def fits(runs: list, d: float) -> dict:
    ok = [r for r in runs if r.get("rate")]
    res = {"per_seed": {}, "over_seed_means": None, "over_runs": None, "means": []}
    for s in sorted({r["seed"] for r in ok}):
        rs = sorted((r for r in ok if r["seed"] == s), key=lambda r: r["D_m"])
        res["per_seed"][str(s)] = _fit(np.array([r["D_m"] for r in rs]), np.array([r["W_norm"] for r in rs]), d)
    Ds = sorted({r["D_m"] for r in ok})
    for D in Ds:
        y = np.array([r["W_norm"] for r in ok if r["D_m"] == D])
        sem = float(y.std(ddof=1) / math.sqrt(len(y))) if len(y) > 1 else None
        res["means"].append({"D_m": D, "W_norm": float(y.mean()), "sem": sem, "seeds": len(y)})
    if Ds:
        res["over_seed_means"] = _fit(np.array(Ds), np.array([m["W_norm"] for m in res["means"]]), d)
        res["over_runs"] = _fit(np.array([r["D_m"] for r in ok]), np.array([r["W_norm"] for r in ok]), d)
    return res


def _fmt_fit(f: dict) -> str:
    parts = []
    a = f.get("n_fixed")
    parts.append(f"n = 5/2: C = {a['C']:.3f} +- {a['C_err']:.3f}, k = {a['k']:.2f} +- {a['k_err']:.2f} "
                 f"(rms {a['rms_relative_residual']:.3f})"
                 if a else f"n = 5/2: no fit ({f.get('n_fixed_why')})")  # fmt: skip
    b = f.get("n_free")
    parts.append(f"n free: n = {b['n']:.2f} +- {b['n_err']:.2f}, k = {b['k']:.2f} +- {b['k_err']:.2f}, "
                 f"C = {b['C']:.3g} +- {b['C_err']:.2g} (rms {b['rms_relative_residual']:.3f})"
                 if b else f"n free: no fit ({f.get('n_free_why')})")  # fmt: skip
    return "; ".join(parts)


def report(runs: list, fit: dict) -> None:
    print()
    print(" D/d  seed  L [cm]  grains  fill [s]   phi    H0/D  stop    out   window [s]   W [kg/s]        "
          "W/(rho_b g^.5 d^2.5)")  # fmt: skip
    for r in sorted(runs, key=lambda r: (r["D_m"], r["seed"])):
        fl = r["fill"]
        fill = f"{fl['time_s']:.2f}{'' if fl['settled'] else '*'}"
        head = f"{r['head0_m'] / r['D_m']:.2f}"
        if r.get("rate"):
            rt = r["rate"]
            d25 = (r["D_m"] / r["D_over_d"]) ** 2.5
            w = f"{rt['slope']:.3f} +- {rt['stderr']:.3f}"
            wn = f"{r['W_norm'] / d25:.2f} +- {r['W_norm_err'] / d25:.2f}"
            win = f"{rt['t0']:.2f}-{rt['t1']:.2f}"
        else:
            w, wn, win = "no rate", "", ""
        print(f"{r['D_over_d']:4.0f}  {r['seed']:4d}  {100 * r['bin_width_m']:6.0f}  {r['grains']:6d}  {fill:>8}  "
              f"{r['packing_fraction']:.3f}  {head:>5}  {r['stop']:6}  {r['discharged'][-1]:5d}  {win:>11}  "
              f"{w:>15}  {wn}")  # fmt: skip
    print("  (* fill stopped at the cap, not at rest)")
    for s, f in fit["per_seed"].items():
        print(f"seed {s}: {_fmt_fit(f)}")
    if fit["over_seed_means"]:
        print(f"seed means: {_fmt_fit(fit['over_seed_means'])}")
        print(f"every run:  {_fmt_fit(fit['over_runs'])}")
    print(f"published: C {PUBLISHED['C']}; k {PUBLISHED['k_spheres']}; k {PUBLISHED['k_angular']}")


# ----------------------------------------------------------------------------------------------- main


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--size", choices=sorted(SIZES), default="tiny")
    ap.add_argument("--device", default="cpu")
    ap.add_argument("--orifices", default=None, help="orifice diameters D/d, comma-separated (size's default)")
    ap.add_argument("--seeds", type=int, default=None, help="how many seeds (size's default)")
    ap.add_argument("--first-seed", type=int, default=1)
    ap.add_argument("--width", type=float, default=None, help="bin width in d for every orifice (default: the rule)")
    ap.add_argument("--head", type=float, default=None, help="least head kept while counting, in D")
    ap.add_argument("--extra", type=float, default=None, help="fill above the least head, in d")
    ap.add_argument("--fill-time", type=float, default=None, help="cap on the fill [s]")
    ap.add_argument("--discharge-time", type=float, default=None, help="longest counting [s]")
    ap.add_argument("--sample", type=float, default=None, help="counting interval [s]")
    ap.add_argument("--settle-kinetic", type=float, default=1e-5, help="fill at rest: kinetic over released energy")
    ap.add_argument("--settle-speed", type=float, default=0.05, help="fill at rest: no grain faster [m/s]")
    ap.add_argument("--lo", type=float, default=0.2, help="the rate's window starts at this fraction of the count")
    ap.add_argument("--plate", type=float, default=0.01, help="plate thickness [m]")
    ap.add_argument("--catch", type=float, default=0.3, help="catch floor below the plate [m]")
    ap.add_argument("--segments", type=int, default=48, help="sides of the orifice polygon (multiple of 8)")
    ap.add_argument("--spacing", type=float, default=1.0, help="emitter cell over the bounding diameter")
    ap.add_argument("--precision", default="mixed")
    ap.add_argument("--tag", default=None, help="file name tag (default: the size)")
    ap.add_argument("--out", default=None)
    ap.add_argument("--merge", nargs="+", default=None, metavar="JSON", help="fit the runs of these files together")
    args = ap.parse_args()
    d = 0.01

    if args.merge:
        runs, metas = [], []
        for f in args.merge:
            data = json.loads(Path(f).read_text())
            runs += data["runs"]
            metas.append({"file": str(f), **data["meta"]})
        fit = fits(runs, d)
        report(runs, fit)
        devices = sorted({m["device"].replace(":", "") for m in metas})
        tag = args.tag or "merged"
        path = Path(args.out) if args.out else RESULTS / f"beverloo_{'+'.join(devices)}_{tag}.json"
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_text(json.dumps({"meta": {"merged": metas, "published": PUBLISHED}, "runs": runs,
                                    "fits": fit}, indent=1) + "\n")  # fmt: skip
        print(f"wrote {path}")
        return 0

    import warp as wp

    wp.config.quiet = True
    size = SIZES[args.size]
    p = {k: (getattr(args, k) if getattr(args, k, None) is not None else size[k])
         for k in ("head", "extra", "fill_time", "discharge_time", "sample")}  # fmt: skip
    p.update(d=d, width=args.width, wall_factor=size["wall_factor"], wall_extra=size["wall_extra"],
             settle_kinetic=args.settle_kinetic, settle_speed=args.settle_speed, lo=args.lo, plate=args.plate,
             catch=args.catch, segments=args.segments, spacing=args.spacing, precision=args.precision)  # fmt: skip
    orifices = [float(x) for x in (args.orifices or size["orifices"]).split(",")]
    seeds = list(range(args.first_seed, args.first_seed + (args.seeds or size["seeds"])))
    tag = args.tag or args.size
    dev = args.device.replace(":", "")
    path = Path(args.out) if args.out else RESULTS / f"beverloo_{dev}_{tag}.json"
    path.parent.mkdir(parents=True, exist_ok=True)
    meta = {**vars(args), "params": p, "orifices_d": orifices, "seeds_run": seeds, "warp": wp.__version__,
            "device_name": str(wp.get_device(args.device).name), "published": PUBLISHED}  # fmt: skip
    runs = []
    t_all = time.perf_counter()

    def save(fit):
        # After every run: a call cut short (a time limit) keeps the runs it finished.
        meta["wall_s"] = time.perf_counter() - t_all
        path.write_text(json.dumps({"meta": meta, "runs": runs, "fits": fit}, indent=1) + "\n")

    for seed in seeds:
        for o in orifices:
            r = run_one(o * d, seed, p, args.device)
            runs.append(r)
            save(None)
            rt = r["rate"]
            msg = (f"W = {rt['slope']:.4f} +- {rt['stderr']:.4f} kg/s over {rt['t0']:.2f}-{rt['t1']:.2f} s"
                   if rt else f"no rate ({r['why_no_rate']})")  # fmt: skip
            print(f"D = {o:g} d, seed {seed}: bin {100 * r['bin_width_m']:.0f} cm, {r['grains']} grains, fill "
                  f"{r['fill']['time_s']:.2f} s ({'at rest' if r['fill']['settled'] else 'cap'}), phi "
                  f"{r['packing_fraction']:.3f}, head {100 * r['head0_m']:.1f} cm, {r['discharged'][-1]} out "
                  f"(stop: {r['stop']}), {msg}; {r['steps']} steps, build {r['build_s']:.1f} s, fill "
                  f"{r['fill_s']:.1f} s, discharge {r['discharge_s']:.1f} s "
                  f"({1e3 * (r['fill_s'] + r['discharge_s']) / r['steps']:.2f} ms/step)", flush=True)  # fmt: skip
    fit = fits(runs, d)
    report(runs, fit)
    save(fit)
    print(f"wrote {path} ({meta['wall_s']:.0f} s)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
