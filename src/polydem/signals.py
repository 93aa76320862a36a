"""Ctrl-C (SIGINT) and SIGTERM in the ``polydem`` command.

A batch scheduler stops a job with SIGTERM (and SIGKILL after a grace period), so SIGTERM is
treated like Ctrl-C. Exit codes follow the shell's convention, 128 + the signal's number: 130 for
SIGINT, 143 for SIGTERM.

* While the command starts (modules import, Warp initialises, the scene loads, kernels compile) a
  signal stops it at once: Python raises KeyboardInterrupt, the command prints one line and exits.
  Inside an import the signal is only noted, and :func:`check` (called after the imports and between
  the start-up phases) stops the command: an exception raised inside an import can leave a module
  half imported, and some libraries catch BaseException around their optional imports (trimesh
  does), which would swallow it and let the run go on to its end.
* While the run steps (:func:`running`), the first signal asks it to stop after the steps under way
  and write its outputs; a second one stops at once (KeyboardInterrupt).
* While the outputs are written (:func:`finishing`), a first signal is noted and ignored.

This module imports nothing heavy, so that ``polydem.__main__`` can install the handlers before
the rest of polydem loads.
"""

from __future__ import annotations

import signal
import sys
import threading

__all__ = [
    "check",
    "exit_code",
    "finishing",
    "install",
    "name",
    "received",
    "running",
    "signum",
    "started",
    "uninstall",
]

EXIT_SIGINT = 130
EXIT_SIGTERM = 143

_STARTING, _RUNNING, _FINISHING = "starting", "running", "finishing"


class _State:
    def __init__(self):
        self.depth = 0
        self.saved: dict = {}
        self.reset()

    def reset(self):
        self.signum = None
        self.count = 0
        self.phase = _STARTING


_state = _State()


def _importing(frame) -> bool:
    while frame is not None:
        if frame.f_code.co_filename.startswith("<frozen importlib"):
            return True
        frame = frame.f_back
    return False


def _handler(signum, frame):
    s = _state
    s.count += 1
    if s.signum is None:
        s.signum = signum
    if s.phase == _STARTING:
        if _importing(frame) and s.count < 3:
            return  # check() stops the command once the import is done
        raise KeyboardInterrupt
    if s.count > 1:
        raise KeyboardInterrupt
    what = "writing the outputs" if s.phase == _FINISHING else "stopping after the steps under way"
    again = " (Ctrl-C again to stop at once)" if signum == signal.SIGINT else ""
    try:
        sys.stderr.write(f"\npolydem: {name(signum)}: {what}{again}\n")
        sys.stderr.flush()
    except (OSError, ValueError):
        pass


def install() -> None:
    """Handle SIGINT and SIGTERM until the matching :func:`uninstall` (calls nest).

    Only in the main thread, and only where Python's defaults are in place (SIGINT raising
    KeyboardInterrupt, SIGTERM ending the process): a signal that the caller ignores or handles
    itself is left alone.
    """
    s = _state
    if s.depth == 0:
        s.reset()
        s.saved = {}
        if threading.current_thread() is threading.main_thread():
            for sig, default in ((signal.SIGINT, signal.default_int_handler), (signal.SIGTERM, signal.SIG_DFL)):
                try:
                    if signal.getsignal(sig) is default:
                        s.saved[sig] = signal.signal(sig, _handler)
                except (ValueError, OSError):
                    pass
    s.depth += 1


def uninstall() -> None:
    """Undo one :func:`install`; the last one puts the previous handlers back."""
    s = _state
    if s.depth == 0:
        return
    s.depth -= 1
    if s.depth == 0:
        for sig, old in s.saved.items():
            try:
                signal.signal(sig, old)
            except (ValueError, OSError):
                pass
        s.saved = {}


def check() -> None:
    """Raise KeyboardInterrupt if a signal came while the command was starting."""
    if _state.signum is not None and _state.phase == _STARTING:
        raise KeyboardInterrupt


def running() -> None:
    """The run steps from now on: a first signal only asks it to stop (see :func:`received`)."""
    check()
    _state.phase = _RUNNING


def finishing() -> None:
    """The outputs are being written: a first signal is ignored."""
    _state.phase = _FINISHING


def started() -> bool:
    """Whether the run has started stepping (:func:`running` was called)."""
    return _state.phase != _STARTING


def received() -> bool:
    """Whether a signal asked the run to stop."""
    return _state.signum is not None


def signum() -> int:
    """The first signal received (SIGINT when none was: a KeyboardInterrupt raised otherwise)."""
    return signal.SIGINT if _state.signum is None else _state.signum


def name(sig: int | None = None) -> str:
    """``"Ctrl-C"`` or ``"SIGTERM"`` (of the first signal received when ``sig`` is None)."""
    sig = signum() if sig is None else sig
    return "SIGTERM" if sig == signal.SIGTERM else "Ctrl-C"


def exit_code() -> int:
    """130 after SIGINT (or a KeyboardInterrupt without a signal), 143 after SIGTERM."""
    return EXIT_SIGTERM if signum() == signal.SIGTERM else EXIT_SIGINT
