"""Provenance of benchmark figures: the commit, and whether the simulator's sources differ from it."""

import os
import subprocess

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))


def git_state():
    """``git_commit`` and ``git_dirty`` (src/ or kernels/ changed since it), with the changed files."""
    out = {}
    try:

        def git(*a):
            return subprocess.run(["git", *a], cwd=ROOT, capture_output=True, text=True, timeout=10).stdout.rstrip()

        out["git_commit"] = git("rev-parse", "HEAD")
        dirty = git("status", "--porcelain", "--", "src", "kernels")
        out["git_dirty"] = bool(dirty)
        if dirty:
            out["git_dirty_files"] = [line[3:] for line in dirty.splitlines()]
    except Exception:  # no git: the figures simply carry no provenance
        pass
    return out


def run_meta(device=None):
    """Machine, command line, date and git state of a benchmark run; with a Warp ``device`` also
    the device, Warp's version and, on CUDA, the GPU's properties. Plain Python otherwise (the Yade
    and Newton scripts use it too)."""
    import datetime
    import platform
    import sys

    meta = {
        "python": platform.python_version(),
        "machine": platform.platform(),
        "processor": platform.processor(),
        "cpu_count": os.cpu_count(),
        "command": " ".join([os.path.basename(sys.executable), *sys.argv]),
        "date": datetime.datetime.now(datetime.UTC).isoformat(timespec="seconds"),
    }
    if device is not None:
        import numpy as np
        import warp as wp

        meta.update(
            {
                "device": device.name,
                "alias": device.alias,
                "is_cuda": device.is_cuda,
                "warp": wp.config.version,
                "numpy": np.__version__,
            }
        )
        if device.is_cuda:
            meta["memory_bytes"] = getattr(device, "total_memory", None)
            meta["arch"] = getattr(device, "arch", None)
            meta["sm_count"] = getattr(device, "sm_count", None)
            meta["mempool_enabled"] = bool(wp.is_mempool_enabled(device))
            try:
                meta["cuda_driver"] = wp.get_cuda_driver_version()
                meta["cuda_toolkit"] = wp.get_cuda_toolkit_version()
            except Exception:
                pass
    meta.update(git_state())
    return meta


def activity_ms_per_step(run, steps, cuda_filter):
    """Warp's activity timing of ``run()``, which takes ``steps`` steps: GPU milliseconds per step by activity
    (kernel, copy or graph launch) name, the costliest first. ``cuda_filter``: ``wp.TIMING_GRAPH``, or
    ``wp.TIMING_KERNEL | wp.TIMING_MEMCPY`` with the graphs off."""
    import warp as wp

    wp.timing_begin(cuda_filter=cuda_filter)
    run()
    sums = {}
    for r in wp.timing_end():
        sums[r.name] = sums.get(r.name, 0.0) + r.elapsed / steps
    return dict(sorted(sums.items(), key=lambda kv: -kv[1]))
