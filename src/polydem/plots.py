"""Plots of a run (energy against time, packing fraction and contacts against time).

Matplotlib is an optional dependency (``pip install "polydem[plot]"``): it is imported here, when a
plot is asked for, and :func:`write_plots` says so instead of failing when it is missing.
"""

import os
from pathlib import Path


def _save(fig, path: Path) -> None:
    """Save ``fig`` as a PNG through a temporary file: a failed write leaves no partial picture."""
    tmp = path.with_name(path.name + ".tmp")
    try:
        fig.savefig(tmp, format="png")
        os.replace(tmp, path)
    except BaseException:
        try:
            tmp.unlink(missing_ok=True)
        except OSError:
            pass
        raise


def write_plots(history, out_dir):
    """Write ``energy.png`` and ``packing.png`` into ``out_dir`` from a run's frame history.

    ``history`` maps names to equal-length lists: ``time`` [s], ``kinetic``, ``contact``,
    ``gravity``, ``dissipated``, ``total`` [J], ``contacts`` and ``packing_fraction``.
    Returns the paths written, or a string that says why none were.
    """
    try:
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt
    except ImportError:
        return 'no plots: matplotlib is not installed (pip install "polydem[plot]")'
    t = history.get("time", [])
    if len(t) < 2:
        return "no plots: fewer than two frames were recorded"
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    paths = []
    fig, ax = plt.subplots(figsize=(7, 4.5), dpi=110)
    for key, style in (("kinetic", "-"), ("contact", "-"), ("gravity", "-"), ("dissipated", "--"), ("total", "k:")):
        ax.plot(t, history[key], style, label=key)
    ax.set_xlabel("simulated time [s]")
    ax.set_ylabel("energy [J]")
    ax.set_title("energy balance (total = kinetic + contact + gravity + dissipated)")
    ax.legend(loc="best", fontsize="small")
    ax.grid(alpha=0.3)
    fig.tight_layout()
    try:
        _save(fig, out / "energy.png")
    finally:
        plt.close(fig)
    paths.append(out / "energy.png")
    fig, ax = plt.subplots(figsize=(7, 4.5), dpi=110)
    phi = [float("nan") if p is None else p for p in history["packing_fraction"]]
    ax.plot(t, phi, "-", color="tab:blue", label="packing fraction (settled region)")
    ax.set_xlabel("simulated time [s]")
    ax.set_ylabel("packing fraction")
    ax.grid(alpha=0.3)
    ax2 = ax.twinx()
    ax2.plot(t, history["contacts"], "-", color="tab:orange", label="contacts")
    ax2.set_ylabel("contacts")
    fig.legend(loc="upper left", fontsize="small")
    fig.tight_layout()
    try:
        _save(fig, out / "packing.png")
    finally:
        plt.close(fig)
    paths.append(out / "packing.png")
    return paths
