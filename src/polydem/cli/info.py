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
