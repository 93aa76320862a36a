"""The ``polydem`` command: run, check and render scenes, and describe the installation.

::

    polydem run [SCENE] [--device DEV] [--steps N | --duration T] [--out DIR] [--fps F]
                [--precision P] [--resume CHECKPOINT] [--picture-size WxH] [--vtk] [--quiet]
    polydem validate SCENE [SCENE ...] [--quiet]
    polydem render SOURCE --out IMAGE.png [--scene SCENE] [--frame K] [--width W] [--height H] [--device DEV]
    polydem tap SCENE [--motion NAME] [--margin M] [--lead F] [--device DEV] [--precision P] [--out DIR]
    polydem compress SCENE [--motion NAME ...] [--duration T] [--interval S] [--device DEV] [--out DIR]
    polydem anneal SCENE --mu-fill MU [--mu-final MU] --fill-time T --settle-time T [--material NAME]
    polydem info

One module per command (:mod:`~polydem.cli.run`, :mod:`~polydem.cli.validate`,
:mod:`~polydem.cli.render`, :mod:`~polydem.cli.info`; the packing protocols tap, compress and anneal
in :mod:`~polydem.cli.protocol`), imported only when the command runs, so
that ``polydem --help`` needs neither numpy nor Warp; :mod:`~polydem.cli.parser` holds the options.

``polydem run`` without a scene runs the built-in default scene (:func:`polydem.default_scene.default_scene`).
Progress goes to stderr (one line updated in place on a terminal, one line per 5% of the steps
otherwise); the header and the closing summary go to stdout.

Outputs of ``polydem run`` (in ``--out``, default ``polydem_out/<scene name>/``; the scene's
``[output]`` table names them, relative to that folder):

* a USD animation (``output.usd``; ``trajectory.usdc`` when the scene file does not mention ``usd``,
  none for ``usd = false``). Frame k is the state at simulated time k / fps (``--fps`` or
  ``output.fps``) and has time code k: the run steps in chunks up to each frame time and records
  the first state at or after it.
* the summary JSON (``output.summary``, default ``summary.json``; see :func:`settled_region` for
  the packing fraction and the coordination number).
* pictures (``output.pictures``: frame numbers, or ``"last"`` for the final state, the default;
  ``false`` or ``[]`` for none) as ``pictures/frame_NNNNNN.png`` and ``pictures/last.png``.
* plots of the energies, the contacts and the packing fraction against time, ``energy.png`` and
  ``packing.png``, and of the settled region's measures, ``measures.png`` (force distribution, contact
  normals, packing profile, contact types), when matplotlib is installed (``pip install "polydem[plot]"``).
* checkpoints in ``output.checkpoint.path`` (default ``checkpoints/``): ``step_NNNNNNNNN.npz``
  every ``output.checkpoint.steps`` steps or ``.seconds`` of simulated time (counted from t = 0),
  ``final.npz`` at the end and ``interrupted.npz`` when the run stops early.

Every output stays inside the output folder: the scene's paths are relative to it (absolute
paths and ``..`` are refused). The closing lines name every file written. An output that cannot
be written (a name too long for the file system, a file where a folder should be, no permission)
is a user error found before the run starts where possible (exit code 2); one that fails later is
reported in one line (exit code 1), and the other outputs are still written.

Nothing is lost when a run stops early (Ctrl-C, SIGTERM or a :class:`~polydem.SimulationError`):
the USD file is closed with the frames so far, the summary says ``"interrupted": true`` and why,
and ``interrupted.npz`` holds the state after the last completed step (after a SimulationError,
the last finite state). The first Ctrl-C or SIGTERM (what a batch scheduler sends) stops the run
after the steps under way (at most ``MAX_CHUNK_STEPS``); a second one stops at once. While the
command starts (modules importing, Warp initialising, kernels compiling) either signal stops it at
once with one line (see :mod:`polydem.signals`).

Resuming. ``polydem run SCENE --resume CHECKPOINT`` continues from a checkpoint of the same scene;
``--steps`` and ``--duration`` count from t = 0, so the same command line with ``--resume`` added
ends in the same state, bit for bit (on the same device), as a run that was never interrupted. The
resumed part goes to a new USD file, ``<usd stem>.from_step_<N><suffix>`` (N the checkpoint's
step); its time codes continue those of the first file (frame k keeps time code k). The
checkpoint must come from the same physics (its record of the scene's materials, shapes, walls,
bodies, gravity and time step is compared with the scene's; a difference is an error naming it)
and be sound (every array is checked). Checkpoints written by ``polydem run`` also carry the
record of the run so far, so the summary of a resumed run covers the whole run from t = 0: its
frame history, contact counts, largest overlap, initial energy, wall time, pictures and
checkpoints, and ``parts`` (the steps, folder, USD file and time codes of each part). A checkpoint
without that record (of the older format, or from :func:`polydem.checkpoint.save_checkpoint`
without ``run``) is resumed with a note that the summary covers the resumed part only; one of
the older format, without a record of its physics, with a warning that it cannot be checked.

Exit codes: 0 done; 1 the simulation failed (SimulationError: outputs written, message on stderr),
an output could not be written after the run had started (the others written), or an internal
error (with its traceback); 2 a user error (one message on stderr naming the file or option, the
key and the fix); 130 interrupted by Ctrl-C (SIGINT), 143 stopped by SIGTERM (outputs written
when the run had started).
"""

from __future__ import annotations

import importlib
import sys
from pathlib import Path

from polydem import signals
from polydem.cli.errors import (
    EXIT_FAILED,
    EXIT_INTERRUPTED,
    EXIT_OK,
    EXIT_TERMINATED,
    EXIT_USER_ERROR,
    CliError,
)
from polydem.cli.parser import build_parser

__all__ = [
    "EXIT_FAILED",
    "EXIT_INTERRUPTED",
    "EXIT_OK",
    "EXIT_TERMINATED",
    "EXIT_USER_ERROR",
    "CliError",
    "build_parser",
    "main",
    "settled_region",
]

_COMMANDS = {
    "run": ("polydem.cli.run", "cmd_run"),
    "validate": ("polydem.cli.validate", "cmd_validate"),
    "render": ("polydem.cli.render", "cmd_render"),
    "tap": ("polydem.cli.protocol", "cmd_tap"),
    "compress": ("polydem.cli.protocol", "cmd_compress"),
    "anneal": ("polydem.cli.protocol", "cmd_anneal"),
    "info": ("polydem.cli.info", "cmd_info"),
}


def __getattr__(name: str):
    # settled_region needs numpy, which `polydem --help` does without.
    if name == "settled_region":
        from polydem.cli.diagnostics import settled_region

        return settled_region
    raise AttributeError(f"module 'polydem.cli' has no attribute {name!r}")


def main(argv=None) -> int:
    """Run the ``polydem`` command with ``argv`` (default ``sys.argv[1:]``); returns the exit code."""
    import warnings

    signals.install()
    shown = warnings.showwarning

    def show(message, category, filename, lineno, file=None, line=None):
        # polydem's own warnings (scene, shapes, checkpoints) as one line, like its errors.
        if issubclass(category, UserWarning) and _is_ours(category, filename):
            sys.stdout.flush()
            print(f"polydem: warning: {message}", file=sys.stderr)
        else:
            shown(message, category, filename, lineno, file, line)

    warnings.showwarning = show
    try:
        return _main(argv)
    finally:
        warnings.showwarning = shown
        signals.uninstall()


def _is_ours(category, filename) -> bool:
    package = Path(__file__).resolve().parent.parent  # polydem/, not polydem/cli/
    return category.__module__.startswith("polydem") or Path(filename).resolve().is_relative_to(package)


def _is_user_error(exc: BaseException) -> bool:
    """A CliError or a SceneError (which only polydem.scene raises: no need to import it before)."""
    scene = sys.modules.get("polydem.scene")
    return isinstance(exc, CliError) or (scene is not None and isinstance(exc, scene.SceneError))


def _main(argv) -> int:
    parser = build_parser()
    try:
        try:
            args = parser.parse_args(argv)
        except SystemExit as exc:  # --help
            return int(exc.code or 0) if not isinstance(exc.code, str) else EXIT_USER_ERROR
        except CliError:
            from polydem.distributed.comm import launched_rank

            if launched_rank() != 0:
                return EXIT_USER_ERROR  # under mpiexec every rank parses the same line: rank 0 says it once
            raise
        module, name = _COMMANDS[args.command]
        command = getattr(importlib.import_module(module), name)
        signals.check()
        return command(args)
    except KeyboardInterrupt:  # a signal before the run started, or a second one while it wrote its outputs
        sys.stdout.flush()
        what = "nothing was written" if not signals.started() else "while writing the outputs, some may be missing"
        print(f"polydem: stopped by {signals.name()}; {what}", file=sys.stderr)
        return signals.exit_code()
    except Exception as err:
        if not _is_user_error(err):
            raise
        sys.stdout.flush()
        print(f"polydem: error: {err}", file=sys.stderr)
        return EXIT_USER_ERROR


if __name__ == "__main__":
    sys.exit(main())
