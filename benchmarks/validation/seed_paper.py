"""The seed paper's own claims, reproduced (VALIDATION.md section 4).

Feng, Han and Owen, "An energy-based polyhedron-to-polyhedron contact model" (the paper in
../shared/seed/), gives no numerical tables: it derives the contact law from an energy W(V) of the
overlap volume and states what follows. Each claim that can be measured is measured here, on the
paper's own case (Fig. 1: two cubes meeting corner to corner) and on a sweep through every kind of
contact:

1. Eqs. (8)-(21): the force is -W'(V) times the gradient of V under translation, the moment -W'(V)
   times its gradient under rotation. Measured: S_A and M_A - x_A x S_A against central finite
   differences of V (float64), for the corner/corner contact of Fig. 1 and for random poses.
2. Eqs. (22)-(23), Fig. 3: the facet forces of A and of B form an equilibrium system (S_A + S_B = 0,
   M_A + M_B = 0).
3. Eq. (24) and what follows: the contact point lies on the central axis of the wrench (the moment
   of the normal force about it is the whole moment, up to a part along the normal) and on the
   contact plane through the overlap centroid.
4. Introduction and section 3: the normal "evolves in a smooth way" and needs "no distinction between
   node/node, node/edge, edge/edge, edge/surface and surface/surface" contacts. Measured: one cube slid
   corner down across another's top face and out over its edge, so that the contact goes from
   corner/face to edge/edge; the largest turn of the normal between neighbouring poses, as the
   spacing of the poses is halved. A continuous normal halves its largest turn with the spacing. The
   same is shown for the least-penetration separating axis, the usual feature-based normal (computed
   here independently with numpy), which jumps wherever the deepest feature changes.
5. Section 1: no artificial energy. Two cubes collide corner first, spinning, with no damping,
   friction or gravity, under each law of the paper's Table 1; the total energy after the impact
   against before, as the step is halved (symplectic Euler: the error must fall with the step).

    python benchmarks/validation/seed_paper.py            # CPU, about a minute
    python benchmarks/validation/seed_paper.py --quick    # the CI size

Prints a table per claim and writes benchmarks/results/validation/seed_paper.json.
"""

from __future__ import annotations

import argparse
import itertools
import json
import math
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[2]
OUT = ROOT / "benchmarks" / "results" / "validation" / "seed_paper.json"
EDGE = 0.1  # m


def _quat_axis_angle(axis, angle) -> np.ndarray:
    axis = np.asarray(axis, dtype=np.float64)
    axis = axis / np.linalg.norm(axis)
    return np.concatenate([axis * math.sin(angle / 2), [math.cos(angle / 2)]])  # x, y, z, w


def _quat_mul(p, q) -> np.ndarray:
    pv, pw, qv, qw = p[:3], p[3], q[:3], q[3]
    return np.concatenate([pw * qv + qw * pv + np.cross(pv, qv), [pw * qw - pv @ qv]])


def _rot(q) -> np.ndarray:
    x, y, z, w = q
    return np.array(
        [
            [1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
            [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
            [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)],
        ]
    )


def corner_out(direction) -> np.ndarray:
    """Quaternion that turns a cube's corner (1, 1, 1) onto ``direction``."""
    a = np.ones(3) / math.sqrt(3.0)
    b = np.asarray(direction, dtype=np.float64)
    b = b / np.linalg.norm(b)
    axis = np.cross(a, b)
    s = np.linalg.norm(axis)
    if s < 1e-15:
        return _quat_axis_angle((1.0, 0.0, 0.0), 0.0 if a @ b > 0 else math.pi)
    return _quat_axis_angle(axis, math.atan2(s, a @ b))


def _poses(positions, quats) -> np.ndarray:
    return np.concatenate([np.atleast_2d(positions), np.atleast_2d(quats)], axis=1)


def fig1_poses(depth: float, twist: float = 0.0) -> tuple[np.ndarray, np.ndarray]:
    """Fig. 1: cube A's corner points along +x, B's along -x, the corners ``depth`` into each other;
    ``twist`` turns B about the x axis (0: the symmetric case)."""
    half_diag = EDGE * math.sqrt(3.0) / 2
    qa = corner_out((1.0, 0.0, 0.0))
    qb = _quat_mul(_quat_axis_angle((1.0, 0.0, 0.0), twist), corner_out((-1.0, 0.0, 0.0)))
    return _poses((-half_diag, 0.0, 0.0), qa), _poses((half_diag - depth, 0.0, 0.0), qb)


# --- 1-3: gradients, equilibrium, contact point ------------------------------------------------


def gradient_check(cube, pa, pb, h=1e-8) -> dict:
    """S_A and M_A - x_A x S_A against central differences of V, float64 (claims 1 and 2, 3)."""
    from polydem import overlap

    n = len(pa)
    rows_a, rows_b = [pa], [pb]
    for axis in range(3):  # translations of A
        for sign in (1.0, -1.0):
            q = pa.copy()
            q[:, axis] += sign * h
            rows_a.append(q)
            rows_b.append(pb)
    for axis in range(3):  # turns of A about its pose's position (input frame: the cube's centre)
        e = np.zeros(3)
        e[axis] = 1.0
        for sign in (1.0, -1.0):
            dq = _quat_axis_angle(e, sign * h)
            q = pa.copy()
            q[:, 3:] = np.array([_quat_mul(dq, qq) for qq in pa[:, 3:]])
            rows_a.append(q)
            rows_b.append(pb)
    res = overlap(cube, np.concatenate(rows_a), cube, np.concatenate(rows_b), precision="float64", device="cpu")
    v = res.volume.reshape(13, n)
    fd_s = np.stack([(v[1 + 2 * k] - v[2 + 2 * k]) / (2 * h) for k in range(3)], axis=1)
    fd_m = np.stack([(v[7 + 2 * k] - v[8 + 2 * k]) / (2 * h) for k in range(3)], axis=1)
    s = res.area_vector[:n]
    rot = res.moment[:n] - np.cross(pa[:, :3], s)
    scale_s = np.linalg.norm(s, axis=1)
    scale_m = scale_s * EDGE
    eq_s = np.linalg.norm(res.area_vector[:n] + res.area_vector_b[:n], axis=1) / scale_s
    eq_m = np.linalg.norm(res.moment[:n] + res.moment_b[:n], axis=1) / scale_m
    # Contact point: the normal force's moment about it plus a part along the normal is the whole
    # moment (the central axis), and it lies on the plane through the centroid (Eq. 24 and below).
    nrm = res.normal[:n]
    c = res.contact_point[:n]
    resid = res.moment[:n] - np.cross(c, s)
    off_axis = np.linalg.norm(resid - np.sum(resid * nrm, axis=1)[:, None] * nrm, axis=1) / scale_m
    off_plane = np.abs(np.sum((c - res.centroid[:n]) * nrm, axis=1)) / EDGE
    return {
        "volume": v[0].tolist(),
        "force_fd_error": (np.linalg.norm(s - fd_s, axis=1) / scale_s).tolist(),
        "moment_fd_error": (np.linalg.norm(rot - fd_m, axis=1) / scale_m).tolist(),
        "equilibrium_force": eq_s.tolist(),
        "equilibrium_moment": eq_m.tolist(),
        "contact_point_off_axis": off_axis.tolist(),
        "contact_point_off_plane": off_plane.tolist(),
        "normal": nrm.tolist(),
    }


def random_touching_poses(rng, count) -> tuple[np.ndarray, np.ndarray]:
    qa = rng.normal(size=(count, 4))
    qb = rng.normal(size=(count, 4))
    qa /= np.linalg.norm(qa, axis=1)[:, None]
    qb /= np.linalg.norm(qb, axis=1)[:, None]
    d = rng.normal(size=(count, 3))
    d /= np.linalg.norm(d, axis=1)[:, None]
    dist = EDGE * rng.uniform(0.75, 1.05, size=count)  # between face-to-face depth and corner reach
    return _poses(np.zeros((count, 3)), qa), _poses(d * dist[:, None], qb)


# --- 4: smoothness of the normal ------------------------------------------------------------


def _cube_axes(q) -> np.ndarray:
    return _rot(q).T  # rows: the cube's face normals (+ side)


def sat_normal(pa, pb) -> np.ndarray:
    """The least-penetration separating axis of two cubes (feature-based normal), from A into B."""
    ra, rb = _cube_axes(pa[3:]), _cube_axes(pb[3:])
    axes = list(ra) + list(rb)
    for u, w in itertools.product(ra, rb):
        c = np.cross(u, w)
        if np.linalg.norm(c) > 1e-9:
            axes.append(c / np.linalg.norm(c))
    h = EDGE / 2
    d = pb[:3] - pa[:3]
    best, best_axis = np.inf, None
    for ax in axes:
        reach = h * (np.abs(ra @ ax).sum() + np.abs(rb @ ax).sum())
        pen = reach - abs(d @ ax)
        if pen < best:
            best, best_axis = pen, ax if d @ ax >= 0 else -ax
    return best_axis


def slide_path(count: int, depth: float) -> tuple[np.ndarray, np.ndarray]:
    """Cube A lies face up; cube B, corner down and twisted, slides across A's top face and out over
    its edge, held ``depth`` into A at its lowest point where it is over the face: the contact is
    corner/face, then B's corner and edges cross A's edge (edge/edge), until B leaves A."""
    qa = np.array([0.0, 0.0, 0.0, 1.0])
    qb = _quat_mul(_quat_axis_angle((0.3, -0.2, 1.0), 0.4), corner_out((0.2, 0.1, -1.0)))
    low = (_rot(qb) @ (EDGE / 2 * np.array(list(itertools.product((-1, 1), repeat=3))).T))[2].min()
    s = np.linspace(0.0, 1.0, count)
    # From over A's middle to beyond its corner (+x, +y), on a line that passes near the corner.
    start, end = np.array([0.0, 0.01, 0.0]), np.array([0.075, 0.07, 0.0])
    xy = start[None, :] + s[:, None] * (end - start)[None, :]
    z = EDGE / 2 - low - depth
    pb = np.concatenate([xy[:, :2], np.full((count, 1), z), np.tile(qb, (count, 1))], axis=1)
    pa = np.tile(np.concatenate([[0.0, 0.0, 0.0], qa]), (count, 1))
    return pa, pb


def smoothness(cube, counts, depth) -> list[dict]:
    from polydem import overlap

    out = []
    for count in counts:
        pa, pb = slide_path(count, depth)
        res = overlap(cube, pa, cube, pb, precision="float64", device="cpu")
        touching = res.volume > 0
        n = res.normal
        sat = np.array([sat_normal(a, b) for a, b in zip(pa, pb, strict=True)])
        both = touching[1:] & touching[:-1]

        def turn(u, both=both):
            cosang = np.clip(np.sum(u[1:] * u[:-1], axis=1), -1.0, 1.0)
            return np.degrees(np.arccos(cosang))[both]

        out.append(
            {
                "poses": count,
                "spacing_mm": 1e3 * np.linalg.norm(pb[1, :2] - pb[0, :2]),
                "touching": int(touching.sum()),
                "energy_normal_max_turn_deg": float(turn(n).max()),
                "sat_normal_max_turn_deg": float(turn(sat).max()),
                "sat_jumps_over_5deg": int((turn(sat) > 5.0).sum()),
                "energy_normal_total_turn_deg": float(turn(n).sum()),
            }
        )
    return out


# --- 5: energy through an impact --------------------------------------------------------------


def impact_energy(law: str, dt_factors) -> list[dict]:
    """Two cubes meet corner first and spinning, no damping, friction or gravity: total energy
    after the impact against before, for a step of dt_auto / factor."""
    import polydem

    def build(dt):
        scene = polydem.Scene(gravity=(0.0, 0.0, 0.0), dt=dt)
        k = {"linear": 1e8, "hertz": 1e10, "power": 1e10}[law]
        extra = {"m": 1.8} if law == "power" else {}
        scene.add_material("glass", density=2500, law=law, k=k, restitution=1.0, friction=0.0, **extra)
        scene.add_shape("cube", polydem.ConvexShape.box(EDGE))
        pa, pb = fig1_poses(0.0, twist=0.3)
        gap = 0.004
        scene.add_body("cube", "glass", position=pa[0, :3] - (gap, 0, 0), orientation=pa[0, 3:],
                       velocity=(0.5, 0.02, 0.0), angular_velocity=(3.0, 1.0, -2.0))  # fmt: skip
        scene.add_body("cube", "glass", position=pb[0, :3] + (gap, 0, 0), orientation=pb[0, 3:],
                       velocity=(-0.5, 0.0, 0.01), angular_velocity=(-1.0, 2.0, 0.5))  # fmt: skip
        return scene

    dt_auto = build("auto").time_step().dt
    rows = []
    for factor in dt_factors:
        sim = polydem.Simulation(build(dt_auto / factor), device="cpu")
        e0 = sim.energy()["total"]
        # Step until the cubes have met and parted again (checked every chunk of simulated time).
        chunk = max(1, int(round(2e-4 / sim.dt)))
        met, steps = False, 0
        while steps * sim.dt < 0.1:
            sim.step(chunk)
            steps += chunk
            contact = sim.energy()["contact"]
            met = met or contact > 0.0
            if met and contact == 0.0:
                break
        e1 = sim.energy()
        rows.append(
            {
                "law": law,
                "dt": sim.dt,
                "steps": steps,
                "met": met,
                "energy_before_J": e0,
                "energy_after_J": e1["total"],
                "contact_energy_after_J": e1["contact"],
                "relative_change": (e1["total"] - e0) / e0,
            }
        )
    return rows


def main(argv=None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--quick", action="store_true", help="the CI size")
    ap.add_argument("--out", type=Path, default=OUT)
    args = ap.parse_args(argv)
    import polydem

    t0 = time.perf_counter()
    cube = polydem.ConvexShape.box(EDGE)
    result: dict = {"edge_m": EDGE}

    # 1-3 on Fig. 1 (symmetric and twisted, three depths) and on random touching poses.
    fig = {}
    for twist in (0.0, 0.4):
        for depth in (1e-4, 1e-3, 1e-2):
            pa, pb = fig1_poses(depth * EDGE, twist)
            fig[f"twist {twist} depth {depth}"] = gradient_check(cube, pa, pb, h=1e-4 * depth * EDGE)
    result["fig1"] = fig
    rng = np.random.default_rng(7)
    pa, pb = random_touching_poses(rng, 40 if args.quick else 400)
    rnd = gradient_check(cube, pa, pb)
    keep = np.array(rnd["volume"]) > 1e-9 * EDGE**3
    result["random"] = {
        "poses": int(keep.sum()),
        **{k: float(np.max(np.array(v)[keep])) for k, v in rnd.items() if k not in ("volume", "normal")},
    }
    print("Claims 1-3: relative errors (largest over the cases)")
    heads = ("dV/dx", "dV/dtheta", "S_A+S_B", "M_A+M_B", "off axis", "off plane")
    print(f"{'case':28s} " + " ".join(f"{h:>9s}" for h in heads))
    for name, r in list(fig.items()) + [("random (" + str(result["random"]["poses"]) + ")", None)]:
        r = r or {k: [v] for k, v in result["random"].items()}
        print(
            f"{name:28s} {max(r['force_fd_error']):9.1e} {max(r['moment_fd_error']):9.1e} "
            f"{max(r['equilibrium_force']):9.1e} {max(r['equilibrium_moment']):9.1e} "
            f"{max(r['contact_point_off_axis']):9.1e} {max(r['contact_point_off_plane']):9.1e}"
        )
    sym = fig["twist 0.0 depth 0.001"]["normal"][0]
    print(f"Fig. 1 symmetric normal: {np.round(sym, 12)} (along the line of the corners)")
    result["fig1_symmetric_normal"] = sym

    # 4: the normal along the slide.
    counts = (200, 400, 800) if args.quick else (400, 800, 1600, 3200)
    sm = smoothness(cube, counts, 0.05 * EDGE)
    result["smoothness"] = sm
    print("\nClaim 4: largest turn of the normal between neighbouring poses [deg]")
    print(f"{'poses':>6s} {'spacing mm':>10s} {'energy':>9s} {'separating axis':>16s} {'axis jumps > 5 deg':>19s}")
    for r in sm:
        print(
            f"{r['poses']:6d} {r['spacing_mm']:10.4f} {r['energy_normal_max_turn_deg']:9.4f} "
            f"{r['sat_normal_max_turn_deg']:16.2f} {r['sat_jumps_over_5deg']:19d}"
        )

    # 5: energy through the impact.
    factors = (1, 2) if args.quick else (1, 2, 4)
    imp = []
    for law in ("linear", "hertz", "power"):
        imp += impact_energy(law, factors)
    result["impact_energy"] = imp
    print("\nClaim 5: total energy after a corner-first impact, no damping (relative change)")
    for r in imp:
        print(f"{r['law']:7s} dt {r['dt']:.3e} s  {r['steps']:6d} steps  {r['relative_change']:+.3e}  "
              f"(contact energy left {r['contact_energy_after_J']:.1e} J)")  # fmt: skip
    result["seconds"] = time.perf_counter() - t0
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(result, indent=1))
    print(f"\n{result['seconds']:.0f} s; wrote {args.out}")
    return result


if __name__ == "__main__":
    main()
