"""``polydem render``: a PNG picture of a scene file, a checkpoint or a frame of a USD file."""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np

from polydem import signals
from polydem.cli.common import plural, shorten
from polydem.cli.device import device
from polydem.cli.errors import EXIT_OK, CliError, why
from polydem.cli.poses import Poses, check_poses, read_checkpoint
from polydem.cli.settings import load_scene

__all__ = ["cmd_render"]

_USD_SUFFIXES = (".usd", ".usda", ".usdc")


_FIX = "give the scene it was written from with --scene SCENE"


def _scene_file(args, source: Path):
    """Frame 0 of a scene file: (scene, positions, orientations, what is rendered)."""
    if args.scene is not None:
        raise CliError("--scene is for checkpoints and USD files; a scene file renders itself", key="--scene")
    if args.frame not in (None, 0):
        raise CliError(
            f"a scene file holds frame 0 only (its initial state), not frame {args.frame}; run it with "
            "polydem run and render a frame of its USD file or a checkpoint",
            source,
            "--frame",
        )
    scene = load_scene(source)
    return scene, scene.body_position, scene.body_orientation, f"frame 0 of {source}", None


def _checkpoint(args, source: Path):
    """The state in a checkpoint: (scene, positions, orientations, what is rendered)."""
    if args.frame is not None:
        raise CliError(
            "a checkpoint holds one state: leave --frame out (or render a frame of the run's USD file)",
            source,
            "--frame",
        )
    scene = load_scene(args.scene)
    arrays = read_checkpoint(source).arrays
    body_q = arrays["body_q"].astype(np.float64)
    check_poses(source, body_q[:, :3], scene, args.scene, "checkpoint", _FIX)
    mesh_q = arrays.get("mesh_q")  # the mesh walls' poses, where it has mesh walls
    return scene, body_q[:, :3], body_q[:, 3:7], f"the checkpoint {source}", mesh_q


def _usd_frame(args, source: Path):
    """A frame of a USD file written by polydem run: (scene, positions, orientations, what is rendered)."""
    from polydem.usd import read_frame, read_metadata, read_time_codes

    try:
        codes = read_time_codes(source)
        recorded = read_metadata(source)
    except (ValueError, OSError) as exc:
        raise CliError(f"{exc}; give a USD file written by polydem run", source) from None
    scene_arg = args.scene
    if scene_arg is None and recorded.get("scene_file"):
        scene_arg = recorded["scene_file"]
        if not Path(scene_arg).is_file():
            raise CliError(
                f"the scene file it was written from, '{scene_arg}', is gone; give the scene with --scene SCENE",
                source,
            )
    scene = load_scene(scene_arg)
    if not len(codes):
        raise CliError("the USD file has no frames; render a checkpoint or the scene instead", source)
    frame = int(codes[-1]) if args.frame is None else args.frame
    if frame not in set(codes.astype(np.int64).tolist()):
        raise CliError(
            f"the USD file has no frame {frame}: it holds {len(codes)} frames, {int(codes[0])} to "
            f"{int(codes[-1])}; give one of them with --frame",
            source,
            "--frame",
        )
    positions, orientations = read_frame(source, frame)
    check_poses(source, positions, scene, scene_arg, "USD file", _FIX)
    _check_shapes(source, recorded, scene, scene_arg, args.scene is not None)
    return scene, positions, orientations, f"frame {frame} of {source}", None


def _check_shapes(source: Path, recorded: dict, scene, scene_arg, given: bool) -> None:
    """CliError unless ``scene`` has the shapes the USD file was written with: another scene of as many
    bodies passes the body count, and its shapes would be drawn at the file's poses without a word."""
    from polydem.usd import shapes_digest

    digest = recorded.get("shapes_sha256")
    label = "the built-in default scene" if scene_arg is None else f"the scene {scene_arg}"
    if digest is None:
        sys.stdout.flush()
        sys.stderr.write(
            f"polydem: warning: {source}: written by an older polydem, without a record of its shapes: "
            f"it cannot be checked to come from {label}\n"
        )
        sys.stderr.flush()
        return
    if digest != shapes_digest(scene):
        if given:
            why_not = f"{label} has other shapes (or assigns them to other bodies) than the scene it was written from"
            fix = _FIX
        else:
            why_not = f"the shapes of {label}, which it was written from, have changed since"
            fix = "give the scene as it was with --scene SCENE"
        raise CliError(f"{why_not}; {fix}", source, "--scene")


def _source(args) -> Path:
    """The file to render (CliError when it is of no known kind or not there)."""
    source = Path(args.source)
    if source.suffix.lower() not in (".toml", ".npz", *_USD_SUFFIXES):
        raise CliError(
            "give a scene file (.toml, frame 0), a checkpoint (.npz) or a USD file written by polydem run "
            "(.usd, .usda, .usdc)",
            source,
        )
    try:
        found = source.is_file()
    except OSError as exc:  # a name too long for the file system
        raise CliError(f"cannot read the file ({why(exc)}); check the path", shorten(source)) from None
    if not found:
        raise CliError(f"file not found (looked for '{source.absolute()}'); check the path", source)
    return source


def _check_size(args, dev) -> None:
    """CliError for a picture the memory of this machine (or of the GPU that draws) cannot hold,
    naming the option to change: --supersample where a smaller one fits, else --width/--height."""
    from polydem.picture_memory import PictureSizeError
    from polydem.render import check_picture

    try:
        check_picture(args.width, args.height, args.supersample, dev)
    except PictureSizeError as exc:
        if exc.supersample > 1 and exc.largest_supersample >= 1:
            raise CliError(
                f"{exc}; give --supersample {exc.largest_supersample} or less, or a smaller --width/--height",
                key="--supersample",
            ) from None
        fix = "a smaller --width/--height" + (" with --supersample 1" if exc.supersample > 1 else "")
        raise CliError(f"{exc}; give {fix}", key="--width/--height") from None


def cmd_render(args) -> int:
    from polydem.render import render_simulation

    out_png = Path(args.out)
    if out_png.suffix.lower() != ".png":
        raise CliError("the picture must be a .png file, e.g. --out frame.png", out_png, "--out")
    source = _source(args)
    dev = device(args.device)
    _check_size(args, dev)
    read = {".toml": _scene_file, ".npz": _checkpoint}.get(source.suffix.lower(), _usd_frame)
    scene, positions, orientations, what, mesh_q = read(args, source)
    poses = Poses(scene, positions, orientations, dev, mesh_q=mesh_q)
    signals.check()
    try:
        out_png.parent.mkdir(parents=True, exist_ok=True)
        render_simulation(
            poses,
            out_png,
            width=args.width,
            height=args.height,
            supersample=args.supersample,
            azimuth=args.azimuth,
            elevation=args.elevation,
        )
    except OSError as exc:
        raise CliError(f"cannot write the picture ({why(exc)})", shorten(out_png), "--out") from None
    sys.stdout.write(
        f"wrote {out_png} ({args.width} x {args.height}): {what}, {plural(scene.num_bodies, 'body', 'bodies')}\n"
    )
    return EXIT_OK
