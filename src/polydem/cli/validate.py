"""``polydem validate``: check scene files without running them (host only: no Warp, no device)."""

from __future__ import annotations

import math
import sys

from polydem.cli.common import plural, steps_at
from polydem.cli.errors import EXIT_OK, EXIT_USER_ERROR
from polydem.cli.settings import DEFAULT_STEPS, load_scene, usd_setting

__all__ = ["cmd_validate", "depth_lines", "float32_rest_warnings"]

FLOAT32_REST_SPACINGS = 16.0
"""A face resting fewer float32 spacings deep than this chatters from one representable position to the
next in precision "float32". The spacing is float32's at the larger of the body's farthest coordinate and
its bounding radius (the two terms of a vertex's world position). Measured (BENCHMARKS.md 10a,
tests/test_at_rest.py): 77 spacings (the 0.1 m cube at k 1e8) rest within 10% of the weight in every step
and 1% on average; 71 (the incline's block at k 1e7) hold on 20 degrees; 0.7 (the block at k 1e9) creep
0.24 mm in 0.5 s. The threshold lies between, not at a measured edge."""


def cmd_validate(args) -> int:
    import warnings

    from polydem.scene import SceneError, SceneWarning
    from polydem.scene.depth import pile_depths

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
        rows = pile_depths(scene, ts)
        for message in float32_rest_warnings(scene, rows):
            err.write(f"polydem: warning: {message}\n")
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
        lines += depth_lines(scene, rows)
        frames = math.floor(steps * dt * scene.output.fps + 1e-9) + 1
        lines.append(
            f"  a run: {steps} steps to t = {steps * dt:.6g} s ({how}); {frames} frames at {scene.output.fps:g} fps"
            + (f" in {usd}" if usd else " (no USD file)")
        )
        lines.append(f"OK: {path} is a valid scene")
        out.write("\n".join(lines) + "\n")
    out.flush()
    return status


def _share(rest, size: float) -> str:
    """A resting depth as a percentage of the size, marked * where it lies in the resolved toe."""
    if not math.isfinite(rest.depth):
        return "through"
    return f"{100.0 * rest.depth / size:.2g}%" + ("*" if rest.in_toe else "")


def depth_lines(scene, rows) -> list[str]:
    """What ``polydem validate`` prints of the resting depths to expect (``rows`` from
    :func:`polydem.scene.depth.pile_depths` at the scene's time step): per free (shape, material), its
    deepest face / edge / corner under its own weight and under a column of the pile (where that holds at
    least 1.5 grains), and the k that keeps a corner at 1% of the size under the heavier of the two."""
    from polydem.scene.materials import LAW_UNITS

    if not rows:
        return []
    law = scene.pair_table()["law"]
    toe = any(r.in_toe for row in rows for d in (row.depth_weight, row.depth_column) for r in d.values())
    lines = [
        "  resting depth of the deepest face / edge / corner on a flat face, % of the body's size V^(1/3) "
        f"({law}, loading branch, on {rows[0].partner}" + ("; * in the resolved toe, set by dt" if toe else "") + "):"
    ]
    for row in rows:
        own = " / ".join(_share(row.depth_weight[f], row.size) for f in ("face", "edge", "corner"))
        text = f"    {row.shape} ({row.material}, k {row.k:.3g}): own weight {own}"
        load = "its weight"
        if row.column >= 1.5:
            col = " / ".join(_share(row.depth_column[f], row.size) for f in ("face", "edge", "corner"))
            text += f"; a column of {row.column:.3g} ({row.height:.3g} m) {col}"
            load = "the column"
        need = f"{row.k_corner:.3g} {LAW_UNITS[law]}" if math.isfinite(row.k_corner) else "a shorter dt"
        if row.k_corner != row.k_corner_law:
            need += f" ({row.k_corner_law:.3g} by the law alone)"
        lines.append(f"{text}; a corner {100.0 * row.allowed:g}% deep under {load} needs k {need}")
    return lines


def float32_rest_warnings(scene, rows) -> list[str]:
    """Warnings for precision "float32" where the shallowest face's resting depth under its own weight
    (``rows`` from :func:`polydem.scene.depth.pile_depths`) is under FLOAT32_REST_SPACINGS spacings of
    float32 numbers (see there): positions are float32 numbers, so the body hops between representable
    depths instead of resting."""
    import numpy as np

    from polydem.kernels.precision import Precision
    from polydem.scene.bodies import BodyKind

    if scene.precision != Precision.FLOAT32 or not rows:
        return []
    a = scene.body_arrays()
    free = a["kind"] == BodyKind.FREE
    radius = np.array([s.radius for s in scene.shapes.values()])[a["shape"][free]]
    reach = float(np.max(np.maximum(np.abs(a["position"][free]).max(axis=1), radius)))
    spacing = float(np.spacing(np.float32(reach)))
    out = []
    for row in rows:
        depth = row.shallowest_face.depth
        if math.isfinite(depth) and depth < FLOAT32_REST_SPACINGS * spacing:
            out.append(
                f"shape {row.shape!r} ({row.material}) rests on a face {depth:.2g} m deep, "
                f"{depth / spacing:.3g} float32 spacings ({spacing:.2g} m at {reach:.3g} m), "
                f'under the {FLOAT32_REST_SPACINGS:g} that precision = "float32" needs to rest: it will chatter '
                'and creep; use precision = "mixed" (float64 positions), a softer k (the depth grows as 1/k), '
                "or place the scene nearer the origin (simulation.precision)"
            )
    return out
