"""Pair kernel against the machine's ceiling: roofline fractions from measured counts.

Times the narrow-phase kernel (``kernels/narrowphase.py``) for cubes at 1% depth on the pair set of
``benchmarks/pair_kernel.py`` (imported: same shapes, depths, seed and half-separated mix), counts the
bytes per pair that the launch moves in device memory (from the dtypes of its argument arrays), and
on CUDA measures the machine's ceilings: FP32/FP64 peak from SM count x lanes x 2 x max clock, memory
bandwidth from a large device-to-device copy. The floating-point work per pair is measured, not
modelled: Nsight Compute (``ncu``, when on the PATH and allowed to read the counters) profiles one
launch and gives the executed FP32 add, mul and FMA instructions, DRAM bytes and local-memory bytes;
flops = fadd + fmul + 2 ffma. Without ncu the script reports the timing, the bytes and the ceilings
only.

    python benchmarks/pair_ceiling.py --device cuda:0     # GPU: ceilings, timing, ncu if present
    python benchmarks/pair_ceiling.py --device cpu        # bytes and the CPU timing only

Results: a table on stdout and JSON ``benchmarks/results/pair_ceiling_<device>.json``.
"""

import argparse
import csv
import io
import json
import os
import re
import shutil
import subprocess
import sys
import tempfile
import time

import numpy as np
import warp as wp

HERE = os.path.dirname(os.path.abspath(__file__))
sys.path.insert(0, HERE)

import pair_kernel as pk  # noqa: E402  (benchmarks/pair_kernel.py: pair generation and timing)
from _meta import run_meta  # noqa: E402

from polydem.shapeset import ShapeSet  # noqa: E402

RESULTS = os.path.join(HERE, "results")

# FP32 and FP64 lanes per SM by compute capability, and max SM clocks where nvidia-smi cannot say.
LANES = {(8, 0): (64, 32), (8, 6): (128, 2), (8, 7): (128, 2), (8, 9): (128, 2), (9, 0): (128, 64)}
KNOWN_MAX_CLOCK_MHZ = {"H100": 1980, "H200": 1980, "A100": 1410}


def io_bytes(shapes):
    """Bytes per pair the launch reads and writes in device memory, from the actual argument arrays."""
    scalar = shapes.scalar
    vec3 = wp.types.vector(3, scalar)
    tf = wp.types.transformation(scalar)
    dev = "cpu"  # only the dtypes matter
    inputs = {
        "pairs.shape_a": wp.zeros(1, dtype=int, device=dev),
        "pairs.shape_b": wp.zeros(1, dtype=int, device=dev),
        "pairs.pose_a": wp.zeros(1, dtype=tf, device=dev),
        "pairs.pose_b": wp.zeros(1, dtype=tf, device=dev),
    }
    outputs = {"pair_volume": wp.zeros(1, dtype=scalar, device=dev)}
    for k in pk.OVERLAP_OUTPUTS[1:]:
        outputs[k] = wp.zeros(1, dtype=vec3, device=dev)
    read = {k: a.strides[0] for k, a in inputs.items()}
    write = {k: a.strides[0] for k, a in outputs.items()}
    shape_arrays = {name: getattr(shapes, name) for name in ShapeSet.ARRAYS}
    shape_bytes = {k: int(a.size * wp.types.type_size_in_bytes(a.dtype)) for k, a in shape_arrays.items()}
    return {
        "precision": shapes.precision,
        "read_per_pair": read,
        "write_per_pair": write,
        "bytes_per_pair": sum(read.values()) + sum(write.values()),
        "shape_data_bytes_total": sum(shape_bytes.values()),
        "shape_data_bytes": shape_bytes,
        "note": "the overflow flag is written (atomically) only on a polygon-buffer overflow; not counted",
    }


# ---------------------------------------------------------------------------------------------
# Ceilings (CUDA only)


def max_clock(dev):
    """Max SM clock [MHz] and where it came from."""
    smi = shutil.which("nvidia-smi")
    if smi:
        try:
            out = subprocess.run(
                [smi, "--query-gpu=clocks.max.sm,name", "--format=csv,noheader,nounits"],
                capture_output=True,
                text=True,
                timeout=30,
            ).stdout.strip()
            line = out.splitlines()[dev.ordinal if len(out.splitlines()) > dev.ordinal else 0]
            mhz = float(line.split(",")[0])
            return mhz, f"nvidia-smi clocks.max.sm ({line.strip()})"
        except Exception as e:  # fall back to the table
            err = repr(e)
    else:
        err = "nvidia-smi not found"
    for key, mhz in KNOWN_MAX_CLOCK_MHZ.items():
        if key in dev.name:
            return float(mhz), f"known value for {key} ({err})"
    return None, f"unknown ({err})"


def peaks(dev):
    arch = getattr(dev, "arch", None)
    sms = getattr(dev, "sm_count", None)
    cc = (arch // 10, arch % 10) if arch else None
    fp32_lanes, fp64_lanes = LANES.get(cc, (128, None))
    mhz, clock_source = max_clock(dev)
    out = {
        "arch": arch,
        "sm_count": sms,
        "fp32_lanes_per_sm": fp32_lanes,
        "fp64_lanes_per_sm": fp64_lanes,
        "lanes_source": "table by compute capability" if cc in LANES else "default 128 FP32 (unknown arch)",
        "max_sm_clock_mhz": mhz,
        "clock_source": clock_source,
    }
    if sms and mhz:
        out["fp32_flops"] = sms * fp32_lanes * 2 * mhz * 1e6
        out["fp32_instr_per_s"] = sms * fp32_lanes * mhz * 1e6
        out["fp64_flops"] = sms * fp64_lanes * 2 * mhz * 1e6 if fp64_lanes else None
    return out


def copy_bandwidth(dev, nbytes=1 << 29, repeats=10):
    """Bytes read + written per second of a large device-to-device wp.copy, median of `repeats`."""
    n = nbytes // 4
    src = wp.zeros(n, dtype=wp.float32, device=dev)
    dst = wp.empty(n, dtype=wp.float32, device=dev)
    wp.copy(dst, src)
    wp.synchronize_device(dev)
    times = []
    for _ in range(repeats):
        try:
            e0 = wp.Event(dev, enable_timing=True)
            e1 = wp.Event(dev, enable_timing=True)
            with wp.ScopedDevice(dev):
                wp.record_event(e0)
                wp.copy(dst, src)
                wp.record_event(e1)
            wp.synchronize_device(dev)
            times.append(wp.get_event_elapsed_time(e0, e1) / 1e3)
            how = "CUDA events"
        except Exception:
            t0 = time.perf_counter()
            wp.copy(dst, src)
            wp.synchronize_device(dev)
            times.append(time.perf_counter() - t0)
            how = "host clock"
    del src, dst
    t = float(np.median(times))
    return {"bytes_per_copy": 2 * nbytes, "seconds": t, "bytes_per_second": 2 * nbytes / t, "timing": how}


# ---------------------------------------------------------------------------------------------
# Nsight Compute (CUDA only, if installed)

NCU_METRICS = [
    "smsp__sass_thread_inst_executed_op_fadd_pred_on.sum",
    "smsp__sass_thread_inst_executed_op_fmul_pred_on.sum",
    "smsp__sass_thread_inst_executed_op_ffma_pred_on.sum",
    "dram__bytes_read.sum",
    "dram__bytes_write.sum",
    "l1tex__t_bytes_pipe_lsu_mem_local_op_ld.sum",
    "l1tex__t_bytes_pipe_lsu_mem_local_op_st.sum",
]
NCU_EXTRA = [
    "gpu__time_duration.sum",
    "launch__registers_per_thread",
    "sm__warps_active.avg.pct_of_peak_sustained_active",
    "smsp__inst_executed.sum",
    "lts__t_bytes_equiv_l1sectormiss_pipe_lsu_mem_local_op_ld.sum",
]


def ncu_child(path, device):
    """Child process under ncu: one launch of the float32 kernel on the saved poses."""
    data = np.load(path)
    shapes = ShapeSet([pk.shape_library()["cube"]], device=device, precision="float32")
    pk.time_kernel(shapes, data["pa"].astype(np.float64), data["pb"].astype(np.float64), 0)


def run_ncu(pa, pb, dev, timeout=300):
    ncu = shutil.which("ncu")
    if not ncu:
        return {"available": False, "reason": "ncu not on PATH"}
    tmp = tempfile.mkdtemp(prefix="pair_ceiling_")
    path = os.path.join(tmp, "poses.npz")
    np.savez(path, pa=pa.astype(np.float32), pb=pb.astype(np.float32))
    out = {"available": True, "ncu": ncu, "pairs": len(pa)}
    for metrics in (NCU_METRICS + NCU_EXTRA, NCU_METRICS):
        cmd = [ncu, "--csv", "--print-units", "base", "--kernel-name", "regex:overlap_kernel", "--launch-count", "1"]
        cmd += ["--metrics", ",".join(metrics), sys.executable, os.path.abspath(__file__)]
        cmd += ["--device", dev.alias, "--ncu-child", path]
        out["command"] = " ".join(cmd)
        try:
            proc = subprocess.run(cmd, capture_output=True, text=True, timeout=timeout)
        except Exception as e:
            out["error"] = repr(e)
            break
        text = proc.stdout + "\n" + proc.stderr
        values = parse_ncu_csv(proc.stdout)
        if values:
            out["metrics"] = values
            out.pop("error", None)
            break
        out["returncode"] = proc.returncode
        out["error"] = (
            "ERR_NVGPUCTRPERM (no permission for GPU performance counters)"
            if "ERR_NVGPUCTRPERM" in text
            else "no metrics parsed"
        )
        out["output_tail"] = text[-3000:]
        if "ERR_NVGPUCTRPERM" in text:
            break
    shutil.rmtree(tmp, ignore_errors=True)
    if "metrics" in out:
        m = out["metrics"]
        n = len(pa)
        per = {k: v / n for k, v in m.items() if not k.startswith(("launch__", "sm__warps", "gpu__time"))}
        out["per_pair"] = per
        get = per.get
        if all(get(k) is not None for k in NCU_METRICS[:3]):
            out["per_pair"]["fp32_fadd_fmul_ffma"] = sum(get(k) for k in NCU_METRICS[:3])
            out["per_pair"]["flops_fadd_fmul_2ffma"] = (
                get(NCU_METRICS[0]) + get(NCU_METRICS[1]) + 2 * get(NCU_METRICS[2])
            )
        if get("dram__bytes_read.sum") is not None and get("dram__bytes_write.sum") is not None:
            out["per_pair"]["dram_bytes"] = get("dram__bytes_read.sum") + get("dram__bytes_write.sum")
    return out


def parse_ncu_csv(text):
    """{metric: value} from ncu --csv output (rows: ..., "Metric Name", "Metric Unit", "Metric Value")."""
    lines = [line for line in text.splitlines() if line.startswith('"')]
    if not lines:
        return {}
    values = {}
    for row in csv.DictReader(io.StringIO("\n".join(lines))):
        name, value = row.get("Metric Name"), row.get("Metric Value")
        if not name or value is None:
            continue
        try:
            values[name] = float(re.sub(r"[,\s]", "", value))
        except ValueError:
            continue
    return values


# ---------------------------------------------------------------------------------------------


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--device", default=None, help="Warp device (default: Warp's default)")
    ap.add_argument(
        "--pairs", type=int, default=None, help="pairs per set (default as pair_kernel.py: 2^20 GPU, 4096 CPU)"
    )
    ap.add_argument("--repeats", type=int, default=None, help="timed launches (default 20 GPU, 5 CPU)")
    ap.add_argument("--ncu-pairs", type=int, default=1 << 20, help="pairs in the profiled launch")
    ap.add_argument("--no-ncu", action="store_true")
    ap.add_argument("--ncu-child", default=None, help=argparse.SUPPRESS)
    ap.add_argument("--out", default=None, help="JSON (default benchmarks/results/pair_ceiling_<device>.json)")
    args = ap.parse_args()

    wp.config.quiet = True
    wp.init()
    dev = wp.get_device(args.device)
    if args.ncu_child:
        ncu_child(args.ncu_child, dev)
        return
    n = args.pairs or (1 << 20 if dev.is_cuda else 4096)
    repeats = args.repeats or (20 if dev.is_cuda else 5)
    out = args.out or os.path.join(RESULTS, f"pair_ceiling_{dev.alias.replace(':', '')}.json")
    record = {"meta": run_meta(dev), "config": {k: v for k, v in vars(args).items() if k not in ("out", "ncu_child")}}
    record["config"]["pairs"] = n
    t_start = time.perf_counter()

    def save():
        os.makedirs(os.path.dirname(os.path.abspath(out)), exist_ok=True)
        tmp = out + ".tmp"
        with open(tmp, "w") as fh:
            json.dump(record, fh, indent=1)
        os.replace(tmp, out)

    lib = pk.shape_library()
    print(f"pair kernel against the ceiling on {dev.name} ({dev.alias}), Warp {wp.config.version}")
    shapes32 = ShapeSet([lib["cube"]], device=dev, precision="float32")
    shapes64 = ShapeSet([lib["cube"]], device=dev, precision="float64")
    record["bytes"] = {"float32": io_bytes(shapes32), "float64": io_bytes(shapes64)}
    b32 = record["bytes"]["float32"]["bytes_per_pair"]
    print(
        f"bytes per pair in device memory: float32 {b32}, float64 {record['bytes']['float64']['bytes_per_pair']}"
        f" (shape data, shared: {record['bytes']['float32']['shape_data_bytes_total']} B for one cube, float32)"
    )

    pa, pb = pk.make_pairs(lib["cube"], n, 0.01, np.random.default_rng(12345), dev)
    t, _ = pk.time_kernel(shapes32, pa, pb, repeats)
    pairs_s = n / t
    timing = {"shape": "cube", "depth": 0.01, "precision": "float32", "pairs": n, "repeats": repeats}
    timing.update({"seconds": t, "pairs_per_second": pairs_s, "bytes_per_second": b32 * pairs_s})
    record["timing"] = timing
    save()
    print(f"cube 1% float32: {pairs_s / 1e6:.1f} Mpairs/s ({t / n * 1e9:.2f} ns/pair, median of {repeats})")

    roof = {}
    if not dev.is_cuda:
        reason = "CPU device: no GPU ceilings and no Nsight Compute counts (run with --device cuda:0)"
        record["roofline"] = {"peaks": None, "bandwidth": None, "reason": reason}
        record["ncu"] = {"available": False, "reason": reason}
        print(reason)
    else:
        roof["peaks"] = pk_ = peaks(dev)
        try:
            roof["bandwidth"] = copy_bandwidth(dev)
        except Exception as e:
            roof["bandwidth"] = None
            roof["bandwidth_error"] = repr(e)
        bw = (roof.get("bandwidth") or {}).get("bytes_per_second")
        if bw:
            roof["bandwidth_fraction"] = timing["bytes_per_second"] / bw
            roof["pairs_per_second_bound_bandwidth"] = bw / b32
        print(
            f"peaks: {pk_.get('sm_count')} SMs x {pk_['fp32_lanes_per_sm']} FP32 lanes x 2"
            f" x {pk_['max_sm_clock_mhz']} MHz ({pk_['clock_source']}) = {(pk_.get('fp32_flops') or 0) / 1e12:.1f}"
            f" TFLOP/s FP32, {(pk_.get('fp64_flops') or 0) / 1e12:.1f} FP64; copy bandwidth {(bw or 0) / 1e12:.2f} TB/s"
        )
        if args.no_ncu:
            record["ncu"] = nc = {"available": False, "reason": "--no-ncu"}
        else:
            m = min(args.ncu_pairs, n)
            half = n // 2
            rows = np.concatenate([np.arange(m // 2), half + np.arange(m - m // 2)])
            record["ncu"] = nc = run_ncu(pa[rows], pb[rows], dev)
        per = nc.get("per_pair", {})
        fpp = per.get("flops_fadd_fmul_2ffma")
        if fpp and pk_.get("fp32_flops"):
            timing["flops_per_pair"] = fpp
            timing["flops_per_second"] = fpp * pairs_s
            timing["arithmetic_intensity"] = fpp / b32
            roof["fp32_peak_fraction"] = timing["flops_per_second"] / pk_["fp32_flops"]
            roof["pairs_per_second_bound_fp32"] = pk_["fp32_flops"] / fpp
            if bw:
                roof["machine_balance_flops_per_byte"] = balance = pk_["fp32_flops"] / bw
                ai = timing["arithmetic_intensity"]
                roof["verdict"] = (
                    f"arithmetic intensity {ai:.1f} flop/B vs machine balance {balance:.1f}:"
                    f" {'compute' if ai > balance else 'memory'}-bound by the roofline; reached"
                    f" {roof['fp32_peak_fraction']:.1%} of FP32 peak and {roof['bandwidth_fraction']:.1%} of bandwidth"
                )
        for key, label in (
            ("fp32_peak_fraction", "fraction of FP32 peak (ncu flops)"),
            ("bandwidth_fraction", "fraction of copy bandwidth"),
            ("pairs_per_second_bound_fp32", "pairs/s bound by FP32 peak"),
            ("pairs_per_second_bound_bandwidth", "pairs/s bound by bandwidth"),
        ):
            if key in roof:
                v = roof[key]
                print(f"  {label:<40}{v:.3%}" if "fraction" in key else f"  {label:<40}{v:.3g}")
        if "verdict" in roof:
            print("  " + roof["verdict"])
        if per:
            print("ncu, per pair: " + ", ".join(f"{k} {v:.4g}" for k, v in per.items()))
        else:
            print(f"ncu: {nc.get('reason') or nc.get('error')}")
        record["roofline"] = roof
    record["meta"]["total_s"] = time.perf_counter() - t_start
    save()
    print(f"wrote {out} ({record['meta']['total_s']:.0f} s)")


if __name__ == "__main__":
    main()
