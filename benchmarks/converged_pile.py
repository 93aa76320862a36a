"""Time to a converged pile: the same pour at several contact stiffnesses and steps, each run to settled, and
the fastest setting whose pile is the converged one.

A pile's packing fraction phi and coordination number Z depend on the contact stiffness k and the step dt until both
are refined far enough; the user's job is the pile of the refined limit. Here the pour of time_to_settle.py
(settle.py's cubes in columns in an open box, hertz or ``--law power --exponent m``, e = 0.5, mu = 0.5, k from
``--k-rule``) runs to settled at each setting ``KxS`` of ``--settings`` (k = K x the rule's k, dt = S x the
recommended step of that k, which falls as 1/k where the resting rule of ``Scene.time_step`` sets it, while the stable
limit falls as k^-1/2) and each seed of ``--seeds``. Per size, the reference is the most refined setting (the largest
k, then the smallest dt; the seeds' mean); a setting is converged where its mean phi and Z lie within ``--phi-tol``
(0.005) and ``--z-tol`` (0.1) of the reference's; the time to the converged pile is the wall time of the fastest
converged setting (its seeds' mean), given only where the reference has stopped moving in both k and dt: the next
smaller step at its k and the most refined setting of the next smaller k both within the tolerances of it (a pile at k
x 64 stopped moving in dt and still moved with k: section 25).

``--newton FILE[,FILE]`` (``peers/newton_pour.py --dt-sweep`` results of the same pour, ``pour_scene.py
export``) applies the same rule to Newton's rows, its smallest dt the reference, and prints the ratio of the
times to the converged piles, only where both references have stopped moving (Newton's: in dt). ``--analyse
FILE[,FILE]`` reads runs of this script (their runs together) instead of running.

    python benchmarks/converged_pile.py --device cpu --sizes 200 --settings 1x4,4x4 --max-time 1.5
    python benchmarks/converged_pile.py --device cuda:0 --sizes 1e5 --settings 1x4,4x4,16x4,1x1
    python benchmarks/converged_pile.py --analyse results/conv_1e5.json --newton results/newton_1e5.json

Results: a table on stdout and JSON (``--out``), rewritten after every run; the settle criterion is the
simulator's unless ``--speed-fraction off`` (the kinetic part alone, BENCHMARKS.md section 7's rule, the one
newton_pour.py applies by default).
"""

import argparse
import json
import os
import sys
from collections import defaultdict

import numpy as np

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))

PHI_TOL = 0.005
Z_TOL = 0.1


def parse_settings(text):
    """``"1x4,4x4"`` -> [(1.0, 4.0), (4.0, 4.0)]: (k factor, dt scale) pairs."""
    out = []
    for item in text.split(","):
        k, _, s = item.strip().partition("x")
        try:
            out.append((float(k), float(s)))
        except ValueError:
            sys.exit(f"converged_pile.py: a setting is KxS (k factor x dt scale, e.g. 4x2), got {item!r}")
    return out


def summarise(rows, refined_key):
    """Rows of one size grouped by setting: per setting the seeds' mean phi, Z, wall and settle time, sorted from
    the least to the most refined (``refined_key`` of a row gives the order; the last is the reference)."""
    groups = defaultdict(list)
    for r in rows:
        groups[r["setting"]].append(r)
    table = []
    for setting, rs in groups.items():
        phi = [r["packing_fraction"] for r in rs if r.get("packing_fraction") is not None]
        z = [r["coordination_number"] for r in rs if r.get("coordination_number") is not None]
        table.append({
            "setting": setting,
            "order": refined_key(rs[0]),
            "k_factor": rs[0].get("k_factor"),
            "runs": len(rs),
            "settled": all(r["settled"] for r in rs),
            "phi": float(np.mean(phi)) if phi else None,
            "phi_spread": float(np.ptp(phi)) if len(phi) > 1 else None,
            "z": float(np.mean(z)) if z else None,
            "z_spread": float(np.ptp(z)) if len(z) > 1 else None,
            "wall_s": float(np.mean([r["wall_s"] for r in rs])),
            "settle_time_s": float(np.mean([r["settle_time_s"] or np.nan for r in rs])),
        })  # fmt: skip
    table.sort(key=lambda t: t["order"])
    return table


def judge(table, phi_tol, z_tol, by_k=False):
    """Marks each setting converged or not against the most refined one; returns (table, fastest converged
    setting or None, whether the reference has stopped moving, the checks: (what was refined, the setting it was
    refined from, its phi and Z minus the reference's, or None where no such setting ran)).

    The reference has stopped moving where the next most refined setting lies within the tolerances of it; with
    ``by_k`` (settings of k and dt) in both: the next smaller step at the reference's k (dt) and the most refined
    setting of the next smaller k (k). A pile that stops moving in dt at one k may still move with k (the volume
    law's corners: BENCHMARKS.md section 25)."""

    def near(a, b):
        if None in (a["phi"], b["phi"], a["z"], b["z"]):
            return False
        return abs(a["phi"] - b["phi"]) <= phi_tol and abs(a["z"] - b["z"]) <= z_tol

    def check(name, other):
        if other is None or None in (other["phi"], ref["phi"], other["z"], ref["z"]):
            return (name, None if other is None else other["setting"], None, None, False)
        return (name, other["setting"], ref["phi"] - other["phi"], ref["z"] - other["z"], near(other, ref))

    ref = table[-1]
    for t in table:
        t["converged"] = bool(t["settled"] and ref["settled"] and near(t, ref))
    if by_k:
        same_k = [t for t in table[:-1] if t["k_factor"] == ref["k_factor"]]
        softer = [t for t in table if t["k_factor"] < ref["k_factor"]]
        checks = [check("dt", same_k[-1] if same_k else None), check("k", softer[-1] if softer else None)]
    else:
        checks = [check("dt", table[-2] if len(table) > 1 else None)]
    stopped = all(c[-1] for c in checks)
    # Without a reference that has stopped moving there is no converged pile to be near: no verdict.
    done = [t for t in table if t["converged"]] if stopped else []
    fastest = min(done, key=lambda t: t["wall_s"]) if done else None
    return table, fastest, stopped, checks


def polydem_rows(record):
    return [dict(r, setting=f"k x{r['k_factor']:g}, dt x{r['dt_scale']:g}") for r in record["runs"]]


def newton_rows(record):
    """The rows of a newton_pour.py record, less those whose SAP scan wrapped (its broad phase missed pairs, so
    the pile is not Newton's: BENCHMARKS.md 26f), each named on stdout."""
    rows = []
    for r in record["rows"]:
        if r.get("sap_scan_overflow"):
            print(f"newton, {record['grains']} grains, dt {r['dt']:g} s: left out, its SAP scan wrapped "
                  f"({r['sap_work_start']:,} work items)")  # fmt: skip
            continue
        rows.append(dict(r, setting=f"dt {r['dt']:g} s", bodies=record["grains"]))
    return rows


def print_table(name, n, table, fastest, stopped, checks):
    print(f"\n{name}, {n} grains (reference: the last row; converged: phi within the tolerance and Z too)")
    print(f"{'setting':>22s} {'runs':>4s} {'settled':>7s} {'t_settle':>8s} {'wall s':>8s} {'phi':>7s} {'Z':>6s} conv")
    for t in table:
        phi = "-" if t["phi"] is None else f"{t['phi']:.4f}"
        z = "-" if t["z"] is None else f"{t['z']:.3f}"
        print(
            f"{t['setting']:>22s} {t['runs']:>4d} {str(t['settled']):>7s} {t['settle_time_s']:>8.3f} "
            f"{t['wall_s']:>8.2f} {phi:>7s} {z:>6s} {'yes' if t['converged'] else 'no'}"
        )
    for what, other, dphi, dz, ok in checks:
        if other is None:
            print(f"  refined in {what}: no setting to compare with (run one)")
        elif dphi is None:
            print(f"  refined in {what} from {other}: no phi and Z to compare")
        else:
            print(f"  refined in {what} from {other}: phi {dphi:+.4f}, Z {dz:+.3f}: {'within' if ok else 'OUTSIDE'} "
                  "the tolerances")  # fmt: skip
    if stopped:
        print(f"  the reference has stopped moving; fastest converged: {fastest['setting'] if fastest else 'none'}")
    else:
        print(f"  NO VERDICT: the reference still moves (or was not refined); the converged pile takes more than "
              f"{table[-1]['wall_s']:.2f} s")  # fmt: skip


def analyse(record, newton_records, phi_tol, z_tol):
    """Per size: polydem's table and fastest converged setting, Newton's where given, and the ratio."""
    by_size = defaultdict(list)
    for r in polydem_rows(record):
        by_size[r["bodies"]].append(r)
    newton_by_size = defaultdict(list)
    for rec in newton_records:
        for r in newton_rows(rec):
            newton_by_size[r["bodies"]].append(r)
    out = {}
    for n in sorted(set(by_size) | set(newton_by_size)):
        entry = {}
        if by_size.get(n):
            # refined: stiffer first, then the smaller absolute step
            summary = summarise(by_size[n], lambda r: (r["k_factor"], -r["dt"]))
            table, fastest, stopped, checks = judge(summary, phi_tol, z_tol, by_k=True)
            print_table("polydem", n, table, fastest, stopped, checks)
            entry["polydem"] = {"table": table, "fastest": fastest, "refined_agree": stopped, "checks": checks}
        if newton_by_size.get(n):
            table, fastest, stopped, checks = judge(summarise(newton_by_size[n], lambda r: -r["dt"]), phi_tol, z_tol)
            print_table("Newton", n, table, fastest, stopped, checks)
            entry["newton"] = {"table": table, "fastest": fastest, "refined_agree": stopped, "checks": checks}
        p, q = (entry.get(c, {}).get("fastest") for c in ("polydem", "newton"))
        # a ratio only where both codes' references have stopped moving (judge gives no fastest otherwise)
        if p and q:
            entry["newton_over_polydem"] = q["wall_s"] / p["wall_s"]
            print(f"  time to the converged pile: polydem {p['wall_s']:.2f} s, Newton {q['wall_s']:.2f} s: "
                  f"polydem {entry['newton_over_polydem']:.2f}x sooner")  # fmt: skip
        out[str(n)] = entry
    return out


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--device", default="cpu")
    ap.add_argument("--sizes", default="200", help="comma-separated cube counts")
    ap.add_argument("--settings", default="1x4,4x4", help="comma-separated KxS: k factor x dt scale")
    ap.add_argument("--seeds", default="0", help="comma-separated seeds of the pour")
    ap.add_argument("--phi-tol", type=float, default=PHI_TOL)
    ap.add_argument("--z-tol", type=float, default=Z_TOL)
    ap.add_argument("--newton", default=None, help="comma-separated newton_pour.py --dt-sweep JSON files")
    ap.add_argument("--analyse", default=None, help="JSON files of this script (comma-separated): analyse them")
    ap.add_argument("--out", default=None, help="JSON (default benchmarks/results/converged_pile_<device>.json)")
    args, rest = ap.parse_known_args()
    newton = []
    for path in (args.newton or "").split(","):
        if path:
            with open(path) as f:
                newton.append(json.load(f))
    if args.analyse:
        record = {"runs": []}
        for path in args.analyse.split(","):
            with open(path) as f:
                record["runs"] += json.load(f)["runs"]
        analyse(record, newton, args.phi_tol, args.z_tol)
        return

    import warp as wp
    from _meta import run_meta
    from time_to_settle import make_parser, run_size

    # time_to_settle.py's options (precision, k rule, criterion, ...) for the runs
    tts_args = make_parser().parse_args(rest)
    wp.config.quiet = True
    wp.init()
    device = wp.get_device(args.device)
    out = args.out or os.path.join(
        os.path.dirname(os.path.abspath(__file__)), "results", f"converged_pile_{str(device).replace(':', '')}.json"
    )
    record = {"meta": run_meta(device), "args": vars(args), "time_to_settle_args": vars(tts_args), "runs": []}

    def save():
        os.makedirs(os.path.dirname(out) or ".", exist_ok=True)
        with open(out, "w") as f:
            json.dump(record, f, indent=1)

    settings = parse_settings(args.settings)
    for n in (int(float(s)) for s in args.sizes.split(",")):
        for k, scale in settings:
            for seed in (int(s) for s in args.seeds.split(",")):
                tts_args.k_factor, tts_args.seed = k, seed
                r = run_size(n, tts_args, device, scale)
                r |= {"k_factor": k, "seed": seed}
                record["runs"].append(r)
                print(
                    f"{n} cubes, k x{k:g}, dt x{scale:g}, seed {seed}: settled {r['settled']} at "
                    f"{r['settle_time_s']}, {r['steps']} steps, {r['wall_s']:.2f} s, phi {r['packing_fraction']}, "
                    f"Z {r['coordination_number']}",
                    flush=True,
                )
                save()
    record["analysis"] = analyse(record, newton, args.phi_tol, args.z_tol)
    save()
    print(f"wrote {out}")


if __name__ == "__main__":
    main()
