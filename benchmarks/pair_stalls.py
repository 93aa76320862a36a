"""Where a pair's latency goes: Nsight Compute's warp-state sampling of the overlap kernel, by reason and by line.

At small sizes the step waits on one pair's latency (BENCHMARKS.md sections 27b, 30: a cube pair alone 85 us on an
H200, 53 us of it the set-up). This script launches the engine's overlap kernel (the pair kernel's geometry, as
``pair_latency.py`` does) under ``ncu`` with its warp-state statistics and its per-instruction sampling, the
kernel compiled with line information (``wp.config.lineinfo``: Warp's ``#line`` directives name the Python lines
of kernels/geometry.py), and reports:

* the share of the sampled warp states by stall reason (long scoreboard: a wait on global or local memory; wait: a
  fixed-latency dependency; short scoreboard: shared memory and special functions; ...);
* the source lines with the most samples, from ncu's source page.

Each case is one launch: ``one`` (a single touching pair), ``spreadN`` (N touching pairs one to a warp),
``packedN`` (N touching pairs, 32 to a warp) of the overlap kernel, each shape of ``--shapes``; or ``pileN``: the
step's pair kernel and gather kernel (``--pile-kernels``) in time_to_settle.py's pour of N grains
(``--pile-shapes``, 4 dt_rec, the volume rule's k, the default kernels), ``--pile-steps`` steps in (the launches
before it run unprofiled, without graphs). The reports (``.ncu-rep``), ncu's CSV pages and a JSON summary go to
``--out``. Needs ``ncu`` on the PATH and permission to read the GPU's counters; without them it says so and
stops.

    python benchmarks/pair_stalls.py --device cuda:0 --shapes cube,rock20 --cases one,spread1024,pile1000 --out DIR
"""

import argparse
import json
import os
import re
import shutil
import subprocess
import sys

import numpy as np
import warp as wp

HERE = os.path.dirname(os.path.abspath(__file__))
sys.path.insert(0, HERE)
from _meta import run_meta  # noqa: E402
from pair_kernel import make_pairs, shape_library, time_kernel  # noqa: E402
from pair_latency import spread  # noqa: E402
from sass_lines import attribute, read_disassembly, read_page, table  # noqa: E402

from polydem.shapeset import ShapeSet  # noqa: E402

SECTIONS = ("LaunchStats", "Occupancy", "SpeedOfLight", "WarpStateStats", "SourceCounters")
# ncu locks the clocks (to base, by default): cycles, not the duration, compare with a run's events
SUMMARY = ("Elapsed Cycles", "SM Frequency", "Duration", "Warp Cycles Per Issued Instruction", "Executed Ipc Active")


def case_kind(case):
    """("one", 1), ("spread"|"packed"|"pile", N) of a case's name."""
    kind = re.fullmatch(r"(one)|(spread|packed|pile)(\d+)", case)
    if kind is None:
        raise SystemExit(f"pair_stalls: unknown case {case!r}: one, spreadN, packedN (N touching pairs) or pileN")
    return ("one", 1) if kind.group(1) else (kind.group(2), int(kind.group(3)))


def case_pairs(shape, case, depth, device):
    """The poses (xyz, xyzw float64) of one case's pairs: ``one``, ``spreadN`` or ``packedN``."""
    n = case_kind(case)[1]
    pa, pb = make_pairs(shape, 2 * max(n, 32), depth, np.random.default_rng(7), device)
    pa, pb = pa[:n], pb[:n]  # the touching half
    return spread(pa, pb, 32) if case.startswith("spread") else (pa, pb)


def pile_child(args, n):
    """Under ncu: time_to_settle.py's pour of ``n`` grains, ``--pile-steps`` steps and a few more."""
    from time_to_settle import default_pour

    sim = default_pour(n, args.device, args.pile_shapes, use_graph=False)
    sim.step(args.pile_steps + 3)
    wp.synchronize_device(sim.device)


def child(args):
    """Under ncu: the launches of one case (the first compiles and warms up; ncu profiles a later one)."""
    wp.config.quiet = True
    wp.config.lineinfo = True
    kind, n = case_kind(args.case)
    if kind == "pile":
        pile_child(args, n)
        return
    data = np.load(args.child)
    shape = shape_library()[args.shapes]
    shapes = ShapeSet([shape], device=args.device, precision="float32")
    time_kernel(shapes, data["pa"], data["pb"], 3, pose_scalar=wp.float64, events=True)


def ncu_csv(ncu, report, *page):
    """Rows of one of ncu's CSV pages of ``report`` (a list of dicts), and the text."""
    proc = subprocess.run([ncu, "-i", report, "--csv", *page], capture_output=True, text=True, timeout=600)
    text = proc.stdout
    _, rows = read_page(text)  # the source page names its kernel on a line of its own above the header
    return rows, text + proc.stderr


def number(value):
    try:
        return float(str(value).replace(",", ""))
    except ValueError:
        return None


STALL_METRIC = re.compile(
    r"smsp__(pcsamp_warps|average_warps|average_warp_latency)_issue_stalled_(\w+?)"
    r"(_per_issue_active\.ratio|_per_warp_active\.pct|\.sum|\.ratio)?"
)


def stall_shares(raw_rows):
    """{reason: share} of the warps' stalls from the raw page: the sampled counts (smsp__pcsamp_warps_issue_stalled_*)
    where ncu gives them, else WarpStateStats' cycles a warp spent stalled per issued instruction, by reason."""
    families = {}
    for row in raw_rows:
        for key, value in row.items():
            found = STALL_METRIC.fullmatch(key or "")
            v = number(value)
            if found is None or v is None or found.group(2).endswith("not_issued"):
                continue
            families.setdefault(found.group(1), {})[found.group(2)] = v
    counts = families.get("pcsamp_warps") or families.get("average_warps") or families.get("average_warp_latency") or {}
    total = sum(counts.values())
    return {k: v / total for k, v in sorted(counts.items(), key=lambda kv: -kv[1])} if total else {}


def top_lines(source_rows, top):
    """The source page's rows with the most samples: (samples, share, location, source text)."""
    if not source_rows:
        return []
    keys = [k for k in source_rows[0] if k]
    sample_key = next((k for k in keys if "Sampling" in k and "All" in k), None)
    sample_key = sample_key or next((k for k in keys if "Samples" in k or "Sampling" in k), None)
    if sample_key is None:
        return []
    text_key = next((k for k in keys if k.strip() in ("Source", "Source Line")), keys[1] if len(keys) > 1 else keys[0])
    where_key = next((k for k in keys if k.strip() in ("#", "Line", "Address", "Line Number")), keys[0])
    rows = [(number(r.get(sample_key)) or 0.0, r.get(where_key, ""), (r.get(text_key) or "").strip())
            for r in source_rows]  # fmt: skip
    total = sum(s for s, _, _ in rows) or 1.0
    rows.sort(key=lambda r: -r[0])
    return [{"samples": s, "share": s / total, "at": w, "source": t[:160]} for s, w, t in rows[:top] if s > 0]


def profile(ncu, stem, kernel, skip, child_args, args):
    """One launch of ``kernel`` (a regex) after ``skip`` others, under ncu, in a child running this script with
    ``child_args``; the report at ``stem``.ncu-rep, its pages as CSV beside it. The summary as a dict."""
    cmd = [ncu, "-f", "-o", stem, "--target-processes", "all", "--import-source", "yes",
           "--warp-sampling-interval", args.sampling_interval,
           "--kernel-name", kernel, "--launch-skip", str(skip), "--launch-count", "1"]  # fmt: skip
    for section in SECTIONS:
        cmd += ["--section", section]
    cmd += [sys.executable, os.path.abspath(__file__), *child_args]
    proc = subprocess.run(cmd, capture_output=True, text=True, timeout=900)
    entry = {"command": " ".join(cmd)}
    report = stem + ".ncu-rep"
    if proc.returncode != 0 or not os.path.exists(report):
        entry["error"] = f"rc {proc.returncode}: " + (proc.stdout + proc.stderr)[-3000:]
        return entry
    raw, raw_text = ncu_csv(ncu, report, "--page", "raw")
    details, details_text = ncu_csv(ncu, report, "--page", "details")
    for label, page in (("sass", "sass"), ("python", "cuda")):
        rows, text = ncu_csv(ncu, report, "--page", "source", "--print-source", page)
        if not rows and label == "sass":  # an ncu without --print-source: its source page as it prints it
            rows, text = ncu_csv(ncu, report, "--page", "source")
        with open(f"{stem}_source_{label}.csv", "w") as f:
            f.write(text)
        entry[f"top_{label}"] = top_lines(rows, args.top)
    entry.update(python_lines(stem, args))
    with open(stem + "_raw.csv", "w") as f:
        f.write(raw_text)
    with open(stem + "_details.csv", "w") as f:
        f.write(details_text)
    entry["stall_shares"] = stall_shares(raw)
    for row in details:
        if row.get("Metric Name") in SUMMARY:
            entry[row["Metric Name"]] = f"{row.get('Metric Value')} {row.get('Metric Unit', '')}".strip()
    return entry


def find_cubin(kernel_name, cache_dir):
    """The cubin in Warp's kernel cache that holds ``kernel_name`` (the newest), or None."""
    found = []
    for root, _, files in os.walk(cache_dir):
        for name in files:
            if name.endswith(".cubin"):
                path = os.path.join(root, name)
                with open(path, "rb") as f:
                    if kernel_name.encode() in f.read():
                        found.append(path)
    return max(found, key=os.path.getmtime) if found else None


def python_lines(stem, args):
    """The SASS page's samples and instructions by Python line and function (sass_lines.py), from the profiled
    kernel's cubin in Warp's kernel cache disassembled with nvdisasm -gi (kept as ``stem``.sass); {} without
    nvdisasm or the cubin."""
    tool = shutil.which("nvdisasm") or "/usr/local/cuda/bin/nvdisasm"
    try:
        with open(f"{stem}_source_sass.csv") as f:
            kernel, rows = read_page(f.read())
    except OSError:
        return {}
    cubin = find_cubin(kernel, wp.config.kernel_cache_dir) if kernel and rows else None
    if cubin is None or not os.path.exists(tool):
        return {"lines_missing": f"cubin {cubin}, nvdisasm {tool if os.path.exists(tool) else 'absent'}"}
    text = subprocess.run([tool, "-gi", "-c", cubin], capture_output=True, text=True, timeout=600).stdout
    with open(stem + ".sass", "w") as f:
        f.write(text)
    roots = [os.path.join(HERE, "..", "kernels"), os.path.join(HERE, "..", "src", "polydem")]
    _, by_line, by_def, differ = attribute(read_disassembly(text), kernel, rows, "inner", roots)
    return {"opcodes_differ": differ, "by_line": table(by_line, args.top), "by_function": table(by_def, args.top)}


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--device", default="cuda:0")
    ap.add_argument("--shapes", default="cube,rock20")
    ap.add_argument("--cases", default="one,spread1024", help="one, spreadN, packedN")
    ap.add_argument("--depth", type=float, default=0.01, help="depth of the touching pairs (fraction of the size)")
    ap.add_argument("--top", type=int, default=30, help="source lines to report")
    ap.add_argument("--sampling-interval", default="0", help="ncu's: 0 samples every 2^5 cycles")
    ap.add_argument("--out", default=os.path.join(HERE, "results", "issue27", "pair_stalls"))
    ap.add_argument("--pile-shapes", default="cube", help="the pileN cases' grains: cube or mixed")
    ap.add_argument(
        "--pile-steps", type=int, default=6000, help="the pileN cases' profiled step (6,720 settle 1e3 cubes)"
    )
    ap.add_argument("--pile-kernels", default="pair_contact_kernel,gather_kernel", help="the pileN cases' kernels")
    ap.add_argument("--child", help=argparse.SUPPRESS)
    ap.add_argument("--case", help=argparse.SUPPRESS)
    args = ap.parse_args()
    if args.child:
        child(args)
        return
    ncu = shutil.which("ncu") or next(
        (p for p in ("/usr/local/cuda/bin/ncu", "/opt/nvidia/nsight-compute/ncu") if os.path.exists(p)), None
    )
    if ncu is None:
        sys.exit("pair_stalls: ncu (Nsight Compute's command line) is not on the PATH; it runs where the CUDA "
                 "toolkit is installed with a GPU")  # fmt: skip
    wp.config.quiet = True
    dev = wp.get_device(args.device)
    if not dev.is_cuda:
        sys.exit(f"pair_stalls: --device {args.device} is not a CUDA device; ncu samples GPU kernels only")
    os.makedirs(args.out, exist_ok=True)
    lib = shape_library()
    record = {"meta": run_meta(dev), "args": vars(args), "cases": []}
    runs = []
    for case in args.cases.split(","):
        if case_kind(case)[0] == "pile":
            runs += [(args.pile_shapes, case, kernel) for kernel in args.pile_kernels.split(",")]
        else:
            runs += [(name, case, "overlap_kernel") for name in args.shapes.split(",")]
    for name, case, kernel_name in runs:
        stem = os.path.join(args.out, f"{name}_{case}")
        child_args = ["--case", case, "--device", args.device]
        if case_kind(case)[0] == "pile":
            threads = None
            stem += f"_{kernel_name}"
            # one launch of each a step (a step whose lists are rebuilt launches them once too)
            kernel, skip = f"regex:{kernel_name}", args.pile_steps
            child_args += ["--child", "-", "--pile-shapes", name, "--pile-steps", str(args.pile_steps)]
        else:
            pa, pb = case_pairs(lib[name], case, args.depth, dev)
            threads = len(pa)
            np.savez(stem + "_poses.npz", pa=pa, pb=pb)
            kernel, skip = "regex:overlap_kernel", 1
            child_args += ["--child", stem + "_poses.npz", "--shapes", name]
        entry = {"shape": name, "case": case, "kernel": kernel_name, "threads": threads}
        entry.update(profile(ncu, stem, kernel, skip, child_args, args))
        record["cases"].append(entry)
        if "error" in entry:
            print(f"{name} {case} {kernel_name}: ncu failed:\n{entry['error'][-800:]}")
            continue
        figures = [f"{k} {entry[k]}" for k in SUMMARY if k in entry]
        print(f"== {name} {case} {kernel_name} ({threads or 'the step'} threads): " + ", ".join(figures))
        for reason, share in list(entry["stall_shares"].items())[:8]:
            print(f"   {reason:<28s} {share:6.1%}")
        for e in entry.get("by_function", [])[:10]:
            print(f"   def    {e['samples']:6.1%} {e['instructions']:6.1%} instr. {e['at'][0]}:{e['at'][1]}")
        for e in entry.get("by_line", [])[:15]:
            at = f"{os.path.basename(e['at'][0])}:{e['at'][1]}"
            print(f"   line   {e['samples']:6.1%} {e['instructions']:6.1%} instr. {at}")
        for label in ("python", "sass"):
            for line in entry[f"top_{label}"][:12]:
                print(f"   {label:6s} {line['share']:6.1%} {line['at']:>8} {line['source'][:90]}")
    path = os.path.join(args.out, "pair_stalls.json")
    with open(path, "w") as f:
        json.dump(record, f, indent=1)
    print(f"wrote {path}")


if __name__ == "__main__":
    main()
