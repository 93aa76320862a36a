"""``polydem info``: the versions of polydem and its libraries, and the Warp devices."""

from __future__ import annotations

import sys

import numpy as np

from polydem.cli.device import WARP_NOTES, warp
from polydem.cli.errors import EXIT_OK

__all__ = ["cmd_info"]


def cmd_info(args) -> int:
    import platform

    import polydem

    wp = warp()
    lines = [f"polydem {polydem.__version__}", f"  Python {platform.python_version()}, numpy {np.__version__}"]
    lines.append(f"  Warp {wp.config.version}, kernel cache {wp.config.kernel_cache_dir}")
    try:
        from pxr import Usd

        lines.append(f"  usd-core (OpenUSD) {'.'.join(map(str, Usd.GetVersion()))}")
    except ImportError:
        lines.append("  usd-core: not installed (no USD output)")
    lines.append(f"  several processes: {_distributed_line()}")
    default = wp.get_device()
    lines.append(f"devices (default {default.alias}):")
    for d in wp.get_devices():
        extra = ""
        if d.is_cuda:
            extra = f", sm_{d.arch}, {d.total_memory / 2**30:.1f} GiB"
        lines.append(f"  {d.alias:<8} {d.name}{extra}")
    if not wp.get_cuda_device_count():
        lines.append("  no CUDA device: runs use the CPU")
    for note in WARP_NOTES:
        lines.append(f"  note: {note}")
    sys.stdout.write("\n".join(lines) + "\n")
    return EXIT_OK


def _distributed_line() -> str:
    """What a run over several processes (mpiexec) would have here: mpi4py, and nccl4py for the ghost rows from GPU
    to GPU (``--exchange auto`` takes it where each rank has a GPU of its own)."""
    from importlib.util import find_spec

    if find_spec("mpi4py") is None:
        return 'mpi4py not installed (pip install "polydem[mpi]" to run under mpiexec)'
    try:
        nccl = find_spec("nccl.core") is not None
    except ModuleNotFoundError:
        nccl = False
    exchange = (
        "nccl4py present: ghost rows GPU to GPU with NCCL"
        if nccl
        else ('nccl4py not installed: ghost rows through host memory (pip install "polydem[nccl]" for NCCL)')
    )
    return f"mpi4py present; {exchange}"
