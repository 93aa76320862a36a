"""The figures of VALIDATION.md, drawn from the result files in benchmarks/results/validation/ (needs the ``plot``
extra: matplotlib). Each figure shows ours beside the published value it is compared with.

    python benchmarks/validation/plots.py            # writes benchmarks/results/validation/plots/*.png
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np

RESULTS = Path(__file__).resolve().parents[1] / "results" / "validation"


def load(name: str) -> dict:
    return json.loads((RESULTS / name).read_text())


def taps(plt, out: Path) -> Path:
    """Packing fraction, coordination and cubic order against the number of taps; the paper's densest random
    packings as bands."""
    fig, (ax, az, aq) = plt.subplots(1, 3, figsize=(13, 4))
    runs = [("tapping_5000_66taps_h100.json", "cubes, seed 1 (first round)", "C0", ":"),
            ("tapping_cube_5000_s1_75taps_h200.json", "cubes, seed 1", "C0", "-"),
            ("tapping_cube_5000_s2_76taps_h200.json", "cubes, seed 2", "C1", "-"),
            ("tapping_tetrahedron_8000_s1_33taps_h200.json", "tetrahedra, seed 1", "C2", "-")]  # fmt: skip
    for name, label, colour, style in runs:
        rec = load(name)["records"]
        n = [r["tap"] for r in rec]
        ax.plot(n, [r["packing_fraction"] for r in rec], style, color=colour, label=label)
        if "coordination" in rec[-1]:
            az.plot(n, [r.get("coordination", np.nan) for r in rec], style, color=colour, label=label)
        if "cubic_order" in rec[-1]:
            aq.plot(n, [r.get("cubic_order", np.nan) for r in rec], style, color=colour, label=f"{label}, box frame")
    for sel, colour in (("s1_t", "C0"), ("s2_t", "C1")):  # the best-frame order from the checkpoints
        rows = [r for r in load("tap_order_cpu.json")["rows"] if f"cube_{sel}" in r["checkpoint"]]
        taps = []
        for r in rows:  # the tap a checkpoint was taken before, from its run's schedule
            run = json.loads((RESULTS / "taps" / Path(r["checkpoint"]).with_suffix(".json").name).read_text())["args"]
            taps.append(round((r["time"] - run["start"]) / run["period"]))
        aq.plot(taps, [r["cubic_order_best"] for r in rows], "o", color=colour, label=f"best frame ({sel[:2]})")
    for value, err, text, colour in ((0.67, 0.01, "cubes, densest (Baker and Kudrolli)", "C0"),
                                     (0.64, 0.0, "tetrahedra, densest", "C2")):  # fmt: skip
        if err:
            ax.axhspan(value - err, value + err, color=colour, alpha=0.15)
        else:
            ax.axhline(value, color=colour, lw=0.8)
        ax.text(1, value + 0.002, text, color=colour, fontsize=8)
    ax.set(xlabel="taps (Gamma = 3)", ylabel="packing fraction", title="Tapped packings")
    az.set(xlabel="taps", ylabel="coordination (walls counted, no rattlers)", title="Coordination")
    aq.axhline(0.012, color="grey", lw=0.8, ls="--")
    aq.text(1, 0.02, "best frame, grains at random", color="grey", fontsize=8)
    aq.set(xlabel="taps", ylabel="cubic order", title="Cubic order (1 aligned, 0 random)")
    for a in (ax, az, aq):
        a.legend(fontsize=7)
    return save(plt, fig, out / "taps.png")


def anneal(plt, out: Path) -> Path:
    fig, ax = plt.subplots(figsize=(5, 4))
    rows = load("anneal_5000_mu0-0.5_h100.json")["rows"] + load("anneal_5000_mu1_h100.json")["rows"]
    rows.sort(key=lambda r: r["mu_fill"])
    mu = [r["mu_fill"] for r in rows]
    ax.plot(mu, [r["fill"]["packing_fraction"] for r in rows], "o-", label="filled at mu_fill")
    ax.plot(mu, [r["final"]["packing_fraction"] for r in rows], "s--", label="after mu = 0.5 is restored")
    ax.axhspan(0.53, 0.55, color="C3", alpha=0.2, label="cubes, loosest (Baker and Kudrolli)")
    ax.axhspan(0.66, 0.68, color="C0", alpha=0.2, label="cubes, densest random")
    ax.set(xlabel="fill friction mu_fill", ylabel="packing fraction", title="Friction annealing, 5000 cubes")
    ax.legend(fontsize=7)
    return save(plt, fig, out / "anneal.png")


def janssen(plt, out: Path) -> Path:
    """Vertical stress against depth: the one-pour fill, the fills in batches, hydrostatic and Janssen's curve
    with the length from the saturated stress."""
    fig, axes = plt.subplots(1, 2, figsize=(11, 4.5))
    cases = [(axes[0], "janssen_small_staged3_cpu.json", "small silo (6 d), 3 batches", None),
             (axes[1], "janssen_full_staged4_lower0.2_h100.json", "full silo (12 d), 4 batches",
              "janssen_full_lower0.2_h100.json")]  # fmt: skip
    for ax, name, title, single in cases:
        r = load(name)
        depth = np.asarray(r["depth"])
        order = np.argsort(depth)
        ax.plot(np.asarray(r["sigma_zz"])[order] / 1e3, depth[order] * 100, "o-", label="sigma_zz, fill in batches")
        ax.plot(np.asarray(r["hydrostatic_sigma_zz"])[order] / 1e3, depth[order] * 100, "k:", label="hydrostatic")
        rho_g = r["packing_fraction"] * r["grain_mass"] / (r["grains"] * r["grain"] ** 3) * 9.81
        h = np.linspace(0.0, depth.max(), 100)
        lam = r["lambda"]
        ax.plot(rho_g * lam * (1 - np.exp(-h / lam)) / 1e3, h * 100, "C1-", label=f"Janssen, fitted lambda {lam:.3f} m")
        k0 = r["K_jaky"]
        lam0 = r["width"] / (4.0 * r["mu_w"] * k0)
        ax.plot(rho_g * lam0 * (1 - np.exp(-h / lam0)) / 1e3, h * 100, "C2--",
                label=f"Janssen with Jaky's K0 = {k0:.3f} (lambda {lam0:.3f} m)")  # fmt: skip
        if single:
            s = load(single)
            d1 = np.asarray(s["depth"])
            o1 = np.argsort(d1)
            ax.plot(np.asarray(s["sigma_zz"])[o1] / 1e3, d1[o1] * 100, "x-", color="C3", alpha=0.6,
                    label="sigma_zz, one pour")  # fmt: skip
        ax.invert_yaxis()
        ax.set(xlabel="vertical stress [kPa]", ylabel="depth below the surface [cm]",
               title=f"{title}, floor lowered {r['lowered'] * 1e3:.0f} mm")  # fmt: skip
        ax.legend(fontsize=7)
    return save(plt, fig, out / "janssen.png")


def beverloo(plt, out: Path) -> Path:
    data = load("beverloo_cuda0_full_h100.json")
    fig, ax = plt.subplots(figsize=(6, 4.5))
    d = None
    for seed, marker in ((1, "o"), (2, "s"), (3, "^")):
        runs = [r for r in data["runs"] if r["seed"] == seed and r.get("W_norm") is not None]
        if not runs:
            continue
        d = runs[0]["D_m"] / runs[0]["D_over_d"]
        x = [r["D_over_d"] for r in runs]
        y = [r["W_norm"] / d**2.5 for r in runs]
        e = [r["W_norm_err"] / d**2.5 for r in runs]
        ax.errorbar(x, y, yerr=e, fmt=marker, label=f"seed {seed}")
    jammed = [r["D_over_d"] for r in data["runs"] if r.get("rate") is None]
    ax.plot(jammed, [0.5] * len(jammed), "kx", label="jammed")
    fit = data["fits"]["over_runs"]["n_fixed"]
    x = np.linspace(fit["k"] + 0.05, 13, 200)
    label = f"fit, n = 5/2: C = {fit['C']:.2f} +- {fit['C_err']:.2f}, k = {fit['k']:.2f} +- {fit['k_err']:.2f}"
    ax.plot(x, fit["C"] * (x - fit["k"]) ** 2.5, "C0-", label=label)
    x = np.linspace(2.95, 13, 200)
    ax.fill_between(x, 0.55 * (x - 2.9) ** 2.5, 0.65 * (x - 2.9) ** 2.5, color="C3", alpha=0.2,
                    label="published: C 0.55-0.65, k 2.9 (angular)")  # fmt: skip
    ax.set(xlabel="orifice D / d", ylabel="W / (rho_b g^0.5 d^2.5)", title="Beverloo's law, cubes (H100)")
    ax.legend(fontsize=7)
    return save(plt, fig, out / "beverloo.png")


def save(plt, fig, path: Path) -> Path:
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", default=str(RESULTS / "plots"), help="folder for the figures")
    args = ap.parse_args(argv)
    try:
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt
    except ImportError:
        raise SystemExit("the figures need matplotlib: pip install 'polydem[plot]'") from None
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    for draw in (taps, anneal, janssen, beverloo):
        print("wrote", draw(plt, out))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
