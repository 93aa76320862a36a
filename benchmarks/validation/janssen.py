"""Janssen's saturation of the pressure in a silo with wall friction (VALIDATION.md, section 1).

A square silo of inner width W is filled with cubes poured at rest from above and left to settle. In
Janssen's model (1895) the vertical stress at a depth h below the free surface of a column whose walls
carry weight by friction is

    sigma_zz(h) = rho_b g lambda (1 - exp(-h / lambda)),   lambda = (A / P) / (mu_w K) = W / (4 mu_w K),

rho_b the bulk density, mu_w the grain-wall friction coefficient and K the ratio of the horizontal to the
vertical stress. The run measures sigma_zz(h) (Love-Weber, horizontal slabs over the whole cross-section,
wall contacts included) and rho_b (the exact packing fraction of the same slabs), fits lambda (one
parameter: rho_b is measured), and reports K = W / (4 mu_w lambda) beside Jaky's K0 = 1 - sin(phi) for
the internal friction angle phi = atan(mu) and Rankine's active K_a = (1 - sin phi) / (1 + sin phi),
the usual bounds. The floor's load is also reported as the apparent mass M_app = F_floor / g against the
mass of the grains (Janssen's own measurement): the walls carry the rest.

Material parameters are set, not fitted: mu = 0.5 between grains, mu_w = 0.3 with the walls, e = 0.3,
glass-like density 2500 kg/m^3 and the Hertz-type law at the stiffness the scene's default rule gives.

    python benchmarks/validation/janssen.py --size small            # CPU, about 300 grains (CI)
    python benchmarks/validation/janssen.py --device cuda:0 --size full   # W = 10 d, H ~ 60 d
"""

from __future__ import annotations

import argparse
import json
import math
import sys
import time
import warnings
from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve().parent
RESULTS = HERE.parent / "results" / "validation"

SIZES = {  # the silo's width in grain sizes, and the grains to pour ("tiny": the CI's check of the machinery)
    "tiny": {"width": 4, "grains": 60},
    "small": {"width": 6, "grains": 300},
    "medium": {"width": 8, "grains": 1200},
    "full": {"width": 12, "grains": 5000},
}


def build(width_d: int, grains: int, *, d: float, mu: float, mu_w: float, k: float, seed: int, precision: str,
          lower: float = 0.0, lower_at: float = 0.0, lower_speed: float = 0.01, previous=None,
          bottom: float | None = None):  # fmt: skip
    """The silo with ``grains`` cubes to pour; ``previous``: (positions, orientations) of grains already at rest
    in it (a staged fill), the new ones poured from ``bottom`` [m] up (default 0.6 d above the floor)."""
    import polydem

    # The pour region: the silo's section, a grid of cells 1.1 bounding diameters wide (the emitter's), as
    # many layers as the grains need; they fall from rest and settle in the bottom of the silo.
    w = width_d * d
    margin = 0.02 * d
    cell = 1.1 * math.sqrt(3.0) * d
    across = int((w - 2.0 * margin) // cell)
    layers = math.ceil(grains / across**2)
    bottom = 0.6 * d if bottom is None else bottom
    fill = bottom + 1.02 * layers * cell
    sc = polydem.Scene(gravity=(0.0, 0.0, -9.81), dt="auto", name="janssen", precision=precision)
    sc.add_material("grain", density=2500.0, k=k, restitution=0.3, friction=mu, law="hertz")
    sc.add_material("wall", density=2500.0, k=k, restitution=0.3, friction=mu_w, law="hertz")
    sc.add_shape("cube", polydem.ConvexShape.box(d))
    if lower > 0.0:
        # Side walls as four planes and the floor a slab that moves down by ``lower`` [m] at ``lower_speed``
        # from ``lower_at`` [s] (a ramp motion): the grains follow it and slide down the walls, so that the
        # wall friction turns upwards, as in experiments that lower the floor after a gentle fill.
        for n in ((1, 0, 0), (-1, 0, 0), (0, 1, 0), (0, -1, 0)):
            sc.add_plane(point=tuple(-0.5 * w * c for c in n), normal=n, material="wall")
        sc.add_motion("lower", kind="ramp", speed=lower_speed, distance=lower, start=lower_at, axis=(0.0, 0.0, -1.0))
        sc.add_shape("floor", polydem.ConvexShape.box(w + 2.0 * d, w + 2.0 * d, d))
        sc.add_body("floor", "wall", position=(0.0, 0.0, -0.5 * d), kind="kinematic", motion="lower")
    else:
        sc.add_box_container((0.0, 0.0, 0.5 * (fill + d)), (w, w, fill + d), "wall")
    for position, orientation in zip(*(previous or ((), ())), strict=True):
        sc.add_body("cube", "grain", position=tuple(position), orientation=tuple(orientation))
    lo = (-0.5 * w + margin, -0.5 * w + margin, bottom)
    hi = (0.5 * w - margin, 0.5 * w - margin, fill)
    sc.emit("cube", "grain", grains, (lo, hi), seed=seed)
    return sc


def staged_fill(args, size, d: float, lower: float):
    """A gentler fill than one pour of every grain: ``--stages`` batches, each poured from just above the pile
    the batches before it left at rest (as the grains of a silo filled slowly rain onto the pile), the last one
    in the scene whose floor is then lowered. Between batches the grains start again from rest at the poses
    they settled in (velocities and friction springs are not carried over). Returns the last batch's scene and
    simulation, at t = 0 of that batch."""
    from polydem import Simulation
    from polydem.scene.errors import SceneWarning
    from polydem.settle import SettleCriterion

    counts = [len(c) for c in np.array_split(np.arange(size["grains"]), args.stages)]
    previous, bottom = None, None
    common = dict(d=d, mu=args.mu, mu_w=args.mu_w, k=args.k, precision=args.precision, lower=lower)
    for stage, n in enumerate(counts):
        last = stage == len(counts) - 1
        # The floor's motion starts at the last batch's fill time; before that it must not move.
        sc = build(size["width"], n, seed=args.seed + stage, lower_at=args.fill_time if last else 1e9,
                   previous=previous, bottom=bottom, **common)  # fmt: skip
        with warnings.catch_warnings():
            # The grains at rest overlap at their corners as the stiffness sets (up to about a tenth of the edge
            # at k = 1e9): the check of initial overlaps would call each of them out.
            warnings.filterwarnings("ignore", message=r".*initial overlaps", category=SceneWarning)
            sim = Simulation(sc, device=args.device)
        if last:
            return sc, sim
        done = sim.run_until_settled(args.fill_time, SettleCriterion())
        state = sim.state()
        free = np.asarray(sc.body_kind) == 0
        pos, quat = state["body_position"][free], state["body_orientation"][free]
        previous = (pos, quat)
        bottom = float(pos[:, 2].max()) + 1.0 * d  # above the highest centre by a bounding radius and more
        print(f"  stage {stage + 1}/{len(counts)}: {int(free.sum())} grains, at rest {done.settled} at "
              f"t = {done.time:.3f} s, top centre {bottom - d:.4f} m", flush=True)  # fmt: skip
    raise AssertionError("unreachable")


def janssen_fit(depth, sigma, rho_g):
    """lambda [m] of sigma = rho_g lambda (1 - exp(-h / lambda)) by least squares (a scan, then a refinement),
    and the residual's rms [Pa]."""

    def rms(lam):
        return float(np.sqrt(np.mean((rho_g * lam * (1.0 - np.exp(-depth / lam)) - sigma) ** 2)))

    grid = np.geomspace(1e-3 * depth.max() + 1e-12, 1e3 * depth.max(), 2001)
    best = grid[int(np.argmin([rms(x) for x in grid]))]
    fine = np.geomspace(best / 1.01, best * 1.01, 2001)
    best = fine[int(np.argmin([rms(x) for x in fine]))]
    return float(best), rms(best)


def run(args) -> dict:
    import warp as wp

    wp.config.quiet = True
    from polydem import Simulation
    from polydem.settle import SettleCriterion

    size = SIZES[args.size]
    d = args.grain
    lower = args.lower * d
    if args.stages > 1:
        sc, sim = staged_fill(args, size, d, lower)
    else:
        sc = build(size["width"], size["grains"], d=d, mu=args.mu, mu_w=args.mu_w, k=args.k, seed=args.seed,
                   precision=args.precision, lower=lower, lower_at=args.fill_time)  # fmt: skip
        sim = Simulation(sc, device=args.device)
    t0 = time.perf_counter()
    if lower > 0.0:
        sim.step(max(1, math.ceil(args.fill_time / sim.dt)))
        filled = measure(sim, sc, args, size, d, floor=0.0)
        sim.step(max(1, math.ceil((lower / 0.01 + 0.02) / sim.dt)))  # the ramp, then a little more
    settled = sim.run_until_settled(args.max_time, SettleCriterion())
    wall = time.perf_counter() - t0
    out = measure(sim, sc, args, size, d, floor=-lower)
    out.update(settled=bool(settled.settled), settle_time=settled.time, wall_s=wall, lowered=lower, stages=args.stages)
    if lower > 0.0:
        out["before_lowering"] = {k: filled[k] for k in ("floor_apparent_mass", "side_walls_apparent_mass",
                                                         "packing_fraction", "lambda", "K_fit")}  # fmt: skip
    if args.checkpoint:
        from polydem.checkpoint import save_checkpoint

        save_checkpoint(sim, args.checkpoint)
    return out


def measure(sim, sc, args, size, d, floor: float) -> dict:
    """The silo's profiles, Janssen fit and wall loads of the state now; ``floor``: the floor's top [m]."""
    from polydem import measures

    g = measures.Grains.from_simulation(sim)
    contacts = sim.contacts()
    free = g.free
    pos = g.position[free]
    top = float(np.percentile(pos[:, 2], 95.0))  # the free surface: the top 5% are a loose layer
    w = size["width"] * d
    section = measures.Box((-0.5 * w, -0.5 * w, floor), (0.5 * w, 0.5 * w, top))
    bin_width = 2.0 * d
    packing = measures.packing_profile(g, axis=2, bin_width=bin_width, box=section)
    stress = measures.stress_profile(g, axis=2, bin_width=bin_width, box=section, contacts=contacts)
    sigma_zz = stress.stress[:, 2, 2]
    depth = top - stress.centres
    rho_s = 2500.0
    # The bulk density of the column below its top layer (the top slab is partly empty).
    inner = depth > bin_width
    phi = float(np.sum(packing.solid_volume[inner]) / np.sum(packing.slab_volume[inner]))
    rho_g = phi * rho_s * 9.81
    lam, res = janssen_fit(depth[inner], sigma_zz[inner], rho_g)
    k_fit = w / (4.0 * args.mu_w * lam)
    phi_int = math.atan(args.mu)
    k_jaky = 1.0 - math.sin(phi_int)
    k_rankine = (1.0 - math.sin(phi_int)) / (1.0 + math.sin(phi_int))

    # The floor's load: the normal force of the contacts with the floor slab (the first non-free body).
    kinds = np.asarray(sc.body_kind)
    floor_body = int(np.flatnonzero(kinds != 0)[0])
    a, b = contacts["body_a"], contacts["body_b"]
    on_floor = (a == floor_body) | (b == floor_body)
    on_a = -contacts["normal_force"][:, None] * contacts["normal"] + contacts["tangential_force"]
    sign = np.where(a[on_floor] == floor_body, -1.0, 1.0)  # the grain is B where the floor is A
    f_floor = float(np.sum(sign * on_a[on_floor, 2]))  # the floor's upward push on the grains
    mass = float(np.sum(g.volumes()[free]) * rho_s)
    height = top - floor
    m_janssen = phi * rho_s * w * w * lam * (1.0 - math.exp(-height / lam))
    # The force balance of the free grains: the floor, the side walls and gravity (at rest: sum 0).
    grain_of = np.where(a < 0, a, np.where(np.isin(a, np.flatnonzero(kinds != 0)), b, a))
    walls_z = 0.0
    for row in range(len(a)):
        if row in np.flatnonzero(on_floor):
            continue
        other = b[row] if grain_of[row] == a[row] else a[row]
        if other < 0 or kinds[other] != 0:
            walls_z += on_a[row, 2] if grain_of[row] == a[row] else -on_a[row, 2]
    out = {
        "size": args.size,
        "grains": int(free.sum()),
        "grain": d,
        "width": w,
        "fill_height": height,
        "mu": args.mu,
        "mu_w": args.mu_w,
        "k": sim.model.material_k.numpy().tolist() if hasattr(sim.model, "material_k") else args.k,
        "packing_fraction": phi,
        "depth": depth.tolist(),
        "sigma_zz": sigma_zz.tolist(),
        "sigma_xx_yy": (0.5 * (stress.stress[:, 0, 0] + stress.stress[:, 1, 1])).tolist(),
        "hydrostatic_sigma_zz": (rho_g * depth).tolist(),
        "lambda": lam,
        "fit_rms": res,
        "K_fit": k_fit,
        "K_ratio_measured": float(
            np.median(0.5 * (stress.stress[inner, 0, 0] + stress.stress[inner, 1, 1]) / sigma_zz[inner])
        ),  # fmt: skip
        "K_jaky": k_jaky,
        "K_rankine_active": k_rankine,
        "floor_apparent_mass": f_floor / 9.81,
        "side_walls_apparent_mass": walls_z / 9.81,
        "grain_mass": mass,
        "janssen_apparent_mass": m_janssen,
    }
    return out


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--device", default="cpu")
    ap.add_argument("--size", default="small", choices=sorted(SIZES))
    ap.add_argument("--grain", type=float, default=0.01, help="cube edge d [m]")
    ap.add_argument("--mu", type=float, default=0.5, help="friction between grains")
    ap.add_argument("--mu-w", type=float, default=0.3, help="friction between grains and walls")
    ap.add_argument("--k", type=float, default=1e9, help="Hertz-type stiffness [J/m^4.5]")
    ap.add_argument("--precision", default="mixed", choices=("float32", "mixed", "float64"))
    ap.add_argument("--max-time", type=float, default=4.0, help="simulated seconds at most")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--lower", type=float, default=0.2, help="lower the floor by this many d after the fill (0: not)")
    ap.add_argument("--fill-time", type=float, default=1.5, help="when the floor is lowered [s]")
    ap.add_argument("--stages", type=int, default=1, help="fill in this many batches, each let come to rest")
    ap.add_argument("--out", default=None)
    ap.add_argument("--checkpoint", default=None, help="save the settled state here (.npz)")
    args = ap.parse_args()
    out = run(args)
    print(
        f"{out['grains']} cubes of {out['grain']:g} m in a silo {out['width']:.3g} m wide, filled to "
        f"{out['fill_height']:.3g} m; settled {out['settled']} at {out['settle_time']:.3f} s ({out['wall_s']:.1f} s)"
    )
    print(
        f"  packing fraction {out['packing_fraction']:.3f}; Janssen length {out['lambda']:.4g} m "
        f"(fit rms {out['fit_rms']:.3g} Pa)"
    )
    print(
        f"  K fitted {out['K_fit']:.3f}; sigma_h / sigma_v measured {out['K_ratio_measured']:.3f}; Jaky "
        f"{out['K_jaky']:.3f}, Rankine active {out['K_rankine_active']:.3f}"
    )
    if "before_lowering" in out:
        b = out["before_lowering"]
        print(f"  before the floor was lowered {out['lowered'] * 1e3:.2g} mm: floor {b['floor_apparent_mass']:.4g} kg, "
              f"side walls {b['side_walls_apparent_mass']:.4g} kg")  # fmt: skip
    print(f"  side walls carry {out['side_walls_apparent_mass']:.4g} kg")
    print(
        f"  floor carries {out['floor_apparent_mass']:.4g} kg of {out['grain_mass']:.4g} kg "
        f"(Janssen with the fitted length: {out['janssen_apparent_mass']:.4g} kg)"
    )
    path = Path(args.out) if args.out else RESULTS / f"janssen_{args.size}_{args.device.replace(':', '')}.json"
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps(out, indent=1) + "\n")
    print(f"wrote {path}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
