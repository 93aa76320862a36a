"""Exit codes and the errors of the ``polydem`` command, and one line about a failed write.

Nothing heavy is imported here: ``polydem --help`` loads this module.
"""

from __future__ import annotations

from polydem import signals

__all__ = [
    "EXIT_FAILED",
    "EXIT_INTERRUPTED",
    "EXIT_OK",
    "EXIT_TERMINATED",
    "EXIT_USER_ERROR",
    "CliError",
    "OutputError",
    "why",
]

EXIT_OK = 0
EXIT_FAILED = 1
EXIT_USER_ERROR = 2
EXIT_INTERRUPTED = signals.EXIT_SIGINT
EXIT_TERMINATED = signals.EXIT_SIGTERM


class CliError(Exception):
    """A user error found by the command itself (options, checkpoints, output folders).

    Printed like a :class:`~polydem.SceneError`: ``"FILE: KEY: MESSAGE"`` without the parts that
    are None; the message says how to fix it. The command exits with code 2.
    """

    def __init__(self, message: str, file=None, key: str | None = None):
        super().__init__(message)
        self.message = message
        self.file = file
        self.key = key

    def __str__(self) -> str:
        parts = [str(p) for p in (self.file, self.key) if p not in (None, "")]
        return ": ".join([*parts, self.message])


class OutputError(Exception):
    """An output file could not be written; the message is one line that says why and what to do."""


_ERRNO_FIX = {
    "ENAMETOOLONG": "give a shorter name",
    "EACCES": "check the permissions or give another --out",
    "EPERM": "check the permissions or give another --out",
    "EROFS": "the file system is read-only: give another --out",
    "ENOSPC": "the disk is full: free some space or give another --out",
    "EDQUOT": "the disk quota is used up: free some space or give another --out",
    "ENOTDIR": "a file is in the way of a folder: remove it or give another --out",
    "EEXIST": "a file is in the way of a folder: remove it or give another --out",
    "EISDIR": "a folder is in the way of the file: remove it or give another --out",
}


def why(exc: BaseException) -> str:
    """One line about a failed write: the OS's reason and the fix, or the first line of the error."""
    if isinstance(exc, OSError) and exc.strerror:
        import errno

        code = errno.errorcode.get(exc.errno or 0, "")
        fix = _ERRNO_FIX.get(code)
        return f"{exc.strerror}{'; ' + fix if fix else ''}"
    text = " ".join(str(exc).split())  # pxr errors come on several lines
    return f"{type(exc).__name__}: {text[:300]}" if text else type(exc).__name__
