#!/usr/bin/env python3
"""Mutation check: deliberate faults that some test must catch.

A fault injected into a copy of the package (each pair's reaction 1e-4 too small) once passed every
physics and checkpoint test: their bounds were float32 ones while the default precision keeps
velocities and force sums in float64. This check keeps that from coming back. It copies the source
tree into a temporary folder, applies each fault below by text substitution to that copy, and runs the
few tests chosen to catch it (``-x``, on the CPU) against the copy. Every fault must make them fail;
the run exits non-zero naming each fault that survived.

The copy is imported, not installed: PYTHONPATH puts its ``src`` first, and its ``kernels`` folder
is copied to ``src/polydem/kernels``, the place where the package maps ``polydem.kernels``
(pyproject.toml, ``package-dir``), so that the mutated kernels are the ones loaded whether polydem is
installed plainly or editable. The check verifies that, and that each fault's target text is in its
file exactly once (a refactor that moves the text stops the check instead of disabling the fault).
The selected tests must first pass on the unmutated copy (a fault is only caught by tests that pass
without it).

Usage: python .ci/mutations.py [--list] [--only NAME ...] [--keep]
"""

import argparse
import os
import shutil
import subprocess
import sys
import tempfile
import time
from dataclasses import dataclass
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


@dataclass(frozen=True)
class Fault:
    name: str
    path: str  # relative to the repository root
    old: str
    new: str
    tests: tuple[str, ...]  # pytest node ids, relative to the repository root


FAULTS = (
    Fault(
        "reaction 1e-4 short",
        "kernels/forces.py",
        "        f -= fa\n",
        "        f -= fa * S(1.0 - 1.0e-4)\n",
        ("tests/test_simulation.py::test_momentum_conserved_without_walls[cpu-mixed]",),
    ),
    Fault(
        "friction cap 1% high",
        "kernels/response.py",
        "            cap = mu * fn\n",
        "            cap = mu * fn * scalar(1.01)\n",
        ("tests/test_simulation.py::test_incline_slides_above_friction_angle[cpu-35.0-0.3-hertz]",),
    ),
    Fault(
        "gravity 1e-4 strong",
        "kernels/integrate.py",
        "        v_new = v + (f * model.inv_mass[i] + gravity) * dt\n",
        "        v_new = v + (f * model.inv_mass[i] + gravity * scalar(1.0 + 1.0e-4)) * dt\n",
        ("tests/test_simulation.py::test_free_fall_and_projectile_closed_form[cpu-mixed]",),
    ),
    Fault(
        "restitution 2% low",
        "kernels/response.py",
        "        return turn - (turn - volume) / e2\n",
        "        return turn - (turn - volume) / (e2 * scalar(0.96))\n",
        ("tests/test_simulation.py::test_restitution_at_the_default_step[cpu-edge-0.6-mixed]",),
    ),
    Fault(
        "toe volume doubled",
        "kernels/response.py",
        "                vc = wp.exp(wp.min(ln_x / (scalar(2.0) - m), scalar(3.0) * wp.log(r_min)))\n",
        "                vc = scalar(2.0) * wp.exp(wp.min(ln_x / (scalar(2.0) - m), scalar(3.0) * wp.log(r_min)))\n",
        ("tests/test_depth.py::test_toe_depth_is_where_a_resting_simulation_carries_the_load[cpu-0.5]",),
    ),
    Fault(
        "coincident facets weighted 0.6",
        "kernels/geometry.py",
        "                        weight = scalar(0.5)\n",
        "                        weight = scalar(0.6)\n",
        ("tests/test_contact.py::test_aligned_stacked_cubes[cpu-float32]",),
    ),
    Fault(
        "drum turns against its axis",
        "src/polydem/scene/walls.py",
        "    omega_vec = np.broadcast_to(w * a, (n, 3))\n",
        "    omega_vec = np.broadcast_to(-w * a, (n, 3))\n",
        ("tests/test_drum.py::test_grains_ride_up_the_rising_side",),
    ),
    Fault(
        "energy plot without its curves",
        "src/polydem/plots.py",
        "        ax.plot(t, history[key], style, label=key)\n",
        "        pass\n",
        ("tests/test_plots.py::test_write_plots_of_a_simulation",),
    ),
    Fault(
        "flat contact clipped in body 1's axes",
        "kernels/geometry.py",
        "            frame = axes_onto(n_flat)\n",
        "            frame = mat33d(wp.identity(n=3, dtype=wp.float64))\n",
        ("tests/test_flat_contacts.py::test_float32_flat_contacts_match_float64[cpu-rock-on-tet]",),
    ),
    Fault(
        "a sliver cell's fallback turns a wall contact",
        "kernels/response.py",
        "        if s_norm < scalar(ENCLOSED_RATIO) * v23:\n",
        "        if s_norm < scalar(ENCLOSED_RATIO) * v23 or wp.length(fallback) > scalar(0.0):\n",
        ("tests/test_flat_contacts.py::test_face_on_a_grid_line_pushes_up[cpu-mixed-triangles]",),
    ),
    Fault(
        "compound cut faces shared half and half",
        "kernels/geometry.py",
        "                        if inside_face != inside_other:\n",
        "                        if inside_face != inside_other and False:\n",
        ("tests/test_flat_contacts.py::test_face_in_a_compound_cut_plane_gets_the_union_force[cpu-float64]",),
    ),
    Fault(
        "packing fraction: clipped grains left open",
        "src/polydem/measures.py",
        "    return _Segments.join([kept, closing, cap]), next_face + len(normal)\n",
        "    return _Segments.join([kept, closing]), next_face + len(normal)\n",
        ("tests/test_measures.py::test_clipped_volume_matches_halfspace_intersection",),
    ),
    Fault(
        "Love-Weber stress: whole branch counted",
        "src/polydem/measures.py",
        "    w = _inside_fraction(start, start + branch, box)\n",
        "    w = np.ones(len(start))\n",
        ("tests/test_measures.py::test_column_stress_is_the_weight_above[cpu]",),
    ),
    Fault(
        "a driven plane's velocity left out of its contacts",
        "kernels/forces.py",
        "vec3c(planes.v[j]), zero3, xi_pos,",
        "zero3, zero3, xi_pos,",
        ("tests/test_wall_motion.py::test_a_sideways_vibration_drags_the_cube_by_friction[cpu]",),
    ),
    Fault(
        "a driven plane 1e-4 too fast",
        "kernels/motion.py",
        "            planes.v[j] = vec3(scalar(v[0]), scalar(v[1]), scalar(v[2]))\n",
        "            planes.v[j] = vec3(scalar(v[0]), scalar(v[1]), scalar(v[2])) * scalar(1.0001)\n",
        ("tests/test_wall_motion.py::test_a_shaken_floor_follows_its_motion_and_carries_a_cube[cpu-plane]",),
    ),
    Fault(
        "spin scale not restored",
        "kernels/integrate.py",
        "            pi = pi + pi * ((norm - n) / n)\n",
        "            pi = pi\n",
        ("tests/test_integrate.py::test_many_float32_spins_keep_their_angular_momentum_unbiased[cpu]",),
    ),
    Fault(
        "initial overlaps on the device without edge axes",
        "kernels/initial_overlaps.py",
        "    if (ea1 - ea0) * (eb1 - eb0) <= max_edge_axes:\n",
        "    if (ea1 - ea0) * (eb1 - eb0) <= 0 * max_edge_axes:\n",
        ("tests/test_overlap_check.py::test_device_records_are_the_host_records[cpu-False]",),
    ),
    Fault(
        "pair threads by contact: the contact bit ignored",
        "kernels/pairlist.py",
        "            keys[p] = 2 * (top - keys[p])\n",
        "            keys[p] = 2 * (top - keys[p]) + 1\n",
        ("tests/test_pair_order.py::test_pair_threads_grouped_by_contact_give_the_same_bits[cpu-default]",),
    ),
    Fault(
        "in-place clipping: the output overruns the input (no hand-over to finish_pass)",
        "kernels/geometry.py",
        "                    if k + 2 < count and cut and keep and n_out > k:\n",
        "                    if k + 2 < count and cut and keep and n_out > k + 1:\n",
        ("tests/test_contact.py::test_a_polygon_that_crosses_a_plane_more_than_twice_is_clipped_whole[cpu-0]",),
    ),
    Fault(
        "the material table's damping factor off by 1e-4",
        "kernels/response.py",
        "        out[i] = damping_factor(e[i])\n",
        "        out[i] = damping_factor(e[i]) * scalar(1.0001)\n",
        ("tests/test_damping_load.py::test_the_material_tables_damping_factor_gives_the_dashpots_bits[cpu-float32]",),
    ),
    Fault(
        "the integration's check in one launch: the step before its count",
        "kernels/integrate.py",
        "        check_body(model, body_speed_limit, step[0] + 1, bodies, i, bad_step, body_peak_speed, too_fast)\n",
        "        check_body(model, body_speed_limit, step[0], bodies, i, bad_step, body_peak_speed, too_fast)\n",
        ("tests/test_simulation.py::test_nonfinite_state_names_step_and_body[cpu]",),
    ),
    Fault(
        "spread pairs skip the lanes' rest",
        "kernels/forces.py",
        "                p = p - s * wp.static(SPREAD_LANES - 1)\n",
        "                p = p - s * wp.static(SPREAD_LANES)\n",
        ("tests/test_pair_order.py::test_spread_pairs_give_the_same_bits[cpu-37-1000000000]",),
    ),
    Fault(
        "spread variant: launched over buffers too long to spread a pair",
        "src/polydem/simulation.py",
        "        if kernels.spread and not spread_fits(pairs.capacity, self.spread_threads):\n",
        "        if kernels.spread and not spread_fits(pairs.capacity, 10**9):\n",
        ("tests/test_pair_order.py::test_spread_variant_only_where_the_buffers_could_spread[cpu]",),
    ),
    Fault(
        "shared polygon buffer: a kept vertex not written",
        "kernels/geometry.py",
        "                                poly_rw(n_out, v, 1)\n",
        "                                poly_rw(n_out, prev, 1)\n",
        ("tests/test_pair_variants.py::test_shared_polygon_buffer_agrees_bit_for_bit[cpu-cube_rock-float32]",),
    ),
    Fault(
        "shared polygon buffer: Warp's own shared memory not counted",
        "kernels/geometry.py",
        "SHARED_POLY_BYTES = 48 * 1024 - 4 * SHARED_POLY_BLOCK\n",
        "SHARED_POLY_BYTES = 48 * 1024\n",
        ("tests/test_pair_variants.py::test_the_largest_shared_polygon_buffer_compiles_for_a_gpu",),
    ),
    Fault(
        "costly pairs: the touching ones of the last costly class not counted",
        "kernels/pairlist.py",
        "        below = 2 * (int(num_classes) - 1 - int(costly_from)) + 2\n",
        "        below = 2 * (int(num_classes) - 1 - int(costly_from)) + 1\n",
        ("tests/test_pair_order.py::test_spread_pairs_give_the_same_bits[cpu-10000000-55]",),
    ),
    Fault(
        "tunnelling limits: one code's limit given to every body",
        "src/polydem/scene/checks.py",
        "    if pairs.size == 1:\n",
        "    if pairs.size >= 1:\n",
        ("tests/test_build_vectorised.py::test_run_settings_and_tunnelling_limits_match_the_per_body_reference",),
    ),
    Fault(
        "damping loads never scale a dashpot",
        "kernels/forces.py",
        "    if load > wp.float32(DAMPING_SHARE):\n",
        "    if load > wp.float32(1.0e30):\n",
        ("tests/test_damping_load.py::test_a_pile_comes_to_rest_at_four_recommended_steps[cpu]",),
    ),
    Fault(
        "a ghost's damping load not taken from its owner",
        "kernels/ghosts.py",
        "        damping[i] = wp.float32(rows[k, 13])\n",
        "        damping[i] = damping[i]\n",
        (
            "tests/test_distributed.py::test_decomposed_run_is_the_undivided_run[cpu-box_pour_long-3000-0.004-2-50-True]",
        ),
    ),
    Fault(
        "mesh-wall candidates: a body's cells past those kept in its thread never listed",
        "kernels/meshwall.py",
        "                        if h >= LISTED_IN_REGISTERS:\n",
        "                        if h > LISTED_IN_REGISTERS:\n",
        ("tests/test_meshwall.py::test_candidate_list_gives_the_walks_bits[cpu-mixed]",),
    ),
    Fault(
        "joined mesh cells: their planes 1e-7 m out",
        "src/polydem/meshmerge.py",
        "        p[:, 3] -= p[:, :3] @ mid\n",
        "        p[:, 3] -= p[:, :3] @ mid - 1e-7\n",
        ("tests/test_meshwall.py::test_joined_flat_cells_give_the_triangles_contacts[cpu-float64]",),
    ),
    Fault(
        "gather: the damping loads without the plane walls' dashpots",
        "kernels/forces.py",
        "                if want_load and walls.turn[i, j] > C(0.0):\n",
        "                if want_load and walls.turn[i, j] > C(1.0e30):\n",
        ("tests/test_damping_load.py::test_the_damping_load_is_the_sum_of_the_contacts_dashpots[cpu-cube_drop]",),
    ),
    Fault(
        "initial overlaps on the device: a big body not first in its pairs",
        "kernels/initial_overlaps.py",
        "    if (shape_big[sb] != 0 and shape_big[sa] == 0) or (shape_big[sa] == shape_big[sb] and j < i):\n",
        "    if j < i:\n",
        ("tests/test_overlap_check.py::test_device_records_are_the_host_records[cpu-True]",),
    ),
    Fault(
        "split step: the first part's pairs by A's flag alone",
        "kernels/pairlist.py",
        "    elif body_first[pair_a[p]] + body_first[pair_b[p]] > 0:\n",
        "    elif body_first[pair_a[p]] > 0:\n",
        ("tests/test_split_step.py::test_split_step_is_the_step[cpu-box_pour-True-True]",),
    ),
)

# What the copy needs to run the tests from its own root; kernels/ goes to src/polydem/kernels alone.
COPIED = ("src", "tests", "scenes", "benchmarks", "pyproject.toml", "README.md")


def copy_tree(dest: Path) -> None:
    ignore = shutil.ignore_patterns("__pycache__", "*.pyc", "*.egg-info")
    # benchmarks/ for the scripts some tests build their scenes with (settle.py), not its recorded results
    ignore_results = shutil.ignore_patterns("__pycache__", "*.pyc", "*.egg-info", "results")
    for name in COPIED:
        src = ROOT / name
        if src.is_dir():
            shutil.copytree(src, dest / name, ignore=ignore_results if name == "benchmarks" else ignore)
        else:
            shutil.copy2(src, dest / name)
    target = dest / "src" / "polydem" / "kernels"
    if target.exists():
        sys.exit(f"mutations: {target.relative_to(dest)} exists in the source tree; the kernels layout changed")
    shutil.copytree(ROOT / "kernels", target, ignore=ignore)


def copied_path(path: str) -> str:
    """Where a file of the repository lies in the copy."""
    return "src/polydem/" + path if path.startswith("kernels/") else path


def child_env(copy: Path) -> dict:
    env = dict(os.environ)
    env["PYTHONPATH"] = os.pathsep.join([str(copy / "src"), *filter(None, [env.get("PYTHONPATH")])])
    env["POLYDEM_TEST_DEVICES"] = "cpu"
    env["PYTHONDONTWRITEBYTECODE"] = "1"
    return env


def check_imports(copy: Path, env: dict) -> None:
    """polydem and polydem.kernels (and a module of each) must come from the copy."""
    code = (
        "import polydem, polydem.kernels, polydem.kernels.forces, polydem.scene.walls, polydem.plots\n"
        "for m in (polydem, polydem.kernels, polydem.kernels.forces, polydem.scene.walls, polydem.plots):\n"
        "    print(m.__file__)\n"
    )
    out = subprocess.run([sys.executable, "-c", code], cwd=copy, env=env, capture_output=True, text=True)
    if out.returncode != 0:
        sys.exit(f"mutations: the copy does not import:\n{out.stderr}")
    for line in out.stdout.split():
        if not Path(line).resolve().is_relative_to(copy.resolve()):
            sys.exit(f"mutations: {line} is imported from outside the copy {copy}; the faults would not be tested")


def pytest(copy: Path, env: dict, tests, extra=()) -> tuple[int, str]:
    cmd = [sys.executable, "-m", "pytest", "-q", "-x", "-p", "no:cacheprovider", *extra, *tests]
    out = subprocess.run(cmd, cwd=copy, env=env, capture_output=True, text=True)
    return out.returncode, out.stdout + out.stderr


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--list", action="store_true", help="list the faults and their tests")
    parser.add_argument("--only", nargs="+", metavar="NAME", help="run only the faults whose name contains NAME")
    parser.add_argument("--keep", action="store_true", help="keep the temporary copy")
    args = parser.parse_args(argv)
    faults = [f for f in FAULTS if not args.only or any(n in f.name for n in args.only)]
    if args.list:
        for f in faults:
            print(f"{f.name}: {f.path}\n    " + "\n    ".join(f.tests))
        return 0
    if not faults:
        sys.exit("mutations: no fault matches --only")

    start = time.perf_counter()
    copy = Path(tempfile.mkdtemp(prefix="polydem-mutations-"))
    try:
        copy_tree(copy)
        env = child_env(copy)
        check_imports(copy, env)
        for f in faults:
            if (ROOT / f.path).read_text().count(f.old) != 1:
                sys.exit(
                    f"mutations: the text of fault '{f.name}' is not in {f.path} exactly once; update .ci/mutations.py "
                    f"to the code as it is now (the fault would otherwise test nothing):\n{f.old}"
                )

        # Baseline: every selected test passes on the unmutated copy.
        tests = list(dict.fromkeys(t for f in faults for t in f.tests))
        t0 = time.perf_counter()
        rc, log = pytest(copy, env, tests)
        took = time.perf_counter() - t0
        print(f"mutations: baseline, {len(tests)} tests on the unmutated copy: exit code {rc} ({took:.0f} s)")
        if rc != 0:
            print(log)
            print("mutations: the selected tests fail without any fault; fix them first")
            return 1

        survived, broken = [], []
        for f in faults:
            path = copy / copied_path(f.path)
            original = path.read_text()
            path.write_text(original.replace(f.old, f.new))
            t0 = time.perf_counter()
            try:
                rc, log = pytest(copy, env, f.tests)
            finally:
                path.write_text(original)
            took = time.perf_counter() - t0
            if rc == 1:
                failed = [line for line in log.splitlines() if line.startswith("FAILED")]
                print(f"mutations: caught   '{f.name}' ({took:.0f} s): {failed[0] if failed else 'a test failed'}")
            elif rc == 0:
                survived.append(f.name)
                print(f"mutations: SURVIVED '{f.name}' ({took:.0f} s): {', '.join(f.tests)} passed with the fault")
            else:
                broken.append(f.name)
                print(f"mutations: ERROR    '{f.name}' ({took:.0f} s): pytest exit code {rc}\n{log}")
        print(f"mutations: {len(faults) - len(survived) - len(broken)} of {len(faults)} faults caught "
              f"in {time.perf_counter() - start:.0f} s")  # fmt: skip
        if survived:
            print("mutations: faults no test caught: " + "; ".join(survived))
        if broken:
            print("mutations: faults whose tests did not run: " + "; ".join(broken))
        return 1 if survived or broken else 0
    finally:
        if args.keep:
            print(f"mutations: the copy is kept in {copy}")
        else:
            shutil.rmtree(copy, ignore_errors=True)


if __name__ == "__main__":
    sys.exit(main())
