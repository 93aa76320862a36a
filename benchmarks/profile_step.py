"""The step's pair kernel under Nsight Compute: what limits it, in counts per candidate pair.

Pours the settling benchmark's pile (benchmarks/settle.py's scene: 1 cm cubes, hertz, e = 0.5,
mu = 0.5) for ``--warmup-time`` simulated seconds, then profiles one launch of the kernel the step
actually runs (``pair_contact_kernel``, kernels/forces.py: geometry, law, damping, friction and the
wrench per candidate pair) with ``ncu``: duration, registers, achieved occupancy, executed FP32 and
FP64 instructions, local-memory (per-thread stack) bytes loaded and stored, and device-memory bytes.
Everything is divided by the candidate pairs of that step (the broad phase's ``pair_count``) and set
against the machine's ceilings (``benchmarks/pair_ceiling.py``: FP32 peak from SMs x lanes x clock,
bandwidth from a large device copy).

    python benchmarks/profile_step.py --device cuda:0 --bodies 100000 [--precision mixed]

Needs ``ncu`` on the PATH and permission to read the counters; without them it says so and reports
the timing only. Results: a table on stdout and JSON (``--out``, default
``benchmarks/results/profile_step_<device>.json``).
"""

import argparse
import ctypes
import json
import os
import shutil
import subprocess
import sys
import time

import numpy as np
import warp as wp

HERE = os.path.dirname(os.path.abspath(__file__))
sys.path.insert(0, HERE)

import pair_ceiling as pc  # noqa: E402
from _meta import run_meta  # noqa: E402
from settle import add_kernel_options, kernel_options, make_scene, scene_options  # noqa: E402

METRICS = [
    "gpu__time_duration.sum",
    "launch__registers_per_thread",
    "launch__block_size",
    "launch__grid_size",
    "sm__warps_active.avg.pct_of_peak_sustained_active",
    "smsp__inst_executed.sum",
    "smsp__sass_thread_inst_executed_op_fadd_pred_on.sum",
    "smsp__sass_thread_inst_executed_op_fmul_pred_on.sum",
    "smsp__sass_thread_inst_executed_op_ffma_pred_on.sum",
    "smsp__sass_thread_inst_executed_op_dadd_pred_on.sum",
    "smsp__sass_thread_inst_executed_op_dmul_pred_on.sum",
    "smsp__sass_thread_inst_executed_op_dfma_pred_on.sum",
    "dram__bytes_read.sum",
    "dram__bytes_write.sum",
    "l1tex__t_bytes_pipe_lsu_mem_local_op_ld.sum",
    "l1tex__t_bytes_pipe_lsu_mem_local_op_st.sum",
    "lts__t_bytes_equiv_l1sectormiss_pipe_lsu_mem_local_op_ld.sum",
    "smsp__thread_inst_executed_per_inst_executed.ratio",
]


def build(args, device):
    from polydem import Simulation

    options = scene_options(edge=0.01, precision=args.precision)
    scene, _ = make_scene(args.bodies, options, seed=args.seed)
    # Without the graph every kernel is its own launch, which ncu then finds by name.
    return Simulation(scene, device=device, use_graph=False, **kernel_options(args))


def child(args):
    """Under ncu: pour, then one profiled step (the profiler API brackets it)."""
    wp.config.quiet = True
    wp.init()
    device = wp.get_device(args.device)
    sim = build(args, device)
    sim.step(max(1, int(round(args.warmup_time / sim.dt))))
    wp.synchronize_device(device)
    cuda = ctypes.CDLL("libcuda.so.1")
    cuda.cuProfilerStart()
    sim.step(1)
    wp.synchronize_device(device)
    cuda.cuProfilerStop()
    pairs = int(sim.current_contacts.broadphase.pair_count.numpy()[0])
    with open(args.child_out, "w") as f:
        json.dump({"candidate_pairs": pairs, "contacts": int(len(sim.contacts()["volume"]))}, f)


def timing(args, device):
    """ms per step of the same pour with the graph on (median of chunks), for scale."""
    from polydem import Simulation

    options = scene_options(edge=0.01, precision=args.precision)
    scene, _ = make_scene(args.bodies, options, seed=args.seed)
    sim = Simulation(scene, device=device, **kernel_options(args))
    sim.step(max(1, int(round(args.warmup_time / sim.dt))))
    times = []
    for _ in range(5):
        wp.synchronize_device(device)
        t0 = time.perf_counter()
        sim.step(20)
        wp.synchronize_device(device)
        times.append((time.perf_counter() - t0) / 20)
    return float(np.median(times)) * 1e3


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--device", default="cuda:0")
    ap.add_argument("--bodies", type=int, default=100000, help="cubes in the pile")
    ap.add_argument("--warmup-time", type=float, default=0.1, help="simulated pour before the profiled step [s]")
    ap.add_argument("--precision", default="mixed", choices=("float32", "mixed", "float64"))
    ap.add_argument("--seed", type=int, default=0)
    add_kernel_options(ap)
    ap.add_argument("--out", default=None)
    ap.add_argument("--child-out", default=None, help=argparse.SUPPRESS)
    args = ap.parse_args()
    if args.child_out:
        child(args)
        return

    wp.config.quiet = True
    wp.init()
    device = wp.get_device(args.device)
    out = args.out or os.path.join(HERE, "results", f"profile_step_{device.alias.replace(':', '')}.json")
    record = {"meta": run_meta(device), "args": vars(args)}
    record["ms_per_step_graph"] = timing(args, device)
    record["peaks"] = pc.peaks(device)
    record["bandwidth"] = pc.copy_bandwidth(device)
    ncu = shutil.which("ncu")
    if not ncu:
        record["ncu"] = {"available": False, "reason": "ncu not on PATH"}
    else:
        child_out = os.path.join(os.path.dirname(os.path.abspath(out)), ".profile_step_child.json")
        cmd = [ncu, "--csv", "--print-units", "base", "--profile-from-start", "off"]
        cmd += ["--kernel-name", "regex:pair_contact_kernel", "--launch-count", "1", "--metrics", ",".join(METRICS)]
        cmd += [sys.executable, os.path.abspath(__file__), "--device", args.device, "--bodies", str(args.bodies)]
        cmd += ["--warmup-time", str(args.warmup_time), "--precision", args.precision, "--seed", str(args.seed)]
        cmd += ["--child-out", child_out]
        if args.max_registers is not None:
            cmd += ["--max-registers", str(args.max_registers)]
        proc = subprocess.run(cmd, capture_output=True, text=True, timeout=540)
        values = pc.parse_ncu_csv(proc.stdout)
        info = {"available": True, "command": " ".join(cmd), "metrics": values}
        if not values:
            text = proc.stdout + proc.stderr
            info["error"] = "ERR_NVGPUCTRPERM" if "ERR_NVGPUCTRPERM" in text else "no metrics parsed"
            info["output_tail"] = text[-3000:]
        elif os.path.exists(child_out):
            with open(child_out) as f:
                info.update(json.load(f))
            os.remove(child_out)
            n = max(info["candidate_pairs"], 1)
            g = values.get
            per = {
                "fp32_inst": sum(
                    g(f"smsp__sass_thread_inst_executed_op_{o}_pred_on.sum", 0.0) for o in ("fadd", "fmul", "ffma")
                )
                / n,
                "fp64_inst": sum(
                    g(f"smsp__sass_thread_inst_executed_op_{o}_pred_on.sum", 0.0) for o in ("dadd", "dmul", "dfma")
                )
                / n,
                "local_ld_bytes": g("l1tex__t_bytes_pipe_lsu_mem_local_op_ld.sum", 0.0) / n,
                "local_st_bytes": g("l1tex__t_bytes_pipe_lsu_mem_local_op_st.sum", 0.0) / n,
                "local_ld_l1_miss_bytes": g("lts__t_bytes_equiv_l1sectormiss_pipe_lsu_mem_local_op_ld.sum", 0.0) / n,
                "dram_bytes": (g("dram__bytes_read.sum", 0.0) + g("dram__bytes_write.sum", 0.0)) / n,
                "warp_inst": g("smsp__inst_executed.sum", 0.0) / n,
            }
            info["per_pair"] = per
            sec = g("gpu__time_duration.sum", 0.0) * 1e-9
            peaks = record["peaks"]
            if sec > 0:
                flops = (
                    g("smsp__sass_thread_inst_executed_op_fadd_pred_on.sum", 0.0)
                    + g("smsp__sass_thread_inst_executed_op_fmul_pred_on.sum", 0.0)
                    + 2 * g("smsp__sass_thread_inst_executed_op_ffma_pred_on.sum", 0.0)
                )
                info["pairs_per_s"] = n / sec
                if peaks.get("fp32_flops"):
                    info["fraction_of_fp32_peak"] = flops / sec / peaks["fp32_flops"]
                dram = (g("dram__bytes_read.sum", 0.0) + g("dram__bytes_write.sum", 0.0)) / sec
                info["fraction_of_bandwidth"] = dram / record["bandwidth"]["bytes_per_second"]
        record["ncu"] = info
    os.makedirs(os.path.dirname(os.path.abspath(out)), exist_ok=True)
    with open(out, "w") as f:
        json.dump(record, f, indent=1)
    info = record["ncu"]
    print(f"{args.bodies} cubes, {args.precision}, {device.name}: {record['ms_per_step_graph']:.3f} ms/step (graph)")
    if info.get("per_pair"):
        m = info["metrics"]
        print(
            f"pair_contact_kernel: {m.get('gpu__time_duration.sum', 0) * 1e-6:.3f} ms, {info['candidate_pairs']} "
            f"candidate pairs ({info['pairs_per_s']:.3g}/s), {m.get('launch__registers_per_thread')} registers, "
            f"{m.get('sm__warps_active.avg.pct_of_peak_sustained_active', 0):.1f}% warps active, "
            f"{100 * info.get('fraction_of_fp32_peak', 0):.2f}% of FP32 peak, "
            f"{100 * info.get('fraction_of_bandwidth', 0):.2f}% of bandwidth"
        )
        print("per candidate pair: " + ", ".join(f"{k} {v:.1f}" for k, v in info["per_pair"].items()))
    else:
        print(f"ncu: {info.get('reason') or info.get('error')}")
    print(f"wrote {out}")


if __name__ == "__main__":
    main()
