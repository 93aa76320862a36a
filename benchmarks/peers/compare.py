"""Ratios and differences between polydem and the peer codes, from the JSON files in results/peers/.

    python benchmarks/peers/compare.py            # -> results/peers/compare.json and a table

Contact geometry (``pairs.json`` from contact_pairs.py, ``yade_pairs.json`` from yade_pairs.py):
per pair, Yade's overlap volume against polydem's exact one (relative difference; Yade's
first-step value too), the angle between Yade's contact normal and polydem's S_A/|S_A|, the
distance between the contact points (x size), the angle between the forces on A, and polydem's own
float32 normal against its float64 one; summarised per shape and depth.

Pours (``polydem_pour_*``, ``yade_pour_*``, ``newton_pour_*``): time per body-step and polydem's
speed-up over each peer (only between runs on the same kind of device: CPU with CPU, GPU with GPU),
and the overlaps of every code's final state measured with one yardstick: the exact float64
overlap volume (``polydem.overlap``) of every cube pair whose bounding spheres meet and of every
cube with the walls, as a fraction of a cube's volume (the largest, and the number of pairs with an
overlap), and the largest penetration depth as a fraction of the edge. Codes whose contact law is
not polydem's (Yade: force proportional to V; Newton: point contacts) are compared on what they
are, not on equal stiffness.
"""

import argparse
import glob
import json
import math
import os

import numpy as np

HERE = os.path.dirname(os.path.abspath(__file__))
PEERS = os.path.join(HERE, "..", "results", "peers")


def angle_deg(a, b):
    a = np.asarray(a, dtype=np.float64)
    b = np.asarray(b, dtype=np.float64)
    na, nb = np.linalg.norm(a), np.linalg.norm(b)
    if na == 0.0 or nb == 0.0:
        return float("nan")
    return math.degrees(math.acos(float(np.clip(a @ b / (na * nb), -1.0, 1.0))))


def compare_pairs(peers_dir):
    path_p = os.path.join(peers_dir, "pairs.json")
    path_y = os.path.join(peers_dir, "yade_pairs.json")
    if not (os.path.exists(path_p) and os.path.exists(path_y)):
        return None
    with open(path_p) as f:
        pairs = json.load(f)["pairs"]
    with open(path_y) as f:
        yade = json.load(f)["pairs"]
    rows = []
    for p, y in zip(pairs, yade, strict=True):
        row = {"shape": p["shape"], "depth": p["depth"], "found": y["found"], "volume": p["volume"]}
        row["f32_normal_angle_deg"] = angle_deg(p["normal"], p["float32"]["normal"])
        if y["found"]:
            row.update(
                {
                    "volume_rel_diff": (y["volume"] - p["volume"]) / p["volume"],
                    "volume_rel_diff_first_step": (
                        None
                        if y.get("volume_first_step") is None
                        else (y["volume_first_step"] - p["volume"]) / p["volume"]
                    ),
                    "normal_angle_deg": angle_deg(p["normal"], y["normal"]),
                    "contact_point_distance": float(
                        np.linalg.norm(np.subtract(p["contact_point"], y["contact_point"])) / p["size"]
                    ),
                    # polydem's force on A is along -S_A; Yade's force on A as written by yade_pairs.py.
                    "force_angle_deg": angle_deg(-np.asarray(p["area_vector"]), y["force_on_a"]),
                    "yade_force_over_volume": float(np.linalg.norm(y["force_on_a"]) / y["volume"])
                    if y["volume"] > 0
                    else None,
                    "polydem_area_over_yade_cross_section": float(
                        np.linalg.norm(p["area_vector"]) / y["equivalent_cross_section"]
                    )
                    if y.get("equivalent_cross_section")
                    else None,
                }
            )
        rows.append(row)
    summary = []
    for shape in sorted({r["shape"] for r in rows}):
        for depth in sorted({r["depth"] for r in rows}):
            g = [r for r in rows if r["shape"] == shape and r["depth"] == depth]
            f = [r for r in g if r["found"]]

            def stat(key, rows_=f, fn=np.max):
                vals = [abs(r[key]) for r in rows_ if r.get(key) is not None and np.isfinite(r[key])]
                return float(fn(vals)) if vals else None

            summary.append(
                {
                    "shape": shape,
                    "depth": depth,
                    "pairs": len(g),
                    "yade_found": len(f),
                    "normal_angle_deg_median": stat("normal_angle_deg", fn=np.median),
                    "normal_angle_deg_max": stat("normal_angle_deg"),
                    "force_angle_deg_max": stat("force_angle_deg"),
                    "volume_rel_diff_max": stat("volume_rel_diff"),
                    "volume_rel_diff_first_step_max": stat("volume_rel_diff_first_step"),
                    "contact_point_distance_max": stat("contact_point_distance"),
                    "polydem_f32_normal_angle_deg_max": stat("f32_normal_angle_deg", rows_=g),
                }
            )
    return {"rows": rows, "summary": summary}


# ---------------------------------------------------------------------------------------------
# Overlaps of a final state, with one yardstick


def quat_from_cube_vertices(world, edge):
    """(centre, xyzw quaternion) of a cube given its 8 world vertices, in any order.

    The three edges at one vertex give the axes; the result maps the axis-aligned cube of edge
    ``edge`` (polydem's body frame of ``ConvexShape.box``) onto ``world``.
    """
    from scipy.spatial.transform import Rotation

    w = np.asarray(world, dtype=np.float64)
    c = w.mean(axis=0)
    d = np.linalg.norm(w - w[0], axis=1)
    near = np.argsort(d)[1:4]
    axes = (w[near] - w[0]).T / edge
    if np.linalg.det(axes) < 0.0:
        axes[:, 2] *= -1.0
    u, _, vt = np.linalg.svd(axes)
    r = u @ vt
    return c, Rotation.from_matrix(r).as_quat()  # xyzw


def measure_overlaps(positions, quats, scene):
    """Largest overlap volume (x cube volume), largest penetration depth (x edge) and number of
    overlapping pairs, cube-cube and cube-wall."""
    import warp as wp
    from scipy.spatial import cKDTree

    wp.config.quiet = True
    wp.config.log_level = wp.LOG_WARNING
    import polydem

    a = scene["edge"]
    cube = polydem.ConvexShape.box(a)
    r = cube.radius
    pos = np.asarray(positions, dtype=np.float64)
    q = np.asarray(quats, dtype=np.float64)
    q /= np.linalg.norm(q, axis=1, keepdims=True)
    poses = np.hstack([pos, q])
    pairs = np.array(sorted(cKDTree(pos).query_pairs(2.0 * r)), dtype=np.int64).reshape(-1, 2)
    vols = []
    depths = []
    if len(pairs):
        res = polydem.overlap(
            cube, poses[pairs[:, 0]], cube, poses[pairs[:, 1]], frame="body", device="cpu", precision="float64"
        )
        vols.append(res.volume)
        depths.append(res.depth)
    for w in scene["walls"]:
        half = np.asarray(w["half_extents_body"])
        box = polydem.ConvexShape.box(*(2.0 * half))
        centre = np.asarray(w["center"])
        # Walls are axis-aligned in the world, but the side walls' body axes are turned against it
        # (half_extents_body is not the world box): the distance from a cube centre to the world box
        # of the wall's vertices decides the candidates.
        corners = np.asarray(w["world_vertices"], dtype=np.float64)
        gap = np.maximum(np.maximum(corners.min(axis=0) - pos, pos - corners.max(axis=0)), 0.0)
        near = np.flatnonzero(np.linalg.norm(gap, axis=1) < r)
        if len(near):
            wall_pose = np.concatenate([centre, w["orientation_xyzw"]])
            res = polydem.overlap(cube, poses[near], box, wall_pose, frame="body", device="cpu", precision="float64")
            vols.append(res.volume)
            depths.append(res.depth)
    v = np.concatenate(vols) if vols else np.zeros(0)
    d = np.concatenate(depths) if depths else np.zeros(0)
    return {
        "max_overlap_volume_fraction": float(v.max() / a**3) if len(v) else 0.0,
        # The penetration depth (shortest separating translation), what a user sees and what
        # Newton reports natively, beside the volume, which is polydem's measure.
        "max_depth_fraction_of_edge": float(d.max() / a) if len(d) else 0.0,
        "overlapping_pairs": int((v > 0).sum()),
        "mean_overlap_volume_fraction": float(v[v > 0].mean() / a**3) if (v > 0).any() else 0.0,
    }


def final_poses(run, scene):
    final = run.get("final")
    if not final:
        return None
    if run["code"] == "yade":
        poses = [quat_from_cube_vertices(w, scene["edge"]) for w in final["world_vertices"]]
        return np.array([p[0] for p in poses]), np.array([p[1] for p in poses])
    return np.asarray(final["position"]), np.asarray(final["orientation_xyzw"])


def device_kind(run):
    name = str(run.get("device", ""))
    return "cpu" if name.upper() == "CPU" else "gpu"


def compare_pours(peers_dir, skip_overlaps):
    runs = []
    for path in sorted(glob.glob(os.path.join(peers_dir, "*_pour_*.json"))):
        with open(path) as f:
            run = json.load(f)
        run["file"] = os.path.basename(path)
        runs.append(run)
    rows = []
    for run in runs:
        n = run["grains"]
        row = {
            k: run.get(k)
            for k in (
                "file",
                "code",
                "version",
                "device",
                "threads",
                "solver",
                "grains",
                "dt",
                "steps",
                "step_s",
                "body_steps_per_s",
                "contacts",
                "max_penetration_at_rest_m",
                "max_overlap_volume_fraction_own",
            )
        }
        row["device_kind"] = device_kind(run)
        row["ns_per_body_step"] = 1e9 / run["body_steps_per_s"]
        # A code with a longer step covers more simulated time per step: compare that too.
        row["simulated_s_per_wall_s"] = run["dt"] / run["step_s"] if run.get("dt") else None
        scene_path = os.path.join(peers_dir, f"pour_{n}.json")
        if not skip_overlaps and os.path.exists(scene_path):
            with open(scene_path) as f:
                scene = json.load(f)
            fp = final_poses(run, scene)
            if fp is not None:
                row["final_overlaps"] = measure_overlaps(fp[0], fp[1], scene)
        rows.append(row)
    # polydem's speed-up over each peer: same grains, same kind of device.
    for row in rows:
        if row["code"] == "polydem":
            continue
        ref = [
            r
            for r in rows
            if r["code"] == "polydem" and r["grains"] == row["grains"] and r["device_kind"] == row["device_kind"]
        ]
        if ref:
            row["polydem_speedup"] = ref[0]["body_steps_per_s"] / row["body_steps_per_s"]
            if ref[0]["simulated_s_per_wall_s"] and row["simulated_s_per_wall_s"]:
                row["polydem_speedup_simulated_time"] = ref[0]["simulated_s_per_wall_s"] / row["simulated_s_per_wall_s"]
            row["polydem_reference"] = ref[0]["file"]
    return rows


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--dir", default=PEERS)
    ap.add_argument("--out", default=None)
    ap.add_argument("--skip-overlaps", action="store_true", help="do not measure the final states' overlaps")
    args = ap.parse_args()
    out = {"pairs": compare_pairs(args.dir), "pours": compare_pours(args.dir, args.skip_overlaps)}
    if out["pairs"]:
        print("contact geometry, Yade Polyhedra against polydem.overlap (float64):")
        print(
            f"{'shape':<8}{'depth':>7}{'found':>7}{'normal med':>11}{'normal max':>11}{'force max':>10}"
            f"{'dV max':>9}{'dV 1st':>9}{'point':>9}{'f32 normal':>11}"
        )

        def f(v, fmt):
            return "-" if v is None else format(v, fmt)

        for s in out["pairs"]["summary"]:
            print(
                f"{s['shape']:<8}{s['depth']:>7g}{s['yade_found']:>4}/{s['pairs']:<2}"
                f"{f(s['normal_angle_deg_median'], '.2f'):>11}{f(s['normal_angle_deg_max'], '.2f'):>11}"
                f"{f(s['force_angle_deg_max'], '.2f'):>10}{f(s['volume_rel_diff_max'], '.1e'):>9}"
                f"{f(s['volume_rel_diff_first_step_max'], '.1e'):>9}{f(s['contact_point_distance_max'], '.1e'):>9}"
                f"{f(s['polydem_f32_normal_angle_deg_max'], '.1e'):>11}"
            )
    if out["pours"]:
        print("\npours (same scene and protocol; see pour_scene.py):")
        print(
            f"{'code':<9}{'device':<14}{'thr':>4}{'N':>7}{'dt':>9}{'ms/step':>10}{'ns/body-step':>13}{'speed-up':>9}"
            f"{'sim s/s':>9}{'sim-time x':>11}{'max overlap':>12}{'max depth':>10}{'overlapping':>12}"
        )
        for r in out["pours"]:
            fo = r.get("final_overlaps", {})
            sim_x = r.get("polydem_speedup_simulated_time")
            print(
                f"{r['code']:<9}{str(r['device'])[:13]:<14}{str(r.get('threads') or '-'):>4}{r['grains']:>7}"
                f"{r['dt']:>9.3g}{1e3 * r['step_s']:>10.3f}{r['ns_per_body_step']:>13.0f}"
                f"{(format(r['polydem_speedup'], '.1f') + 'x') if 'polydem_speedup' in r else '-':>9}"
                f"{format(r['simulated_s_per_wall_s'] or 0.0, '.3g'):>9}"
                f"{(format(sim_x, '.2g') + 'x') if sim_x else '-':>11}"
                f"{(format(100 * fo['max_overlap_volume_fraction'], '.2f') + '%') if fo else '-':>12}"
                f"{(format(100 * fo['max_depth_fraction_of_edge'], '.1f') + '%') if fo else '-':>10}"
                f"{fo.get('overlapping_pairs', '-'):>12}"
            )
    path = args.out or os.path.join(args.dir, "compare.json")
    with open(path, "w") as f:
        json.dump(out, f, indent=1)
    print(f"\nwrote {path}")


if __name__ == "__main__":
    main()
