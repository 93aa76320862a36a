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


def write_measure_plots(grains, contacts, box, summary: dict, out_dir, *, up=(0.0, 0.0, 1.0)):
    """Write ``measures.png`` into ``out_dir``: the settled pile's measures (:mod:`polydem.measures`) in four
    panels: the distribution of normal contact forces P(f / <f>) with the exponential e^-x beside it, the
    contact normals' rose in a vertical plane, the exact packing fraction in slabs up the pile (across the
    measuring ``box``'s horizontal extent), and the contacts in ``box`` by type.

    ``grains``: a :class:`polydem.measures.Grains`; ``contacts``: a dict as ``Simulation.contacts()``;
    ``box``: the :class:`polydem.measures.Box` measured; ``summary``: :func:`polydem.measures.summary` of it
    (its contact counts by features); ``up``: the vertical unit vector along a coordinate axis. Returns the
    paths written, or a string that says why none were.
    """
    try:
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt
    except ImportError:
        return 'no measure plots: matplotlib is not installed (pip install "polydem[plot]")'
    import numpy as np

    from polydem import measures

    vertical = int(np.argmax(np.abs(np.asarray(up, dtype=np.float64))))
    horizontal = (vertical + 1) % 3
    in_box = box.contains(np.asarray(contacts["point"], dtype=np.float64))
    pairs = in_box & (np.asarray(contacts["body_b"]) >= 0)
    if not pairs.any():
        return "no measure plots: no pair contact in the settled region"
    forces = measures.force_distribution(contacts, select=in_box, bins=20)
    rose = measures.normal_rose(contacts, plane=(horizontal, vertical), select=in_box, bins=36)
    # The profile across the pile's whole height, within the box's horizontal extent.
    around = measures.Box.around(grains)
    lower, upper = box.lower.copy(), box.upper.copy()
    lower[vertical], upper[vertical] = around.lower[vertical], around.upper[vertical]
    profile = measures.packing_profile(grains, vertical, 0.5 * grains.grain_size(), measures.Box(lower, upper))

    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    fig = plt.figure(figsize=(10, 8), dpi=100)
    ax = fig.add_subplot(2, 2, 1)
    centres = 0.5 * (forces.edges[1:] + forces.edges[:-1])
    shown = forces.density > 0.0
    ax.semilogy(centres[shown], forces.density[shown], "o-", label=f"{forces.count} contacts")
    x = np.linspace(0.0, forces.edges[-1], 100)
    ax.semilogy(x, np.exp(-x), "k:", label="exp(-x)")
    ax.set_xlabel("normal force / mean normal force")
    ax.set_ylabel("probability density")
    ax.set_title(f"P(f/<f>), <f> = {forces.mean:.3g} N")
    ax.legend(fontsize="small")
    ax.grid(alpha=0.3)
    ax = fig.add_subplot(2, 2, 2, projection="polar")
    ax.bar(0.5 * (rose.edges[1:] + rose.edges[:-1]), rose.fraction, width=np.diff(rose.edges), alpha=0.7)
    names = "xyz"
    ax.set_title(f"contact normals in the {names[horizontal]}-{names[vertical]} plane ({rose.count} contacts)")
    ax = fig.add_subplot(2, 2, 3)
    ax.plot(profile.fraction, profile.centres, "-")
    ax.axhspan(box.lower[vertical], box.upper[vertical], color="tab:green", alpha=0.1, label="measured box")
    ax.set_xlabel("packing fraction (exact, in slabs of half a grain)")
    ax.set_ylabel(f"{names[vertical]} [m]")
    ax.set_xlim(0.0, 1.0)
    ax.legend(fontsize="small")
    ax.grid(alpha=0.3)
    ax = fig.add_subplot(2, 2, 4)
    counts = summary.get("contact_features") or {}
    labels = [*measures.KINDS, "unclassified"]
    ax.bar(range(len(labels)), [counts.get(k, 0) for k in labels], color="tab:orange")
    ax.set_xticks(range(len(labels)), labels, rotation=20, fontsize="small")
    ax.set_ylabel("contacts in the box")
    coord = summary.get("coordination") or {}
    z = coord.get("z")
    ax.set_title("contacts by type" + (f" (coordination {z:.2f} without rattlers)" if z is not None else ""))
    fig.tight_layout()
    try:
        _save(fig, out / "measures.png")
    finally:
        plt.close(fig)
    return [out / "measures.png"]
