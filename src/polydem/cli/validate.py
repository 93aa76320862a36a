"""``polydem validate``: check scene files without running them (host only: no Warp, no device)."""

from __future__ import annotations

import math
import sys

from polydem.cli.common import plural, steps_at
from polydem.cli.errors import EXIT_OK, EXIT_USER_ERROR
from polydem.cli.settings import DEFAULT_STEPS, load_scene, usd_setting

__all__ = ["cmd_validate"]


def cmd_validate(args) -> int:
    import warnings

    from polydem.scene import SceneError, SceneWarning

    out, err = sys.stdout, sys.stderr
    status = EXIT_OK
    for k, path in enumerate(args.scenes):
        # Host-only: the scene's checks and time step need neither Warp nor a device.
        try:
            with warnings.catch_warnings(record=True) as caught:
                warnings.simplefilter("always", SceneWarning)
                scene = load_scene(path)
                ts = scene.time_step()
        except SceneError as exc:
            err.write(f"polydem: error: {exc}\n")
            err.flush()
            status = EXIT_USER_ERROR
            continue
        for w in caught:
            if issubclass(w.category, SceneWarning):
                err.write(f"polydem: warning: {w.message}\n")
            else:
                warnings.warn_explicit(w.message, w.category, w.filename, w.lineno)
        err.flush()
        dt = ts.dt
        if scene.duration is not None:
            steps, how = max(1, steps_at(scene.duration, dt)), f"duration {scene.duration:g} s"
        elif scene.steps is not None:
            steps, how = scene.steps, "steps"
        else:
            steps, how = DEFAULT_STEPS, "no steps or duration given: the default"
        usd = usd_setting(scene)
        if args.quiet:
            out.write(f"{path}: OK, {plural(scene.num_bodies, 'body', 'bodies')}, dt {dt:.4g} s, {steps} steps\n")
            continue
        if k:
            out.write("\n")
        lines = [scene.describe()]
        auto = "auto" if scene.dt == "auto" else "given"
        lines.append(
            f"  time step: {dt:.4g} s ({auto}; recommended {ts.recommended:.4g} s, stable limit {ts.limit:.4g} s)"
        )
        frames = math.floor(steps * dt * scene.output.fps + 1e-9) + 1
        lines.append(
            f"  a run: {steps} steps to t = {steps * dt:.6g} s ({how}); {frames} frames at {scene.output.fps:g} fps"
            + (f" in {usd}" if usd else " (no USD file)")
        )
        lines.append(f"OK: {path} is a valid scene")
        out.write("\n".join(lines) + "\n")
    out.flush()
    return status
