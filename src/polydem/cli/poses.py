"""Body poses read from a file (a checkpoint or a USD frame): the checks that they belong to a
scene, and what the renderer reads of them."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from polydem.cli.errors import CliError
from polydem.scene.bodies import BodyKind

__all__ = ["Poses", "check_poses", "read_checkpoint", "read_checkpoint_poses"]


def _fixed_pose_mismatch(scene, positions) -> int | None:
    """Index of a fixed body whose position is not the scene's (a state of another scene), or None.

    Fixed bodies never move, so every state of this scene holds their initial positions exactly
    (as float32, which checkpoints and USD files keep).
    """
    fixed = np.flatnonzero(np.asarray(scene.body_kind) == BodyKind.FIXED)
    if not len(fixed):
        return None
    expect = np.asarray(scene.body_position, dtype=np.float64)[fixed].astype(np.float32)
    got = np.asarray(positions, dtype=np.float64)[fixed].astype(np.float32)
    bad = np.flatnonzero(np.any(got != expect, axis=1))
    return int(fixed[bad[0]]) if len(bad) else None


def check_poses(path, positions, scene, scene_arg, what: str, fix: str, key=None) -> None:
    """CliError unless ``positions`` (from a checkpoint or USD file) can be a state of ``scene``."""
    label = "the built-in default scene" if scene_arg is None else f"the scene {scene_arg}"
    n = len(positions)
    if n != scene.num_bodies:
        raise CliError(f"the {what} has {n} bodies but {label} has {scene.num_bodies}; {fix}", path, key)
    bad = _fixed_pose_mismatch(scene, positions)
    if bad is not None:
        raise CliError(
            f"fixed body {bad} is not where {label} puts it, so the {what} comes from another scene; {fix}", path, key
        )


def read_checkpoint(path: Path, key=None):
    """The checked :class:`polydem.checkpoint.Checkpoint` in ``path`` (CliError naming what is wrong)."""
    from polydem.checkpoint import CheckpointError
    from polydem.checkpoint import read_checkpoint as read

    try:
        return read(path)
    except CheckpointError as err:
        raise CliError(err.message, path, key) from None
    except OSError as err:
        raise CliError(
            f"cannot read the checkpoint ({err.strerror or err}); check the path and its permissions", path, key
        ) from None


def read_checkpoint_poses(path: Path) -> np.ndarray:
    """The (N, 7) body poses [px, py, pz, qx, qy, qz, qw] of a checkpoint (CliError if it is not one)."""
    return read_checkpoint(path).arrays["body_q"].astype(np.float64)


class Poses:
    """What :func:`polydem.render.render_simulation` reads of a Simulation, for poses from a file."""

    def __init__(self, scene, positions, orientations, device, mesh_q=None):
        from types import SimpleNamespace

        self.device = device
        self.scene = scene
        self.model = SimpleNamespace(
            shapes=[scene.shapes[name] for name in scene.shape_names],
            body_flags_np=np.asarray(scene.body_kind),
        )
        self.mesh_q = mesh_q  # (M, 7) mesh wall poses, or None: their initial poses
        self._state = {
            "body_position": np.asarray(positions, dtype=np.float64),
            "body_orientation": np.asarray(orientations, dtype=np.float64),
        }

    def state(self):
        return self._state
