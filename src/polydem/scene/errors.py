"""SceneError, SceneWarning and the wording of "unknown name" messages (did-you-mean, known names)."""

from __future__ import annotations

import difflib
from os import PathLike

MAX_LISTED = 20
"""Most names an "unknown name" message lists."""


class SceneError(ValueError):
    """A user error in a scene: bad value, unknown name, malformed scene file.

    Attributes:
        message: what is wrong and how to fix it.
        key: where, as a dotted path into the scene file, e.g. ``"bodies[3].material"`` or
            ``"materials.steel.k"``; None when the whole file is concerned.
        file: the scene file (as given), or None for scenes built in Python.

    ``str(err)`` reads ``"FILE: KEY: MESSAGE"``, leaving out the parts that are None.
    """

    def __init__(self, message: str, key: str | None = None, file: str | PathLike | None = None):
        super().__init__(message)
        self.message = message
        self.key = key
        self.file = file

    def __str__(self) -> str:
        parts = [str(p) for p in (self.file, self.key) if p not in (None, "")]
        return ": ".join([*parts, self.message])

    def __reduce__(self):
        return (type(self), (self.message, self.key, self.file))


class SceneWarning(UserWarning):
    """A scene that runs but probably not as meant, e.g. bodies that start overlapping moderately.

    :meth:`Scene.validate` issues these with :func:`warnings.warn` (category SceneWarning);
    ``polydem validate`` prints them as ``polydem: warning: ...`` lines.
    """


def did_you_mean(word, candidates) -> str:
    if not isinstance(word, str):
        return ""
    close = difflib.get_close_matches(word, [str(c) for c in candidates], n=3, cutoff=0.6)
    if not close:
        return ""
    return "; did you mean " + " or ".join(repr(c) for c in close) + "?"


def listing(names) -> str:
    names = [str(n) for n in names]
    if len(names) > MAX_LISTED:
        return ", ".join(names[:MAX_LISTED]) + f", ... ({len(names)} in all)"
    return ", ".join(names)


def unknown_name(word, known, what: str, how: str) -> str:
    """Message for an unknown name: did-you-mean plus the known names, or how to define one."""
    known = list(known)
    if not known:
        return f"unknown {what} {word!r}: no {what}s are defined; {how}"
    return f"unknown {what} {word!r}{did_you_mean(word, known) or '.'} Known {what}s: {listing(known)}"
