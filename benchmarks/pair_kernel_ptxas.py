"""Registers, stack frame and spills of the pair kernels, from ptxas: no GPU needed.

Warp generates the CUDA source and compiles it to PTX with its NVRTC (sm_90 by default); ptxas -v
then reports, per kernel, the registers per thread and the per-thread stack frame (the local
memory that holds the polygon, plane and face buffers) and spill bytes. Static figures: they say
what each thread holds, not how often it is touched (ncu on a GPU measures the traffic).

    python benchmarks/pair_kernel_ptxas.py --shapes cube,rock20 --precisions mixed
    python benchmarks/pair_kernel_ptxas.py --ptx-out /tmp/ptx_new   # then the same in the old tree, diff -r

``--ptx-out`` writes each kernel's PTX without comments, line records and hashes: two trees whose texts agree
compile the same code (how a change that should not touch the default kernels is checked; BENCHMARKS.md 29).
``--shared-poly`` and ``--lanes`` add the variants of section 29.

Needs ptxas on the PATH (the CUDA toolkit). When ptxas is older than Warp's NVRTC, the PTX's
.version line is lowered to --ptx-version (the kernels use no newer PTX feature). The pair-kernel
variants of BENCHMARKS.md section 7c live at the git tag ``pair-variants-7c``, where this script
takes ``--variants``; the clip layouts of issue 27 (section 14) at the tag ``clip-layouts-27``, where
it takes ``--layouts``.
"""

import argparse
import glob
import os
import re
import subprocess
import tempfile

import warp as wp
from polydem.kernels.forces import make_contact_kernels
from polydem.kernels.narrowphase import NARROWPHASE_BLOCK_DIM, make_narrowphase

from polydem import ConvexShape
from polydem.shapeset import ShapeSet

SHAPES = {
    "cube": lambda: ConvexShape.box(1.0),
    "rock20": lambda: ConvexShape.rock(n_points=20, size=1.0, seed=1),
    "hull64": lambda: ConvexShape.rock(n_points=64, size=1.0, seed=2),
}


def normalised_ptx(ptx):
    """PTX without its comments, source lines and file table, and with Warp's hashes in names replaced: the same text
    for the same code from two trees (``--ptx-out``)."""
    keep = (line for line in ptx.splitlines() if not line.lstrip().startswith(("//", ".loc", ".file")))
    return re.sub(r"_[0-9a-f]{7,16}", "_H", "\n".join(keep)) + "\n"


def ptxas_stats(kernel, arch, ptx_version, ptx_out=None):
    """ptxas -v figures of one kernel's module: registers, stack frame, spill stores and loads, static shared memory
    [bytes]. ``ptx_out``: also write its normalised PTX there."""
    module = kernel.module
    with tempfile.TemporaryDirectory() as tmp:
        # the block the pair kernels launch with: Warp sizes its static tile storage (one word a thread) by it
        options = module.resolve_options(wp.config, block_dim=NARROWPHASE_BLOCK_DIM)
        module._compile(device=None, output_dir=tmp, output_arch=arch, use_ptx=True, options=options)
        (path,) = glob.glob(os.path.join(tmp, "*.ptx"))
        with open(path, "rb") as f:
            ptx = f.read().replace(b"\0", b"").decode()
        if ptx_out:
            with open(ptx_out, "w") as f:
                f.write(normalised_ptx(ptx))
        if ptx_version:
            ptx = re.sub(r"^\.version \S+", f".version {ptx_version}", ptx, count=1, flags=re.M)
        fixed = os.path.join(tmp, "kernel.ptx")
        with open(fixed, "w") as f:
            f.write(ptx)
        run = subprocess.run(
            ["ptxas", "-v", f"-arch=sm_{arch}", "-o", os.devnull, fixed], capture_output=True, text=True, check=False
        )
    text = run.stderr
    if run.returncode != 0:
        raise RuntimeError(text.strip())
    forward = text[text.index("_cuda_kernel_forward") :]
    frame = re.search(r"(\d+) bytes stack frame, (\d+) bytes spill stores, (\d+) bytes spill loads", forward)
    regs = re.search(r"Used (\d+) registers", forward)
    smem = re.search(r"Used \d+ registers.*?(\d+) bytes smem", forward)
    shared = int(smem.group(1)) if smem else 0
    return int(regs.group(1)), int(frame.group(1)), int(frame.group(2)), int(frame.group(3)), shared


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--shapes", default="cube,rock20,hull64")
    ap.add_argument("--precisions", default="float32,mixed")
    ap.add_argument("--arch", type=int, default=90)
    ap.add_argument("--ptx-version", default="9.0", help="PTX .version to write for ptxas ('' keeps NVRTC's)")
    ap.add_argument(
        "--ptx-out",
        default="",
        help="DIR: also write each kernel's normalised PTX there (diff -r two trees' DIRs: the same code or not)",
    )
    ap.add_argument(
        "--shared-poly", action="store_true",
        help="also the overlap and pair kernels with the polygon buffer in shared memory (make_geometry's shared_poly)",
    )  # fmt: skip
    args = ap.parse_args()

    wp.config.quiet = True
    wp.init()
    head = f"{'shape':<8}{'prec':>9}  {'kernel':<13}{'regs':>5}{'stack B':>9}{'spill st':>9}{'spill ld':>9}"
    print(f"{head}{'smem B':>8}")
    for name in args.shapes.split(","):
        shapes = ShapeSet([SHAPES[name]()], device="cpu", precision="float32")
        cap, faces = shapes.default_poly_capacity, shapes.max_faces
        for prec in args.precisions.split(","):
            # The batch overlap kernel (float64 poses with float32 clipping in mixed) and the step's.
            scalar = wp.float64 if prec == "float64" else wp.float32
            pose_scalar = wp.float64 if prec == "mixed" else scalar
            kernels = [("overlap", make_narrowphase(scalar, cap, faces, pose_scalar=pose_scalar).overlap_kernel)]
            if args.shared_poly and scalar == wp.float32:
                shared = make_narrowphase(scalar, cap, faces, pose_scalar=pose_scalar, shared_poly=True)
                kernels.append(("overlap_shm", shared.overlap_kernel))
            contact = make_contact_kernels("hertz", True, cap, faces, precision=prec)
            kernels.append(("pair_contact", contact.pair_contact_kernel))
            if args.shared_poly and scalar == wp.float32:
                contact = make_contact_kernels("hertz", True, cap, faces, precision=prec, shared_poly=True)
                kernels.append(("pair_cont_shm", contact.pair_contact_kernel))
            # the GPU's default step: the pairs ordered by cost, the costly ones spread one to a warp
            spread = make_contact_kernels("hertz", True, cap, faces, precision=prec, thread_order=True, spread=True)
            kernels.append(("pair_spread", spread.pair_contact_kernel))
            if args.shared_poly and scalar == wp.float32:
                spread = make_contact_kernels(
                    "hertz", True, cap, faces, precision=prec, thread_order=True, spread=True, shared_poly=True
                )
                kernels.append(("pair_spr_shm", spread.pair_contact_kernel))
            for label, kernel in kernels:
                out = ""
                if args.ptx_out:
                    os.makedirs(args.ptx_out, exist_ok=True)
                    out = os.path.join(args.ptx_out, f"{name}_{prec}_{label}.ptx")
                regs, frame, st, ld, shared = ptxas_stats(kernel, args.arch, args.ptx_version, out)
                print(f"{name:<8}{prec:>9}  {label:<13}{regs:>5}{frame:>9}{st:>9}{ld:>9}{shared:>8}", flush=True)


if __name__ == "__main__":
    main()
