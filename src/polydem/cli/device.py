"""Warp, initialised for the command, and the device a command runs on."""

from __future__ import annotations

import os
import re
import sys

from polydem.cli.errors import CliError

__all__ = ["WARP_NOTES", "device", "warp"]

WARP_NOTES: list[str] = []
"""Warp's own notes kept from stderr at its start (no CUDA driver), for ``polydem info``."""


def warp():
    """Warp, initialised with its info messages off.

    Warp's native library prints a warning on stderr when it finds no CUDA driver, which on a
    CPU-only machine would come before every message of this command; it is kept for ``polydem
    info`` instead (other native messages are passed on).
    """
    import warp as wp

    wp.config.log_level = max(wp.config.log_level, wp.LOG_WARNING)
    context = getattr(getattr(wp, "_src", None), "context", None)
    if context is None or getattr(context, "runtime", True) is not None:
        wp.init()  # already initialised, or a Warp whose internals differ: nothing to capture
        return wp
    import tempfile

    try:
        sys.stderr.flush()
        saved = os.dup(2)
    except (OSError, ValueError):
        wp.init()
        return wp
    with tempfile.TemporaryFile() as tmp:
        os.dup2(tmp.fileno(), 2)
        try:
            wp.init()
        finally:
            os.dup2(saved, 2)
            os.close(saved)
        tmp.seek(0)
        text = tmp.read().decode(errors="replace")
    for line in text.splitlines():
        if "NVIDIA CUDA driver" in line:
            WARP_NOTES.append(line.strip())
        elif line.strip():
            print(line, file=sys.stderr)
    return wp


def device(name, *, file=None, key="--device"):
    """The Warp device ``name`` (None: Warp's default), or a CliError when this machine lacks it."""
    wp = warp()
    if name is None:
        return wp.get_device()
    aliases = [d.alias for d in wp.get_devices()]
    if not re.fullmatch(r"cpu|cuda(:\d+)?", str(name)):
        raise CliError(
            f'unknown device {name!r}; give "cpu", "cuda" (the default GPU) or "cuda:N" (available here: '
            f"{', '.join(aliases)})",
            file,
            key,
        )
    if name == "cuda" and wp.get_cuda_device_count() > 0:
        return wp.get_device("cuda")
    if name not in aliases:
        fix = "use --device cpu" if key == "--device" else "override it with --device cpu"
        raise CliError(
            f"device {name!r} is not available on this machine (available: {', '.join(aliases)}); {fix}", file, key
        )
    return wp.get_device(name)
