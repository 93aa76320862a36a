"""Output settings: what a run writes (the ``[output]`` table of a scene file)."""

from __future__ import annotations

import re
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from polydem.scene.errors import SceneError
from polydem.scene.values import check_keys, read_boolean, read_integer, read_number, read_string, read_table, typename

_USD_SUFFIXES = (".usd", ".usda", ".usdc")
_OUTPUT_KEYS = ("usd", "fps", "summary", "pictures", "checkpoint", "vtk")
_CHECKPOINT_KEYS = ("steps", "seconds", "path")


def _check_inside(value, key, example):
    """Refuse an output path that is absolute or leads out of the output folder."""
    # Backslashes count as separators too, so that a scene written on Windows is judged alike.
    parts = value.replace("\\", "/").split("/")
    if Path(value).is_absolute() or value.startswith(("/", "\\")) or re.match(r"[A-Za-z]:", value):
        raise SceneError(
            f"{value!r} is an absolute path; outputs stay inside the output folder (polydem run --out DIR): "
            f"give a path relative to it, e.g. {example}",
            key,
        )
    depth = 0
    for part in parts:
        depth += -1 if part == ".." else 0 if part in ("", ".") else 1
        if depth < 0:
            raise SceneError(
                f"{value!r} leads out of the output folder with '..'; outputs stay inside it: give a path "
                f"inside it, e.g. {example}, and choose the folder with polydem run --out DIR",
                key,
            )


@dataclass(frozen=True, kw_only=True)
class Output:
    """What a run writes: the ``[output]`` table of a scene file (validated on construction).

    The scene only stores these settings; the ``polydem`` command acts on them. Paths are relative
    to the output folder of the run (``polydem run --out DIR``) and must stay inside it: absolute
    paths and paths that lead out of it with ``..`` are refused (a scene file must not overwrite
    files elsewhere; the folder itself is the user's choice on the command line).

    Attributes:
        usd: USD file of the trajectory (``.usd``, ``.usda`` or ``.usdc``), or None for none. In a
            scene file ``usd = true`` means ``"trajectory.usd"`` and ``usd = false`` none.
        fps: frames per simulated second of the USD file and of the picture frames, > 0 [1/s].
        summary: JSON summary file, or None for none. In a scene file ``summary = true`` (the
            default) means ``"summary.json"``; ``false`` none; a string is the path.
        pictures: frame numbers to render as pictures (frame k is the state at time k / fps), as a
            sorted tuple of distinct integers >= 0, or ``"last"`` for the final state; ``()`` for none.
            In a scene file ``pictures = true`` means ``"last"`` and ``false`` none; ``polydem run``
            renders the last frame when the scene file does not mention ``pictures``.
        checkpoint_steps: write a checkpoint every so many steps, or None.
        checkpoint_seconds: write a checkpoint every so many simulated seconds, or None (at most
            one of the two is set). In a scene file: ``checkpoint = {steps = 10000}`` or
            ``checkpoint = {seconds = 0.1}``, optionally with ``path``.
        checkpoint_path: folder of the checkpoints.
        vtk: write VTK files for ParaView (``vtk/`` in the output folder: :mod:`polydem.vtk`) at
            every frame; ``polydem run --vtk`` turns it on too.
    """

    usd: str | None = None
    fps: float = 60.0
    summary: str | None = "summary.json"
    pictures: tuple | str = ()
    checkpoint_steps: int | None = None
    checkpoint_seconds: float | None = None
    checkpoint_path: str = "checkpoints"
    vtk: bool = False

    def __post_init__(self):
        usd = self.usd
        if usd is not None:
            usd = read_string(usd, "output.usd", what="a file path string such as 'trajectory.usd' (or true / false)")
            if not usd.strip():
                raise SceneError("the USD path is empty; give a file name such as 'trajectory.usd'", "output.usd")
            if Path(usd).suffix.lower() not in _USD_SUFFIXES:
                raise SceneError(
                    f"the USD file {usd!r} must end in {', '.join(_USD_SUFFIXES)} (e.g. 'trajectory.usd')", "output.usd"
                )
        fps = read_number(self.fps, "output.fps", positive=True, hint=" (frames per simulated second, e.g. fps = 60)")
        summary = self.summary
        if summary is not None:
            summary = read_string(summary, "output.summary", what="a file path string (or true / false)")
            if not summary.strip():
                raise SceneError("the summary path is empty; give a file name such as 'summary.json'", "output.summary")
        pictures = self.pictures
        hint = ' (frame numbers at fps, e.g. pictures = [0, 30, 60], or pictures = "last")'
        if isinstance(pictures, str):
            if pictures != "last":
                raise SceneError(
                    f'expected a list of frame numbers or "last", got {pictures!r}{hint}', "output.pictures"
                )
        elif isinstance(pictures, list | tuple | np.ndarray):
            frames = [read_integer(x, f"output.pictures[{i}]", minimum=0, hint=hint) for i, x in enumerate(pictures)]
            pictures = tuple(sorted(set(frames)))
        else:
            raise SceneError(
                f'expected a list of frame numbers or "last", got {typename(pictures)}{hint}', "output.pictures"
            )
        steps, seconds = self.checkpoint_steps, self.checkpoint_seconds
        if steps is not None and seconds is not None:
            raise SceneError(
                "give the checkpoint interval in steps or in seconds, not both", "output.checkpoint.seconds"
            )
        if steps is not None:
            steps = read_integer(
                steps, "output.checkpoint.steps", minimum=1, hint=" (a checkpoint every so many steps)"
            )
        if seconds is not None:
            seconds = read_number(
                seconds, "output.checkpoint.seconds", positive=True, hint=" (a checkpoint every so many simulated s)"
            )
        path = read_string(self.checkpoint_path, "output.checkpoint.path", what="a folder path string")
        vtk = read_boolean(self.vtk, "output.vtk")

        if usd is not None:
            _check_inside(usd, "output.usd", "usd = 'trajectory.usd'")
        if summary is not None:
            _check_inside(summary, "output.summary", "summary = 'summary.json'")
        _check_inside(path, "output.checkpoint.path", "checkpoint = {steps = 10000, path = 'checkpoints'}")
        for name, value in (
            ("usd", usd),
            ("fps", fps),
            ("summary", summary),
            ("pictures", pictures),
            ("checkpoint_steps", steps),
            ("checkpoint_seconds", seconds),
            ("checkpoint_path", path),
            ("vtk", vtk),
        ):
            object.__setattr__(self, name, value)

    @classmethod
    def from_dict(cls, table, file=None) -> Output:
        """Settings from an ``[output]`` table (errors name ``output.KEY`` and ``file``)."""
        try:
            table = read_table(table, "output", file, what="an [output] table")
            check_keys(table, _OUTPUT_KEYS, "output", file)
            kw = {}
            if "usd" in table:
                usd = table["usd"]
                kw["usd"] = ("trajectory.usd" if usd else None) if isinstance(usd, bool) else usd
            if "fps" in table:
                kw["fps"] = table["fps"]
            if "summary" in table:
                summary = table["summary"]
                kw["summary"] = ("summary.json" if summary else None) if isinstance(summary, bool) else summary
            if "pictures" in table:
                pictures = table["pictures"]
                kw["pictures"] = ("last" if pictures else ()) if isinstance(pictures, bool) else pictures
            if "vtk" in table:
                kw["vtk"] = table["vtk"]
            if "checkpoint" in table:
                cp = read_table(
                    table["checkpoint"],
                    "output.checkpoint",
                    file,
                    what="a table such as checkpoint = {steps = 10000} or checkpoint = {seconds = 0.1}",
                )
                check_keys(cp, _CHECKPOINT_KEYS, "output.checkpoint", file)
                if "steps" not in cp and "seconds" not in cp:
                    raise SceneError(
                        "give the checkpoint interval, e.g. checkpoint = {steps = 10000} or {seconds = 0.1}",
                        "output.checkpoint",
                        file,
                    )
                kw.update(checkpoint_steps=cp.get("steps"), checkpoint_seconds=cp.get("seconds"))
                if "path" in cp:
                    kw["checkpoint_path"] = cp["path"]
            return cls(**kw)
        except SceneError as err:
            if err.file is None:
                err.file = file
            raise

    def to_dict(self) -> dict:
        """The ``[output]`` table of a scene file."""
        d = {"fps": self.fps, "summary": self.summary if self.summary is not None else False}
        d["usd"] = self.usd if self.usd is not None else False
        if self.pictures:
            d["pictures"] = self.pictures if isinstance(self.pictures, str) else list(self.pictures)
        if self.checkpoint_steps is not None or self.checkpoint_seconds is not None:
            cp = {"path": self.checkpoint_path}
            if self.checkpoint_steps is not None:
                cp["steps"] = self.checkpoint_steps
            else:
                cp["seconds"] = self.checkpoint_seconds
            d["checkpoint"] = cp
        if self.vtk:
            d["vtk"] = True
        return d
