"""What a scene asks a run to write and where: the scene's ``[output]`` settings with the
command's defaults, and the check before a run that every output can be written."""

from __future__ import annotations

import os
from pathlib import Path

from polydem.cli.common import shorten
from polydem.cli.errors import CliError, why

__all__ = [
    "DEFAULT_STEPS",
    "DEFAULT_USD",
    "check_outputs",
    "load_scene",
    "output_paths",
    "pictures_setting",
    "usd_setting",
]

DEFAULT_STEPS = 1000
"""Steps of a run when neither the command line nor the scene gives steps or a duration."""

DEFAULT_USD = "trajectory.usdc"
"""USD file of a run whose scene file does not mention ``output.usd``."""


def load_scene(path, validate: bool = True):
    """The scene file ``path`` (validated unless ``validate`` is False), or the built-in default scene when
    ``path`` is None."""
    from polydem.scene import Scene

    if path is None:
        from polydem.default_scene import default_scene

        return default_scene()
    return Scene.from_toml(path, validate=validate)


def _output_keys(scene) -> set | None:
    """The keys of the scene file's ``[output]`` table (None when the scene has no readable file)."""
    file = getattr(scene, "file", None)
    if file is None:
        return None
    import tomllib

    try:
        with open(file, "rb") as fh:
            table = tomllib.load(fh).get("output", {})
    except (OSError, tomllib.TOMLDecodeError):
        return None
    return set(table) if isinstance(table, dict) else set()


def usd_setting(scene) -> str | None:
    """The USD file name of a run: ``output.usd``; the default when the scene file does not
    mention it; None for ``usd = false``."""
    if scene.output.usd is not None:
        return scene.output.usd
    if "usd" in (_output_keys(scene) or ()):
        return None  # usd = false
    return DEFAULT_USD


def pictures_setting(scene):
    """The pictures of a run: ``output.pictures``; ``"last"`` (a picture of the final state) when
    the scene file does not mention it; ``()`` for ``pictures = false`` or ``[]``."""
    if scene.output.pictures or "pictures" in (_output_keys(scene) or ()):
        return scene.output.pictures
    return "last"


def output_paths(scene, out_dir: Path) -> dict:
    """The outputs of a run by the key that names them: ``output.usd`` and ``output.summary`` (when
    written), ``output.checkpoint.path`` (the folder); all inside ``out_dir``."""
    o = scene.output
    paths = {"output.checkpoint.path": out_dir / o.checkpoint_path}
    usd = usd_setting(scene)
    if usd is not None:
        paths["output.usd"] = out_dir / usd
    if o.summary is not None:
        paths["output.summary"] = out_dir / o.summary
    return paths


def _probe_file(path: Path, extra: str = ".tmp") -> list[Path]:
    """OSError unless a file ``path`` can be written (the longest temporary name, ``path`` + ``extra``,
    is created and removed). Returns the folders it had to make, outermost first."""
    made = [p for p in reversed(path.parents) if not p.exists()]
    path.parent.mkdir(parents=True, exist_ok=True)
    if path.is_dir():
        raise IsADirectoryError(21, "Is a directory", str(path))  # EISDIR
    probe = path.with_name(path.name + extra)
    if probe.exists():
        return made
    fd = os.open(probe, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o644)
    os.close(fd)
    os.unlink(probe)
    return made


def check_outputs(args, scene, out_dir: Path) -> None:
    """CliError (before the run) for an output that cannot be written: a name too long for the file
    system, a file where a folder should be, a folder without write permission."""
    file = args.scene
    paths = output_paths(scene, out_dir)
    probes = [(out_dir / "packing.png", ".tmp", "--out")]  # the plots; the folder itself
    if "output.usd" in paths:
        probes.append((paths["output.usd"], ".tmp", "output.usd"))
    if "output.summary" in paths:
        probes.append((paths["output.summary"], ".tmp", "output.summary"))
    probes.append((paths["output.checkpoint.path"] / "step_000000000.npz", ".tmp.npz", "output.checkpoint.path"))
    if pictures_setting(scene):
        probes.append((out_dir / "pictures" / "frame_000000.png", ".tmp", "output.pictures"))
    vtk = out_dir / "vtk"
    if (args.vtk or scene.output.vtk) and vtk.exists() and not vtk.is_dir():
        raise CliError("the VTK output folder is a file; remove it or give another --out", vtk, "--vtk")
    made: list[Path] = []
    try:
        for path, extra, key in probes:
            try:
                made += _probe_file(path, extra)
            except OSError as exc:
                where = shorten(exc.filename) if getattr(exc, "filename", None) else shorten(path)
                raise CliError(f"cannot write {where}: {why(exc)}", None if key == "--out" else file, key) from None
    finally:
        # The run makes the folders it writes to; the check leaves none behind (an empty checkpoints/
        # folder after an error would look like a run that wrote nothing).
        for folder in sorted(set(made), key=lambda p: len(p.parts), reverse=True):
            try:
                folder.rmdir()
            except OSError:
                pass
