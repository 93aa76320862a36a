"""Does a pile follow its step or its toe? One pour of time_to_settle.py to settled, with the resolved toe of
another step (BENCHMARKS.md section 24).

Under hertz the simulator continues the law below a toe volume V_c set per pair from the run's step
(``polydem.kernels.response.toe_volume``: its stiffness meets the pair's mass at TOE_OMEGA_DT e / dt, dt the larger
of the run's step and the recommended one since section 25). Here TOE_OMEGA_DT is multiplied by ``max(--dt-scale,
1) / --toe-step`` before any kernel is built, so that V_c is the one of ``--toe-step`` x the recommended step
while the run steps at ``--dt-scale`` x it: a pile that follows its
toe comes out as the run at ``--toe-step``'s, one that follows its step as its own. ``--no-damping-share`` also
takes the damping loads' scaling of the dashpots out (section 21b). A diagnostic: it changes module constants
of ``polydem.kernels`` in this process only, with a kernel cache of its own.

    python benchmarks/toe_swap.py --bodies 1000 --dt-scale 4 --toe-step 1        # 4 dt_rec with dt_rec's toe
    python benchmarks/toe_swap.py --bodies 1000 --dt-scale 1 --toe-step 4 --seed 1

Prints one JSON line (dt, steps, settle time, wall time, phi, Z, largest depth, energy balance) and writes it to
``--out``.
"""

import argparse
import json
import os
import sys
import tempfile

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--device", default="cpu")
    ap.add_argument("--bodies", type=int, default=1000)
    ap.add_argument("--k-factor", type=float, default=1.0, help="k = this x the volume rule's")
    ap.add_argument("--dt-scale", type=float, default=4.0, help="the step, x the recommended one")
    ap.add_argument("--toe-step", type=float, default=None, help="the toe of this x the recommended step")
    ap.add_argument("--no-damping-share", action="store_true", help="the damping loads never scale a dashpot")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--max-time", type=float, default=1.5)
    ap.add_argument("--out", default=None)
    args = ap.parse_args()
    if args.toe_step is not None and not args.toe_step > 0.0:
        sys.exit(f"toe_swap.py: --toe-step is a positive multiple of the recommended step, got {args.toe_step}")

    import warp as wp

    wp.config.quiet = True
    # V_c goes with (dt / TOE_OMEGA_DT)^(2 / (2 - m)), dt the larger of the step and dt_rec (Model.toe_dt): the toe
    # of T x dt_rec at a step of S x dt_rec takes max(S, 1) / T
    toe = 1.0 if args.toe_step is None else max(args.dt_scale, 1.0) / args.toe_step
    share = None if not args.no_damping_share else 1e30
    # Warp caches kernels by their source: the changed constants get a cache of their own.
    wp.config.kernel_cache_dir = os.path.join(tempfile.gettempdir(), f"polydem_toe_swap_{toe:g}_{share}")
    import polydem.kernels.forces as forces
    import polydem.kernels.response as response

    response.TOE_OMEGA_DT = response.TOE_OMEGA_DT * toe
    if share is not None:
        response.DAMPING_SHARE = forces.DAMPING_SHARE = share
    from time_to_settle import make_parser, run_size

    tts = make_parser().parse_args(
        ["--k-rule", "volume", "--speed-fraction", "off", "--max-time", str(args.max_time),
         "--k-factor", str(args.k_factor), "--seed", str(args.seed)]
    )  # fmt: skip
    wp.init()
    r = run_size(args.bodies, tts, wp.get_device(args.device), args.dt_scale)
    keys = ("dt", "settled", "settle_time_s", "steps", "wall_s", "packing_fraction", "coordination_number")
    keys += ("max_depth_fraction_of_edge", "energy_error_of_released")
    row = {k: r[k] for k in keys} | vars(args)
    print(json.dumps(row))
    if args.out:
        with open(args.out, "w") as f:
            json.dump(row, f, indent=1)


if __name__ == "__main__":
    main()
