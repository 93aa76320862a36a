"""Output settings: what a run writes (the ``[output]`` table of a scene file)."""

from __future__ import annotations

import re
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from polydem.scene.errors import SceneError
from polydem.scene.schema import Key, Table
from polydem.scene.values import read_integer, read_table, typename

_USD_SUFFIXES = (".usd", ".usda", ".usdc")
_PICTURES_HINT = ' (frame numbers at fps, e.g. pictures = [0, 30, 60], or pictures = "last")'


def _pictures(value, key, file):
    if isinstance(value, str):
        if value != "last":
            raise SceneError(f'expected a list of frame numbers or "last", got {value!r}{_PICTURES_HINT}', key, file)
        return value
    if isinstance(value, list | tuple | np.ndarray):
        frames = [read_integer(x, f"{key}[{i}]", file, minimum=0, hint=_PICTURES_HINT) for i, x in enumerate(value)]
        return tuple(sorted(set(frames)))
    raise SceneError(f'expected a list of frame numbers or "last", got {typename(value)}{_PICTURES_HINT}', key, file)


OUTPUT = Table(
    "[output]",
    (
        Key(
            "usd",
            "string",
            what="a file path string such as 'trajectory.usd' (or true / false)",
            on="trajectory.usd",
            off=None,
        ),
        Key("fps", unit="1/s", range="> 0", default=60.0, hint="frames per simulated second, e.g. fps = 60"),
        Key(
            "summary",
            "string",
            what="a file path string (or true / false)",
            default="summary.json",
            on="summary.json",
            off=None,
        ),
        Key("pictures", "any", default=(), on="last", off=(), write="changed", check=_pictures),
        Key("checkpoint", "any", write="never"),
        Key("vtk", "boolean", default=False, write="changed"),
    ),
)
"""The ``[output]`` table: the fields of :class:`Output` but the checkpoint's, which :data:`CHECKPOINT` declares."""

CHECKPOINT = Table(
    "[output] checkpoint",
    (
        Key("steps", "integer", range=">= 1", attr="checkpoint_steps", hint="a checkpoint every so many steps"),
        Key(
            "seconds",
            unit="s",
            range="> 0",
            attr="checkpoint_seconds",
            hint="a checkpoint every so many simulated s",
        ),
        Key("path", "string", what="a folder path string", default="checkpoints", attr="checkpoint_path"),
    ),
)
"""``checkpoint = {steps = N | seconds = T, path = ...}`` of the ``[output]`` table."""


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

    usd: str | None = OUTPUT.defaults["usd"]
    fps: float = OUTPUT.defaults["fps"]
    summary: str | None = OUTPUT.defaults["summary"]
    pictures: tuple | str = OUTPUT.defaults["pictures"]
    checkpoint_steps: int | None = CHECKPOINT.defaults["steps"]
    checkpoint_seconds: float | None = CHECKPOINT.defaults["seconds"]
    checkpoint_path: str = CHECKPOINT.defaults["path"]
    vtk: bool = OUTPUT.defaults["vtk"]

    def __post_init__(self):
        if self.checkpoint_steps is not None and self.checkpoint_seconds is not None:
            raise SceneError(
                "give the checkpoint interval in steps or in seconds, not both", "output.checkpoint.seconds"
            )
        values = OUTPUT.read({k.attr: getattr(self, k.attr) for k in OUTPUT.keys if k.name != "checkpoint"}, "output")
        values |= CHECKPOINT.read({k.attr: getattr(self, k.attr) for k in CHECKPOINT.keys}, "output.checkpoint")
        usd, summary = values["usd"], values["summary"]
        if usd is not None:
            if not usd.strip():
                raise SceneError("the USD path is empty; give a file name such as 'trajectory.usd'", "output.usd")
            if Path(usd).suffix.lower() not in _USD_SUFFIXES:
                raise SceneError(
                    f"the USD file {usd!r} must end in {', '.join(_USD_SUFFIXES)} (e.g. 'trajectory.usd')", "output.usd"
                )
            _check_inside(usd, "output.usd", "usd = 'trajectory.usd'")
        if summary is not None:
            if not summary.strip():
                raise SceneError("the summary path is empty; give a file name such as 'summary.json'", "output.summary")
            _check_inside(summary, "output.summary", "summary = 'summary.json'")
        path = values["checkpoint_path"]
        _check_inside(path, "output.checkpoint.path", "checkpoint = {steps = 10000, path = 'checkpoints'}")
        for name, value in values.items():
            object.__setattr__(self, name, value)

    @classmethod
    def from_dict(cls, table, file=None) -> Output:
        """Settings from an ``[output]`` table (errors name ``output.KEY`` and ``file``)."""
        try:
            table = read_table(table, "output", file, what="an [output] table")
            OUTPUT.check(table, "output", file)
            kw = OUTPUT.arguments(table, "output", file, skip=("checkpoint",))
            if "checkpoint" in table:
                cp = read_table(
                    table["checkpoint"],
                    "output.checkpoint",
                    file,
                    what="a table such as checkpoint = {steps = 10000} or checkpoint = {seconds = 0.1}",
                )
                CHECKPOINT.check(cp, "output.checkpoint", file)
                if "steps" not in cp and "seconds" not in cp:
                    raise SceneError(
                        "give the checkpoint interval, e.g. checkpoint = {steps = 10000} or {seconds = 0.1}",
                        "output.checkpoint",
                        file,
                    )
                kw.update(CHECKPOINT.arguments(cp, "output.checkpoint", file))
            return cls(**kw)
        except SceneError as err:
            if err.file is None:
                err.file = file
            raise

    def to_dict(self) -> dict:
        """The ``[output]`` table of a scene file."""
        d = OUTPUT.write(self)
        if self.checkpoint_steps is not None or self.checkpoint_seconds is not None:
            d["checkpoint"] = CHECKPOINT.write(self)
        return d
