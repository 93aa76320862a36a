"""Small helpers shared by the commands: words and file names in messages, paths inside the
output folder and step counts."""

from __future__ import annotations

import math
import os
import re
from pathlib import Path

__all__ = ["listing", "plural", "relative", "remove", "resolve", "safe_name", "shorten", "steps_at"]


def plural(count: int, word: str, plural_form: str | None = None) -> str:
    """``"1 body"``, ``"3 bodies"``."""
    if count == 1:
        return f"1 {word}"
    return f"{count} {plural_form or word + 's'}"


def shorten(name: str, longest: int = 60) -> str:
    """``name`` with any path component longer than ``longest`` shortened (for messages)."""
    parts = re.split(r"([/\\])", str(name))
    return "".join(p if len(p) <= longest else f"{p[:24]}...{p[-12:]} ({len(p)} characters)" for p in parts)


def listing(names: list[str], what: str, most: int) -> str:
    """``names`` joined, or, beyond ``most`` of them, a count with the first and the last."""
    if len(names) <= most:
        return ", ".join(shorten(n) for n in names)
    folders = {os.path.dirname(n) for n in names}
    if len(folders) == 1 and "" not in folders:
        where = f" in {folders.pop()}{os.sep}"
        names = [os.path.basename(n) for n in names]
    else:
        where = ""
    return f"{len(names)} {what}{where}: {shorten(names[0])}, {shorten(names[1])}, ..., {shorten(names[-1])}"


def safe_name(name: str) -> str:
    return re.sub(r"[^\w.-]+", "_", name).strip("._") or "scene"


def remove(path: Path) -> None:
    """Remove the file ``path`` if it is there (a temporary file after a failed write)."""
    try:
        path.unlink(missing_ok=True)
    except OSError:
        pass  # not there after all (its folder is gone or a file)


def resolve(folder: Path, name) -> Path:
    p = Path(name)
    return p if p.is_absolute() else folder / p


def relative(path, folder: Path) -> str:
    """``path`` relative to ``folder`` when inside it (summary entries), else as given."""
    try:
        return str(Path(path).resolve().relative_to(folder.resolve()))
    except ValueError:
        return str(path)


def steps_at(time_s: float, dt: float) -> int:
    """The first step whose time is at or after ``time_s`` (with a little slack for rounding)."""
    return max(0, math.ceil(time_s / dt - 1e-9))
