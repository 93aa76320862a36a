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
