"""The ``polydem`` command: run, check and render scenes, and describe the installation.

::

    polydem run [SCENE] [--device DEV] [--steps N | --duration T] [--out DIR] [--fps F]
                [--precision P] [--resume CHECKPOINT] [--picture-size WxH] [--vtk] [--quiet]
    polydem validate SCENE [SCENE ...] [--quiet]
    polydem render SOURCE --out IMAGE.png [--scene SCENE] [--frame K] [--width W] [--height H] [--device DEV]
    polydem info

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
  ``packing.png``, when matplotlib is installed (``pip install "polydem[plot]"``).
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
once with one line (see :mod:`polydem._signals`).

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

import argparse
import json
import math
import os
import re
import shlex
import sys
import textwrap
import time
from collections import deque
from pathlib import Path

import numpy as np

from polydem import _signals
from polydem.scene import SceneError

__all__ = ["CliError", "main", "settled_region"]

EXIT_OK = 0
EXIT_FAILED = 1
EXIT_USER_ERROR = 2
EXIT_INTERRUPTED = _signals.EXIT_SIGINT
EXIT_TERMINATED = _signals.EXIT_SIGTERM

DEFAULT_STEPS = 1000
"""Steps of a run when neither the command line nor the scene gives steps or a duration."""

DEFAULT_USD = "trajectory.usdc"
"""USD file of a run whose scene file does not mention ``output.usd``."""

MAX_CHUNK_STEPS = 256
"""Most steps between two checks for Ctrl-C (and progress updates on a terminal)."""

PROGRESS_LINES = 20
"""Progress lines of a run whose stderr is not a terminal (one per 5% of the steps)."""

TTY_REFRESH_S = 0.25
"""Shortest wall time between two updates of the progress line on a terminal [s]."""

FIRST_LINE_S = 10.0
LINE_EVERY_S = 60.0
"""Off a terminal, the first progress line comes after at most FIRST_LINE_S of wall time, the
others at most LINE_EVERY_S apart (besides one per 5% of the steps) [s]."""

ETA_AFTER_S = 0.5
"""The time left is shown once the steps after the first chunk took this much wall time [s]."""

ETA_WINDOW = 0.3
"""The time left follows the rate over this fraction of the wall time so far (the recent past)."""

SETTLED_PERCENTILE = 80.0
"""The settled region reaches up to this percentile of the free bodies' centre heights."""

SETTLED_MARGIN = 2.0
"""The settled region keeps this many mean body diameters from the sides of the free bodies' box."""

_USD_SUFFIXES = (".usd", ".usda", ".usdc")


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


# ---------------------------------------------------------------------- Warp and devices

_WARP_NOTES: list[str] = []


def _warp():
    """Warp, initialised with its info messages off.

    Warp's native library prints a warning on stderr when it finds no CUDA driver, which on a
    CPU-only machine would come before every message of this command; it is kept for ``polydem
    info`` instead (other native messages are passed on).
    """
    import warp as wp

    wp.config.log_level = max(wp.config.log_level, wp.LOG_WARNING)
    context = getattr(getattr(wp, "_src", None), "context", None)
    if context is None or getattr(context, "runtime", True) is not None:
        wp.init()  # already initialised, or a Warp whose internals differ: nothing to capture
        return wp
    import tempfile

    try:
        sys.stderr.flush()
        saved = os.dup(2)
    except (OSError, ValueError):
        wp.init()
        return wp
    with tempfile.TemporaryFile() as tmp:
        os.dup2(tmp.fileno(), 2)
        try:
            wp.init()
        finally:
            os.dup2(saved, 2)
            os.close(saved)
        tmp.seek(0)
        text = tmp.read().decode(errors="replace")
    for line in text.splitlines():
        if "NVIDIA CUDA driver" in line:
            _WARP_NOTES.append(line.strip())
        elif line.strip():
            print(line, file=sys.stderr)
    return wp


def _device(name, *, file=None, key="--device"):
    """The Warp device ``name`` (None: Warp's default), or a CliError when this machine lacks it."""
    wp = _warp()
    if name is None:
        return wp.get_device()
    aliases = [d.alias for d in wp.get_devices()]
    if not re.fullmatch(r"cpu|cuda(:\d+)?", str(name)):
        raise CliError(
            f'unknown device {name!r}; give "cpu", "cuda" (the default GPU) or "cuda:N" (available here: '
            f"{', '.join(aliases)})",
            file,
            key,
        )
    if name == "cuda" and wp.get_cuda_device_count() > 0:
        return wp.get_device("cuda")
    if name not in aliases:
        fix = "use --device cpu" if key == "--device" else "override it with --device cpu"
        raise CliError(
            f"device {name!r} is not available on this machine (available: {', '.join(aliases)}); {fix}", file, key
        )
    return wp.get_device(name)


# ---------------------------------------------------------------------- argument types


def _count(what: str, example: str, one: str):
    def parse(text: str) -> int:
        value = None
        try:
            value = int(text, 10)
        except ValueError:
            try:
                f = float(text)
                if math.isfinite(f) and f.is_integer():
                    value = int(f)
            except ValueError:
                pass
        if value is None:
            raise argparse.ArgumentTypeError(f"expected a whole number of {what}, got {text!r}; e.g. {example}")
        if value < 1:
            raise argparse.ArgumentTypeError(f"expected at least 1 {one}, got {value}; e.g. {example}")
        return value

    return parse


def _positive(what: str, example: str):
    def parse(text: str) -> float:
        try:
            value = float(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"expected {what}, got {text!r}; e.g. {example}") from None
        if not (math.isfinite(value) and value > 0.0):
            raise argparse.ArgumentTypeError(f"expected {what} > 0, got {text!r}; e.g. {example}")
        return value

    return parse


def _angle(lowest: float, highest: float, example: str):
    def parse(text: str) -> float:
        try:
            value = float(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"expected an angle in degrees, got {text!r}; e.g. {example}") from None
        if not math.isfinite(value) or not lowest <= value <= highest:
            span = "finite" if math.isinf(lowest) else f"from {lowest:g} to {highest:g}"
            raise argparse.ArgumentTypeError(f"expected an angle {span} degrees, got {text!r}; e.g. {example}")
        return value

    return parse


def _size(text: str) -> tuple[int, int]:
    m = re.fullmatch(r"\s*(\d+)\s*[xX]\s*(\d+)\s*", text)
    if not m or int(m.group(1)) < 1 or int(m.group(2)) < 1:
        raise argparse.ArgumentTypeError(f"expected WIDTHxHEIGHT in pixels, got {text!r}; e.g. 800x600")
    return int(m.group(1)), int(m.group(2))


# ---------------------------------------------------------------------- helpers


def _load_scene(path):
    """The scene file ``path``, or the built-in default scene when ``path`` is None."""
    from polydem.scene import Scene

    if path is None:
        from polydem.default_scene import default_scene

        return default_scene()
    return Scene.from_toml(path)


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


def _usd_setting(scene) -> str | None:
    """The USD file name of a run: ``output.usd``; the default when the scene file does not
    mention it; None for ``usd = false``."""
    if scene.output.usd is not None:
        return scene.output.usd
    if "usd" in (_output_keys(scene) or ()):
        return None  # usd = false
    return DEFAULT_USD


def _pictures_setting(scene):
    """The pictures of a run: ``output.pictures``; ``"last"`` (a picture of the final state) when
    the scene file does not mention it; ``()`` for ``pictures = false`` or ``[]``."""
    if scene.output.pictures or "pictures" in (_output_keys(scene) or ()):
        return scene.output.pictures
    return "last"


class _OutputError(Exception):
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


def _why(exc: BaseException) -> str:
    """One line about a failed write: the OS's reason and the fix, or the first line of the error."""
    if isinstance(exc, OSError) and exc.strerror:
        import errno

        code = errno.errorcode.get(exc.errno or 0, "")
        fix = _ERRNO_FIX.get(code)
        return f"{exc.strerror}{'; ' + fix if fix else ''}"
    text = " ".join(str(exc).split())  # pxr errors come on several lines
    return f"{type(exc).__name__}: {text[:300]}" if text else type(exc).__name__


def _remove(path: Path) -> None:
    """Remove the file ``path`` if it is there (a temporary file after a failed write)."""
    try:
        path.unlink(missing_ok=True)
    except OSError:
        pass  # not there after all (its folder is gone or a file)


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


def _resolve(folder: Path, name) -> Path:
    p = Path(name)
    return p if p.is_absolute() else folder / p


def _rel(path, folder: Path) -> str:
    """``path`` relative to ``folder`` when inside it (summary entries), else as given."""
    try:
        return str(Path(path).resolve().relative_to(folder.resolve()))
    except ValueError:
        return str(path)


def _n(count: int, word: str, plural: str | None = None) -> str:
    """``"1 body"``, ``"3 bodies"``."""
    if count == 1:
        return f"1 {word}"
    return f"{count} {plural or word + 's'}"


def _short(name: str, longest: int = 60) -> str:
    """``name`` with any path component longer than ``longest`` shortened (for messages)."""
    parts = re.split(r"([/\\])", str(name))
    return "".join(p if len(p) <= longest else f"{p[:24]}...{p[-12:]} ({len(p)} characters)" for p in parts)


def _listing(names: list[str], what: str, most: int) -> str:
    """``names`` joined, or, beyond ``most`` of them, a count with the first and the last."""
    if len(names) <= most:
        return ", ".join(_short(n) for n in names)
    folders = {os.path.dirname(n) for n in names}
    if len(folders) == 1 and "" not in folders:
        where = f" in {folders.pop()}{os.sep}"
        names = [os.path.basename(n) for n in names]
    else:
        where = ""
    return f"{len(names)} {what}{where}: {_short(names[0])}, {_short(names[1])}, ..., {_short(names[-1])}"


def _safe_name(name: str) -> str:
    return re.sub(r"[^\w.-]+", "_", name).strip("._") or "scene"


def _finite(x):
    """JSON-safe: non-finite floats become None, numpy scalars plain Python."""
    if isinstance(x, dict):
        return {k: _finite(v) for k, v in x.items()}
    if isinstance(x, list | tuple):
        return [_finite(v) for v in x]
    if isinstance(x, np.integer):
        return int(x)
    if isinstance(x, float | np.floating):
        x = float(x)
        return x if math.isfinite(x) else None
    return x


def _steps_at(time_s: float, dt: float) -> int:
    """The first step whose time is at or after ``time_s`` (with a little slack for rounding)."""
    return max(0, math.ceil(time_s / dt - 1e-9))


def _body_volumes(scene) -> np.ndarray:
    vol = np.array([scene.shapes[name].volume for name in scene.shape_names], dtype=np.float64)
    return vol[np.asarray(scene.body_shape)]


def _relative_overlaps(contacts, volumes) -> np.ndarray:
    """Overlap volume of each contact over the smaller body's volume (the body's own for walls)."""
    a = contacts["body_a"]
    b = contacts["body_b"]
    va = volumes[a]
    vb = np.where(b >= 0, volumes[np.maximum(b, 0)], np.inf)
    return contacts["volume"] / np.minimum(va, vb)


def _perpendicular(up: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Two horizontal unit axes (x and y for up = z)."""
    axis = np.eye(3)[int(np.argmin(np.abs(up)))]
    e1 = axis - up * float(axis @ up)
    e1 /= np.linalg.norm(e1)
    return e1, np.cross(up, e1)


def settled_region(scene, state, contacts) -> dict:
    """Packing fraction and coordination number of the settled part of a pile.

    Definition (heights along minus gravity, +z when there is none; "horizontal" perpendicular to it):

    * D is the mean volume-equivalent diameter (6 V / pi)^(1/3) of the free bodies;
    * the region is a box: horizontally, the bounding box of the free bodies' centres shrunk by
      ``SETTLED_MARGIN`` (2) D on every side (away from the side walls); vertically, from the lowest
      point of any free body (the floor) up to the ``SETTLED_PERCENTILE`` (80th) percentile of the
      free bodies' centre heights (below the loose top layer);
    * the bodies in the region are the free bodies whose centres lie in it;
    * packing fraction = the sum of their volumes / the volume of the box (bodies cut by the top
      and side faces count whole or not at all, which cancels on average);
    * coordination number = the mean number of contacts of a body in the region, counting every
      contact (with a free, fixed or kinematic body, or a wall plane); ``coordination_number_free``
      counts only the contacts with other free bodies.

    Returns a dict with ``bodies`` (in the region), ``packing_fraction``, ``coordination_number``,
    ``coordination_number_free``, ``diameter`` (D [m]), ``lower`` and ``upper`` (the box: horizontal
    axis 1, horizontal axis 2, height [m]); the three values are None, with a ``note``, when the
    region is empty (a bed narrower than about 4 D, or too few bodies).
    """
    from polydem.quaternions import quat_to_matrix

    kind = np.asarray(scene.body_kind)
    free = kind == 0
    out = {
        "bodies": 0,
        "packing_fraction": None,
        "coordination_number": None,
        "coordination_number_free": None,
    }
    if not free.any():
        out["note"] = "no free bodies"
        return out
    g = np.asarray(scene.gravity, dtype=np.float64)
    up = -g / np.linalg.norm(g) if np.linalg.norm(g) > 0.0 else np.array([0.0, 0.0, 1.0])
    e1, e2 = _perpendicular(up)
    pos = np.asarray(state["body_position"], dtype=np.float64)
    quat = np.asarray(state["body_orientation"], dtype=np.float64)
    volumes = _body_volumes(scene)
    body_shape = np.asarray(scene.body_shape)
    idx = np.flatnonzero(free)
    diameter = float(np.mean((6.0 * volumes[idx] / math.pi) ** (1.0 / 3.0)))
    h, u, w = pos[idx] @ up, pos[idx] @ e1, pos[idx] @ e2
    floor = np.inf
    for s, name in enumerate(scene.shape_names):
        verts = np.asarray(scene.shapes[name].vertices, dtype=np.float64)
        members = idx[body_shape[idx] == s]
        for k in range(0, len(members), 65536):
            rows = members[k : k + 65536]
            up_body = np.einsum("nji,j->ni", quat_to_matrix(quat[rows]), up)  # R^T up
            lowest = pos[rows] @ up + (up_body @ verts.T).min(axis=1)
            floor = min(floor, float(lowest.min()))
    top = float(np.percentile(h, SETTLED_PERCENTILE))
    margin = SETTLED_MARGIN * diameter
    lower = np.array([u.min() + margin, w.min() + margin, floor])
    upper = np.array([u.max() - margin, w.max() - margin, top])
    out.update(diameter=diameter, lower=lower.tolist(), upper=upper.tolist())
    if not np.all(upper > lower):
        out["note"] = (
            f"no settled region: the free bodies span less than {2 * SETTLED_MARGIN:g} mean diameters "
            "horizontally (or do not form a bed)"
        )
        return out
    inside = (u >= lower[0]) & (u <= upper[0]) & (w >= lower[1]) & (w <= upper[1]) & (h <= upper[2])
    members = idx[inside]
    out["bodies"] = int(len(members))
    if not len(members):
        out["note"] = "no free body has its centre in the settled region"
        return out
    n = len(kind)
    a, b = contacts["body_a"], contacts["body_b"]
    count = np.bincount(a, minlength=n) + np.bincount(b[b >= 0], minlength=n)
    both = (b >= 0) & free[a] & free[np.maximum(b, 0)]
    count_free = np.bincount(a[both], minlength=n) + np.bincount(b[both], minlength=n)
    out["packing_fraction"] = float(volumes[members].sum() / np.prod(upper - lower))
    out["coordination_number"] = float(count[members].mean())
    out["coordination_number_free"] = float(count_free[members].mean())
    return out


def _fixed_pose_mismatch(scene, positions) -> int | None:
    """Index of a fixed body whose position is not the scene's (a state of another scene), or None.

    Fixed bodies never move, so every state of this scene holds their initial positions exactly
    (as float32, which checkpoints and USD files keep).
    """
    fixed = np.flatnonzero(np.asarray(scene.body_kind) == 1)
    if not len(fixed):
        return None
    expect = np.asarray(scene.body_position, dtype=np.float64)[fixed].astype(np.float32)
    got = np.asarray(positions, dtype=np.float64)[fixed].astype(np.float32)
    bad = np.flatnonzero(np.any(got != expect, axis=1))
    return int(fixed[bad[0]]) if len(bad) else None


def _check_poses(path, positions, scene, scene_arg, what: str, fix: str, key=None) -> None:
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


def _read_checkpoint(path: Path, key=None):
    """The checked :class:`polydem.checkpoint.Checkpoint` in ``path`` (CliError naming what is wrong)."""
    from polydem.checkpoint import CheckpointError, read_checkpoint

    try:
        return read_checkpoint(path)
    except CheckpointError as err:
        raise CliError(err.message, path, key) from None
    except OSError as err:
        raise CliError(
            f"cannot read the checkpoint ({err.strerror or err}); check the path and its permissions", path, key
        ) from None


def _read_checkpoint_poses(path: Path) -> np.ndarray:
    """The (N, 7) body poses [px, py, pz, qx, qy, qz, qw] of a checkpoint (CliError if it is not one)."""
    return _read_checkpoint(path).arrays["body_q"].astype(np.float64)


class _Poses:
    """What :func:`polydem.render.render_simulation` reads of a Simulation, for poses from a file."""

    def __init__(self, scene, positions, orientations, device):
        from types import SimpleNamespace

        self.device = device
        self.model = SimpleNamespace(
            scene=scene,
            shapes=[scene.shapes[name] for name in scene.shape_names],
            body_flags_np=np.asarray(scene.body_kind),
        )
        self._state = {
            "body_position": np.asarray(positions, dtype=np.float64),
            "body_orientation": np.asarray(orientations, dtype=np.float64),
        }

    def state(self):
        return self._state


# ---------------------------------------------------------------------- progress


class _Progress:
    """Progress on stderr: one line updated in place on a terminal, else one line per 5% (and at
    least one a minute); both with the wall time left once it can be estimated."""

    def __init__(self, stream, start: int, target: int, dt: float, enabled: bool):
        self.stream = stream
        self.start = start
        self.target = target
        self.dt = dt
        self.enabled = enabled
        try:
            self.tty = bool(stream.isatty())
        except (AttributeError, ValueError):
            self.tty = False
        self.t0 = time.perf_counter()
        self.last = -math.inf
        self.last_line = self.t0  # wall time of the last line written (not on a terminal)
        self.lines = 0
        self.last_steps = None
        self.width = 0
        self.samples: deque = deque()  # (wall time, steps) after each chunk, over the recent past
        self.marks = [start + math.ceil(j * (target - start) / PROGRESS_LINES) for j in range(1, PROGRESS_LINES + 1)]

    def next_mark(self, steps: int) -> int | None:
        """The next step at which a line is due (None on a terminal: lines follow the wall clock)."""
        if not self.enabled or self.tty:
            return None
        later = [m for m in self.marks if m > steps]
        return later[0] if later else None

    def sample(self, steps: int, now: float) -> None:
        """Note the progress after a chunk; keep the samples of the last ETA_WINDOW of the run."""
        samples = self.samples
        samples.append((now, steps))
        window = max(ETA_AFTER_S, ETA_WINDOW * (now - samples[0][0]))
        while len(samples) > 2 and samples[1][0] <= now - window:
            samples.popleft()

    def eta(self, steps: int, now: float) -> float | None:
        """Wall time left [s] at the rate of the recent past (a pour slows down as its contacts grow;
        the first chunk, with the start-up costs, is left out); None until it can be estimated."""
        if not self.samples:
            return None
        t_ref, s_ref = self.samples[0]
        if steps <= s_ref or now - t_ref < ETA_AFTER_S:
            return None
        return (self.target - steps) * (now - t_ref) / (steps - s_ref)

    def update(self, sim, force=False) -> None:
        if not self.enabled:
            return
        steps = sim.steps_done
        now = time.perf_counter()
        self.sample(steps, now)
        if self.tty:
            if not force and now - self.last < TTY_REFRESH_S:
                return
        else:
            due = any(self.start < m <= steps for m in self.marks)
            gap = now - self.last_line
            if not (due or force or gap >= (LINE_EVERY_S if self.lines else FIRST_LINE_S)):
                return
            self.marks = [m for m in self.marks if m > steps]
        self.last = now
        self.last_steps = steps
        energy = sim.energy()
        contacts = len(sim.contacts()["volume"])
        rate = (steps - self.start) / max(now - self.t0, 1e-9)
        frac = (steps - self.start) / max(self.target - self.start, 1)
        t_end = self.target * self.dt
        left = self.eta(steps, now)
        if steps >= self.target:
            left_text = f"  took {_duration(now - self.t0)}"
        else:
            left_text = f"  {_duration(left)} left" if left is not None else ""
        if self.tty:
            bar = "#" * int(round(20 * frac))
            line = (
                f"  [{bar:<20}] {100 * frac:5.1f}%  t {sim.time:.4g}/{t_end:.4g} s  {rate:8.1f} steps/s{left_text}  "
                f"{contacts} contacts  kinetic {energy['kinetic']:.3e} J"
            )
            pad = max(0, self.width - len(line))
            self.width = len(line)
            self.stream.write("\r" + line + " " * pad)
        else:
            self.stream.write(
                f"  {100 * frac:5.1f}%  t = {sim.time:.4g} of {t_end:.4g} s  step {steps}/{self.target}  "
                f"{rate:.1f} steps/s{left_text}  {contacts} contacts  kinetic {energy['kinetic']:.3e} J\n"
            )
            self.last_line = now
            self.lines += 1
        self.stream.flush()

    def finish(self, sim=None) -> None:
        """Ends the line on a terminal, after a last update at the state of ``sim`` (if given)."""
        if sim is not None and self.enabled and self.tty and self.last_steps != sim.steps_done:
            self.update(sim, force=True)
        if self.enabled and self.tty and self.width:
            self.stream.write("\n")
            self.stream.flush()
            self.width = 0


def _duration(seconds: float) -> str:
    """``"4.2 s"``, ``"42 s"``, ``"3 min 05 s"``, ``"2 h 07 min"``."""
    if seconds < 9.95:
        return f"{max(0.0, seconds):.1f} s"
    s = int(round(seconds))
    if s < 60:
        return f"{s} s"
    if s < 3600:
        return f"{s // 60} min {s % 60:02d} s"
    return f"{s // 3600} h {s % 3600 // 60:02d} min"


def _roll_back(sim) -> bool:
    """Bring ``sim`` back to a consistent state after an exception inside ``Simulation.step``.

    A step interrupted part-way through a chunk has advanced the device state beyond
    ``sim.steps_done`` (and a SimulationError leaves a non-finite state); the copy saved at the
    start of that chunk is restored. Returns whether the state now matches ``sim.steps_done``.
    """
    try:
        if int(sim.step_count.numpy()[0]) == sim.steps_done and np.all(np.isfinite(sim.body_q.numpy())):
            return True
        saved = getattr(sim, "_saved", None)
        if saved is None or int(saved["step"].numpy()[0]) != sim.steps_done:
            return False
        sim._restore()
        return int(sim.step_count.numpy()[0]) == sim.steps_done and bool(np.all(np.isfinite(sim.body_q.numpy())))
    except Exception:
        return False


# ---------------------------------------------------------------------- polydem run


class _Run:
    """One ``polydem run``: the schedule of frames, pictures and checkpoints, and the outputs."""

    def __init__(self, args, scene, sim, out_dir: Path, target: int, resumed_from):
        self.args = args
        self.scene = scene
        self.sim = sim
        self.out_dir = out_dir
        self.target = target
        self.resumed_from = resumed_from
        self.start = sim.steps_done
        self.dt = sim.dt
        o = scene.output
        self.fps = args.fps if args.fps is not None else o.fps
        self.frame_dt = 1.0 / self.fps
        self.pictures = _pictures_setting(scene)
        self.picture_size = args.picture_size
        self.cp_steps = o.checkpoint_steps
        self.cp_seconds = o.checkpoint_seconds
        paths = _output_paths(scene, out_dir)
        self.cp_dir = paths["output.checkpoint.path"]
        self.summary_path = paths.get("output.summary")
        self.usd_path = paths.get("output.usd")
        if self.usd_path is not None and resumed_from is not None:
            p = self.usd_path
            self.usd_path = p.with_name(f"{p.stem}.from_step_{self.start}{p.suffix}")
        self.volumes = _body_volumes(scene)
        self.recorder = None
        self.vtk = None  # the VtkWriter, made by _execute when VTK output is on (--vtk or output.vtk)
        self.vtk_dir = out_dir / "vtk" if (args.vtk or o.vtk) else None
        self.usd_failed = False
        self.errors: list[str] = []  # outputs that could not be written (one line each)
        self.plot_files: list[str] = []
        self.summary_written = False
        self.frame = self._first_frame(self.start)
        self.frame_contacts: list[int] = []
        self.history: dict[str, list] = {
            k: []
            for k in ("time", "kinetic", "contact", "gravity", "dissipated", "total", "contacts", "packing_fraction")
        }
        self.frame_overlap = 0.0
        self.picture_files: list[str] = []
        self.checkpoints: list[str] = []
        self.cp_index = self._first_checkpoint(self.start)
        self.earlier = None  # the record of the run up to the checkpoint resumed from (continue_record)
        self.usd_codes: list[float] = []  # time codes of the first and last frame of this part's USD file
        self.t0 = time.perf_counter()

    def continue_record(self, checkpoint) -> None:
        """Continue the record of the run that wrote ``checkpoint`` (its history, contact counts,
        largest overlap, initial energy, wall time and files), so the summary covers the whole run."""
        rec = checkpoint.run
        if rec is None:
            return
        self.earlier = rec
        self.history = {k: list(rec["history"][k]) for k in _HISTORY_KEYS}
        self.frame_contacts = list(rec["frame_contacts"])
        self.frame_overlap = float(rec["frame_overlap"])

    def run_record(self, writing=None) -> dict:
        """The record of the run up to now, kept in its checkpoints (``writing``: the checkpoint
        being written). Paths are absolute, so a run resumed into another folder still finds them."""
        e = self.earlier or {}

        def absolute(names):
            return [str(_resolve(self.out_dir, p).resolve()) for p in names]

        wall = time.perf_counter() - self.t0
        checkpoints = [*e.get("checkpoints", []), *absolute(self.checkpoints)]
        if writing is not None:
            checkpoints.append(str(Path(writing).resolve()))
        return _finite(
            {
                "version": RUN_RECORD_VERSION,
                "fps": self.fps,
                "history": self.history,
                "frame_contacts": self.frame_contacts,
                "frame_overlap": self.frame_overlap,
                "energy_initial": self.energy_initial,
                "wall_time": e.get("wall_time", 0.0) + wall,
                "pictures": [*e.get("pictures", []), *absolute(self.picture_files)],
                "checkpoints": list(dict.fromkeys(checkpoints)),
                "parts": [*e.get("parts", []), self.part(wall)],
            }
        )

    def part(self, wall) -> dict:
        """This part of the run (from the start or the checkpoint resumed from, to now)."""
        rec = self.recorder
        return {
            "from_step": self.start,
            "to_step": self.sim.steps_done,
            "folder": str(self.out_dir.resolve()),
            "resumed_from": str(Path(self.resumed_from).resolve()) if self.resumed_from is not None else None,
            "usd": str(self.usd_path.resolve()) if self.usd_path is not None else None,
            "usd_frames": rec.frames if rec is not None else 0,
            "usd_time_codes": [self.usd_codes[0], self.usd_codes[-1]] if self.usd_codes else None,
            "wall_time": wall,
        }

    # -- schedule (all in absolute steps from t = 0)

    def frame_step(self, k: int) -> int:
        return _steps_at(k * self.frame_dt, self.dt)

    def _first_frame(self, steps: int) -> int:
        k = max(0, math.floor(steps * self.dt / self.frame_dt) - 1)
        while self.frame_step(k) < steps:
            k += 1
        return k

    def cp_step(self, j: int) -> int | None:
        if self.cp_steps is not None:
            return j * self.cp_steps
        if self.cp_seconds is not None:
            return _steps_at(j * self.cp_seconds, self.dt)
        return None

    def _first_checkpoint(self, steps: int) -> int:
        j = 1
        if self.cp_steps is not None:
            j = steps // self.cp_steps + 1
        elif self.cp_seconds is not None:
            j = max(1, math.floor(steps * self.dt / self.cp_seconds))
            while self.cp_step(j) <= steps:
                j += 1
        return j

    # -- events

    def record_frames(self) -> None:
        """Record frame ``self.frame`` (and any others due at this step) when the run is at its step."""
        sim = self.sim
        steps = sim.steps_done
        if self.frame_step(self.frame) != steps:
            return
        contacts = sim.contacts()
        times = self.history["time"]
        if not times or sim.time > times[-1] + 0.5 * self.dt:  # a resumed run starts at a frame it may hold
            self.record_history(contacts)
        rec = self.recorder
        if rec is not None and (rec.last_time_code is None or rec.time_code(sim.time) > rec.last_time_code):
            try:
                rec.record_simulation(sim)  # saves the file now and then
            except Exception as exc:
                self.usd_failed = True
                raise _OutputError(f"cannot write the USD file {self.rel(self.usd_path)}: {_why(exc)}") from exc
            self.usd_codes = [*self.usd_codes[:1], rec.last_time_code]
        if self.vtk is not None and (self.vtk.last_index is None or self.frame > self.vtk.last_index):
            try:
                self.vtk.record(sim.time, sim.state(), contacts, index=self.frame)
            except OSError as exc:
                raise _OutputError(f"cannot write the VTK files in {self.rel(self.vtk_dir)}: {_why(exc)}") from exc
        while self.frame_step(self.frame) <= steps:
            if isinstance(self.pictures, tuple) and self.frame in self.pictures:
                self.picture(f"frame_{self.frame:06d}.png")
            self.frame += 1

    def record_history(self, contacts) -> None:
        sim = self.sim
        self.frame_contacts.append(len(contacts["volume"]))
        energy = sim.energy()
        region = settled_region(sim.model.scene, sim.state(), contacts)
        self.history["time"].append(sim.time)
        for key in _ENERGY_KEYS:
            self.history[key].append(energy[key])
        self.history["contacts"].append(len(contacts["volume"]))
        self.history["packing_fraction"].append(region.get("packing_fraction"))
        if len(contacts["volume"]):
            self.frame_overlap = max(self.frame_overlap, float(_relative_overlaps(contacts, self.volumes).max()))

    def rel(self, path) -> str:
        """``path`` as the closing lines and the summary name it: relative to the output folder."""
        return _short(_rel(path, self.out_dir))

    def picture(self, name: str) -> None:
        from polydem.render import render_simulation

        path = self.out_dir / "pictures" / name
        width, height = self.picture_size
        try:
            path.parent.mkdir(parents=True, exist_ok=True)
            render_simulation(self.sim, path, width=width, height=height)
        except OSError as exc:
            raise _OutputError(f"cannot write the picture {self.rel(path)}: {_why(exc)}") from exc
        self.picture_files.append(_rel(path, self.out_dir))

    def checkpoint(self, name: str) -> Path:
        from polydem.checkpoint import save_checkpoint

        path = self.cp_dir / name
        try:
            self.cp_dir.mkdir(parents=True, exist_ok=True)
            save_checkpoint(self.sim, path, run=self.run_record(writing=path))
        except OSError as exc:
            _remove(Path(f"{path}.tmp.npz"))  # save_checkpoint's temporary file
            raise _OutputError(f"cannot write the checkpoint {self.rel(path)}: {_why(exc)}") from exc
        self.checkpoints.append(_rel(path, self.out_dir))
        return path

    def attempt(self, write, *args):
        """``write(*args)``; an output that cannot be written is noted in ``errors`` (returns None)."""
        try:
            return write(*args)
        except _OutputError as exc:
            self.errors.append(str(exc))
            return None

    def periodic_checkpoint(self) -> None:
        steps = self.sim.steps_done
        due = self.cp_step(self.cp_index)
        if due is None or due > steps:
            return
        self.checkpoint(f"step_{steps:09d}.npz")
        while self.cp_step(self.cp_index) <= steps:
            self.cp_index += 1

    def next_stop(self, progress: _Progress) -> int:
        steps = self.sim.steps_done
        stops = [self.target, steps + MAX_CHUNK_STEPS, self.frame_step(self.frame)]
        cp = self.cp_step(self.cp_index)
        if cp is not None:
            stops.append(cp)
        mark = progress.next_mark(steps)
        if mark is not None:
            stops.append(mark)
        return min(s for s in stops if s > steps)

    # -- the run

    def execute(self, out, err) -> int:
        """Run to the target step; whatever stops the run, write the outputs. Returns the exit code."""
        self.out_dir.mkdir(parents=True, exist_ok=True)
        progress = _Progress(err, self.start, self.target, self.dt, enabled=not self.args.quiet)
        energy = self.sim.energy()
        self.energy_initial = energy if self.earlier is None else self.earlier["energy_initial"]
        self.energy_at_start = energy
        self.t0 = t0 = time.perf_counter()
        return self._execute(out, err, progress, t0)

    def _open_recorder(self):
        from polydem.usd import UsdRecorder

        try:
            rec = UsdRecorder(self.usd_path, self.scene, fps=self.fps, frame_dt=self.frame_dt)
        except Exception as exc:  # nothing has run yet: the user can fix it and start again
            raise CliError(f"cannot write the USD file: {_why(exc)}", self.usd_path, "output.usd") from None
        rec.set_metadata(**self.scene_metadata())
        return rec

    def scene_metadata(self) -> dict:
        """What the USD file and the summary record of the scene, so that ``polydem render`` finds it."""
        if self.args.scene is None:
            return {"default_scene": True}
        return {"scene_file": str(Path(self.args.scene).resolve())}

    def _execute(self, out, err, progress, t0) -> int:
        from polydem.simulation import SimulationError

        sim = self.sim
        reason = None
        failure = None
        internal = None
        status = EXIT_OK
        _signals.running()
        try:
            if self.usd_path is not None:
                self.recorder = self._open_recorder()
            if self.vtk_dir is not None:
                from polydem.vtk import VtkWriter

                self.vtk = VtkWriter(self.vtk_dir, self.scene, resume=self.resumed_from is not None)
            self.record_frames()
            while sim.steps_done < self.target:
                sim.step(self.next_stop(progress) - sim.steps_done)
                self.record_frames()
                self.periodic_checkpoint()
                progress.update(sim)
                if _signals.received():
                    raise KeyboardInterrupt
        except CliError:
            raise
        except KeyboardInterrupt:
            status = _signals.exit_code()
            reason = "interrupted by the user (Ctrl-C)" if status == EXIT_INTERRUPTED else "stopped by SIGTERM"
        except SimulationError as exc:
            reason = f"SimulationError: {exc}"
            failure = f"the simulation failed: {exc}"
            status = EXIT_FAILED
        except _OutputError as exc:
            reason = f"an output could not be written: {exc}"
            self.errors.append(str(exc))
            status = EXIT_FAILED
        except Exception as exc:
            reason = f"internal error: {type(exc).__name__}: {exc}"
            internal = exc
            status = EXIT_FAILED
        finally:
            _signals.finishing()
            if self.recorder is not None:
                try:
                    self.recorder.close()  # the frames so far are kept, whatever happened
                except Exception as exc:
                    if not self.usd_failed:
                        self.errors.append(f"cannot save the USD file {self.rel(self.usd_path)}: {_why(exc)}")
                    self.usd_failed = True
        try:
            self._finish(out, err, progress, t0, reason, status)
        except Exception:
            if internal is None:
                raise
            err.write("polydem: the outputs could not be completed after the internal error below\n")
        if internal is not None:
            raise internal
        errors = ([failure] if failure else []) + self.errors
        if errors:
            more = f" (and {_n(len(errors) - 1, 'other error')}: see the lines above)" if len(errors) > 1 else ""
            err.write(f"polydem: error: {errors[0]}{more}\n")
            err.flush()
            if status == EXIT_OK:
                status = EXIT_FAILED
        return status

    def _finish(self, out, err, progress, t0, reason, status) -> None:
        """Final checkpoint and picture, plots, the summary, and the closing lines (also after an interruption)."""
        sim = self.sim
        wall = time.perf_counter() - t0
        notes = []
        consistent = True if reason is None else _roll_back(sim)
        progress.finish(sim if consistent else None)
        cp_path = None
        if consistent:
            cp_path = self.attempt(self.checkpoint, "final.npz" if reason is None else "interrupted.npz")
            if self.pictures == "last":
                self.attempt(self.picture, "last.png")
        else:
            notes.append("no checkpoint: the state could not be brought back to a completed step")
        from polydem.plots import write_plots

        try:
            plots = write_plots(self.history, self.out_dir)
        except OSError as exc:
            self.errors.append(f"cannot write the plots: {_why(exc)}")
            plots = []
        except Exception as exc:  # matplotlib itself: the plots are an extra, the run is fine
            plots = f"no plots: matplotlib failed ({_why(exc)})"
        if isinstance(plots, str):
            notes.append(plots)
            plots = []
        self.plot_files = [_rel(p, self.out_dir) for p in plots]
        summary = self.summary(wall, reason, notes, consistent)
        summary["outputs"]["plots"] = self.plot_files
        if self.errors:
            summary["not_written"] = list(self.errors)
        summary["history"] = self.history
        self.summary_written = False
        if self.summary_path is not None:
            tmp = self.summary_path.with_name(self.summary_path.name + ".tmp")
            try:
                self.summary_path.parent.mkdir(parents=True, exist_ok=True)
                tmp.write_text(json.dumps(_finite(summary), indent=1) + "\n")
                os.replace(tmp, self.summary_path)
                self.summary_written = True
            except OSError as exc:
                self.errors.append(f"cannot write the summary {self.rel(self.summary_path)}: {_why(exc)}")
                _remove(tmp)
        self.report(out, err, summary, cp_path, reason, status)

    def summary(self, wall, reason, notes, consistent) -> dict:
        from polydem import __version__

        sim = self.sim
        scene = self.scene
        kind = np.asarray(scene.body_kind)
        run_steps = sim.steps_done - self.start
        energy = sim.energy() if consistent else None
        contacts = sim.contacts() if consistent else None
        rel = _relative_overlaps(contacts, self.volumes) if contacts is not None else np.zeros(0)
        largest = None
        if len(rel):
            i = int(np.argmax(rel))
            b = int(contacts["body_b"][i])
            largest = {
                "relative": float(rel[i]),
                "volume": float(contacts["volume"][i]),
                "body_a": int(contacts["body_a"][i]),
                "body_b": b if b >= 0 else None,
                "wall": -1 - b if b < 0 else None,
            }
        frames = self.frame_contacts
        e = self.earlier or {}
        folder = self.out_dir
        parts = [dict(p) for p in [*e.get("parts", []), self.part(wall)]]
        for p in parts:
            for k in ("usd", "resumed_from"):
                if p.get(k) is not None:
                    p[k] = _rel(p[k], folder)
        summary = {
            "polydem": __version__,
            "scene": scene.name,
            "scene_file": self.scene_metadata().get("scene_file"),
            "default_scene": self.args.scene is None,
            "device": str(sim.device),
            "precision": scene.precision,
            "interrupted": reason is not None,
            "reason": reason,
            "resumed_from": str(self.resumed_from) if self.resumed_from is not None else None,
            "resumed_at_step": self.start if self.resumed_from is not None else None,
            "history_from_step": parts[0]["from_step"],
            "parts": parts,
            "steps": sim.steps_done,
            "steps_this_run": run_steps,
            "target_steps": self.target,
            "dt": self.dt,
            "simulated_time": sim.time,
            "wall_time": e.get("wall_time", 0.0) + wall,
            "wall_time_this_run": wall,
            "steps_per_second": run_steps / wall if wall > 0 else None,
            "body_steps_per_second": run_steps * sim.num_bodies / wall if wall > 0 else None,
            "bodies": {
                "total": int(sim.num_bodies),
                "free": int(np.sum(kind == 0)),
                "fixed": int(np.sum(kind == 1)),
                "kinematic": int(np.sum(kind == 2)),
            },
            "fps": self.fps,
            "frames": len(frames),
            "contacts": {
                "final": len(contacts["volume"]) if contacts is not None else None,
                "mean": float(np.mean(frames)) if frames else None,
                "max": int(np.max(frames)) if frames else None,
            },
            "largest_overlap": {
                "final": largest,
                "max_over_frames": self.frame_overlap if frames else None,
            },
            "energy": {
                "initial": self.energy_initial,
                "at_resume": self.energy_at_start if self.resumed_from is not None else None,
                "final": energy,
            },
            "settled_region": settled_region(scene, sim.state(), contacts) if consistent else None,
            "outputs": {
                "folder": str(self.out_dir),
                "usd": _rel(self.usd_path, self.out_dir) if self.usd_path is not None and not self.usd_failed else None,
                "usd_frames": self.recorder.frames if self.recorder is not None and not self.usd_failed else 0,
                "vtk": {
                    "files": [_rel(p, self.out_dir) for p in self.vtk.files],
                    "frames": self.vtk.frames,
                }
                if self.vtk is not None
                else None,
                "pictures": [*(_rel(p, folder) for p in e.get("pictures", [])), *self.picture_files],
                "checkpoints": list(
                    dict.fromkeys([*(_rel(p, folder) for p in e.get("checkpoints", [])), *self.checkpoints])
                ),
                "summary": _rel(self.summary_path, self.out_dir) if self.summary_path is not None else None,
            },
        }
        if isinstance(self.pictures, tuple):
            missing = [k for k in self.pictures if k >= self.frame]
            if missing:
                notes.append(f"picture frames {missing} were not reached by this run")
        if self.resumed_from is not None and self.earlier is None:
            notes.append(
                f"the checkpoint holds no record of the run before step {self.start}: the history, contact counts, "
                "initial energy, wall time and files cover the resumed part only"
            )
        if notes:
            summary["notes"] = notes
        return summary

    def report(self, out, err, s, cp_path, reason, status) -> None:
        frames = s["frames"]
        c = s["contacts"]
        lines = []
        head = "interrupted" if status in (EXIT_INTERRUPTED, EXIT_TERMINATED) else "stopped" if reason else "done"
        rate = f" ({s['steps_per_second']:.0f} steps/s)" if s["steps_per_second"] else ""
        lines.append(
            f"{head}: {s['steps_this_run']} steps to step {s['steps']} (t = {s['simulated_time']:.6g} s) in "
            f"{s['wall_time_this_run']:.2f} s{rate}, {_n(s['bodies']['total'], 'body', 'bodies')}"
        )
        if c["final"] is not None:
            over = ""
            if frames:
                over = f" (mean {c['mean']:.1f}, max {c['max']} over {_n(frames, 'frame')})"
            lines.append(f"  contacts: {c['final']}{over}")
        lo = s["largest_overlap"]
        parts = []
        if lo["final"] is not None:
            parts.append(f"{lo['final']['relative']:.3%} now")
        if lo["max_over_frames"] is not None:
            parts.append(f"{lo['max_over_frames']:.3%} at most in the frames")
        if parts:
            lines.append(f"  largest overlap (of the smaller body's volume): {', '.join(parts)}")
        region = s["settled_region"]
        if region is not None and region["packing_fraction"] is not None:
            lines.append(
                f"  settled region ({_n(region['bodies'], 'body', 'bodies')}): packing fraction "
                f"{region['packing_fraction']:.3f}, "
                f"coordination number {region['coordination_number']:.2f}"
            )
        e = s["energy"]["final"]
        if e is not None:
            lines.append(
                f"  energy [J]: kinetic {e['kinetic']:.4g}, contact {e['contact']:.4g}, dissipated "
                f"{e['dissipated']:.4g}, total {e['total']:.6g} (at the start {s['energy']['initial']['total']:.6g})"
            )
        lines.append(f"  written to {self.out_dir}{os.sep}:")
        files = self.written(s)
        width = min(max((len(name) for name, _ in files), default=0), 40)
        lines += [f"    {name:<{width}}  {what}" for name, what in files] or ["    nothing"]
        for note in s.get("notes", []):
            lines.append(f"  note: {note}")
        for error in self.errors:
            lines.append(f"  not written: {error}")
        out.write("\n".join(lines) + "\n")
        out.flush()
        if reason is not None and cp_path is not None and status in (EXIT_INTERRUPTED, EXIT_TERMINATED):
            err.write(
                f"polydem: run interrupted at step {s['steps']}; continue with:\n  {self.resume_command(cp_path)}\n"
            )
            err.flush()

    def written(self, s) -> list[tuple[str, str]]:
        """The files written (relative to the output folder) as (names, what) pairs, by kind."""
        o = s["outputs"]
        files = []
        if o["usd"]:
            files.append((_short(o["usd"]), f"USD animation, {_n(o['usd_frames'], 'frame')}"))
        if o.get("vtk"):
            vtk = o["vtk"]
            names = ", ".join(_short(f) for f in vtk["files"] if f.endswith(".pvd"))
            files.append((names, f"VTK series for ParaView, {_n(vtk['frames'], 'frame')} (and vtk/walls.vtu)"))
        if o["summary"] and self.summary_written:
            files.append((_short(o["summary"]), "summary"))
        pictures = o["pictures"]
        if pictures:
            last = pictures[-1] == "pictures/last.png"
            what = ("picture of the final state" if last else "picture") if len(pictures) == 1 else "pictures"
            files.append((_listing(pictures, "pictures", 6), what))
        if self.plot_files:
            files.append((", ".join(self.plot_files), "plots"))
        if o["checkpoints"]:
            what = "checkpoint" if len(o["checkpoints"]) == 1 else "checkpoints"
            files.append((_listing(o["checkpoints"], "checkpoints", 4), what))
        return files

    def resume_command(self, cp_path) -> str:
        a = self.args
        cmd = ["polydem", "run"]
        if a.scene is not None:
            cmd.append(str(a.scene))
        cmd += ["--resume", str(cp_path)]
        if a.device is not None:
            cmd += ["--device", a.device]
        if a.steps is not None:
            cmd += ["--steps", str(a.steps)]
        if a.duration is not None:
            cmd += ["--duration", repr(a.duration)]
        if a.fps is not None:
            cmd += ["--fps", repr(a.fps)]
        if a.vtk:
            cmd.append("--vtk")
        if a.out is not None:
            cmd += ["--out", str(a.out)]
        return shlex.join(cmd)


def _output_paths(scene, out_dir: Path) -> dict:
    """The outputs of a run by the key that names them: ``output.usd`` and ``output.summary`` (when
    written), ``output.checkpoint.path`` (the folder); all inside ``out_dir``."""
    o = scene.output
    paths = {"output.checkpoint.path": out_dir / o.checkpoint_path}
    usd = _usd_setting(scene)
    if usd is not None:
        paths["output.usd"] = out_dir / usd
    if o.summary is not None:
        paths["output.summary"] = out_dir / o.summary
    return paths


def _check_outputs(args, scene, out_dir: Path) -> None:
    """CliError (before the run) for an output that cannot be written: a name too long for the file
    system, a file where a folder should be, a folder without write permission."""
    file = args.scene
    paths = _output_paths(scene, out_dir)
    probes = [(out_dir / "packing.png", ".tmp", "--out")]  # the plots; the folder itself
    if "output.usd" in paths:
        probes.append((paths["output.usd"], ".tmp", "output.usd"))
    if "output.summary" in paths:
        probes.append((paths["output.summary"], ".tmp", "output.summary"))
    probes.append((paths["output.checkpoint.path"] / "step_000000000.npz", ".tmp.npz", "output.checkpoint.path"))
    if _pictures_setting(scene):
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
                where = _short(exc.filename) if getattr(exc, "filename", None) else _short(path)
                raise CliError(f"cannot write {where}: {_why(exc)}", None if key == "--out" else file, key) from None
    finally:
        # The run makes the folders it writes to; the check leaves none behind (an empty checkpoints/
        # folder after an error would look like a run that wrote nothing).
        for folder in sorted(set(made), key=lambda p: len(p.parts), reverse=True):
            try:
                folder.rmdir()
            except OSError:
                pass


def _target_steps(args, scene, dt: float) -> tuple[int, str]:
    """Total steps from t = 0 and where they come from."""
    if args.steps is not None:
        return args.steps, "--steps"
    if args.duration is not None:
        return max(1, _steps_at(args.duration, dt)), f"--duration {args.duration:g} s"
    if scene.duration is not None:
        return max(1, _steps_at(scene.duration, dt)), f"duration {scene.duration:g} s"
    if scene.steps is not None:
        return scene.steps, "the scene's steps"
    return DEFAULT_STEPS, "the default"


def cmd_run(args) -> int:
    out, err = sys.stdout, sys.stderr
    _warp()
    _signals.check()
    if args.precision == "float64":
        raise CliError(
            "the simulator runs in float32 only; use --precision float32 (or leave it out). Float64 contact geometry "
            'is offered by polydem.overlap(..., precision="float64")',
            key="--precision",
        )
    resume = checkpoint = None
    if args.resume is not None:
        resume = Path(args.resume)
        if not resume.is_file():
            raise CliError(
                f"checkpoint not found (looked for '{resume.absolute()}'); give a .npz file from a run's "
                "checkpoint folder, e.g. polydem_out/<scene>/checkpoints/final.npz",
                resume,
                "--resume",
            )
        checkpoint = _read_checkpoint(resume, "--resume")  # a damaged file fails before the model is built
    scene = _load_scene(args.scene)
    if args.precision is not None:
        scene.precision = args.precision
    device = _device(args.device) if args.device is not None else None
    if device is None and scene.device is not None:
        device = _device(scene.device, file=scene.file, key="simulation.device")
    out_dir = Path(args.out) if args.out is not None else Path("polydem_out") / _safe_name(scene.name)
    try:
        if out_dir.exists() and not out_dir.is_dir():
            raise CliError("the output folder is a file; give a folder with --out", out_dir, "--out")
        out_dir.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise CliError(f"cannot create the output folder ({_why(exc)})", _short(out_dir), "--out") from None
    _check_outputs(args, scene, out_dir)  # before the kernels compile and the run starts
    _signals.check()

    from polydem.simulation import Simulation

    sim = Simulation(scene, device=device)
    _signals.check()
    target, source = _target_steps(args, scene, sim.dt)
    if resume is not None:
        _resume(sim, scene, resume, checkpoint, args)
        if sim.steps_done >= target:
            raise CliError(
                f"the checkpoint is at step {sim.steps_done} (t = {sim.time:.6g} s), which already reaches the "
                f"{target} steps asked for ({source}); ask for more with --steps or --duration (counted from t = 0)",
                resume,
                "--resume",
            )
    run = _Run(args, scene, sim, out_dir, target, resume)
    if checkpoint is not None:
        run.continue_record(checkpoint)
    kind = np.asarray(scene.body_kind)
    what = f"from step {sim.steps_done} (t = {sim.time:.6g} s) " if resume is not None else ""
    out.write(
        f"{scene.name}: {_n(sim.num_bodies, 'body', 'bodies')} ({int(np.sum(kind == 0))} free) on {sim.device}, "
        f"dt {sim.dt:.4g} s; "
        f"{what}to step {target} (t = {target * sim.dt:.6g} s, {source}); frames at {run.fps:g} per simulated s; "
        f"output in {out_dir}{os.sep}\n"
    )
    out.flush()
    return run.execute(out, err)


_HISTORY_KEYS = ("time", "kinetic", "contact", "gravity", "dissipated", "total", "contacts", "packing_fraction")
_ENERGY_KEYS = ("kinetic", "contact", "gravity", "dissipated", "total")
RUN_RECORD_VERSION = 1
"""Layout of the run record that ``polydem run`` keeps in its checkpoints (:meth:`_Run.run_record`)."""


def _run_record_problem(rec, fps, time_s, dt) -> str | None:
    """What is wrong with the run record ``rec`` of a checkpoint at ``time_s`` for a run at ``fps``, or None."""

    def number(x, lo=-math.inf):
        return isinstance(x, int | float) and not isinstance(x, bool) and x >= lo

    def strings(x):
        return isinstance(x, list) and all(isinstance(v, str) for v in x)

    damaged = "; the file is damaged or was edited: use another checkpoint of the run or rerun"
    if rec.get("version") != RUN_RECORD_VERSION:
        return f"its run record has version {rec.get('version')!r}, this polydem reads {RUN_RECORD_VERSION}{damaged}"
    history = rec.get("history")
    if not isinstance(history, dict) or set(history) != set(_HISTORY_KEYS):
        return f"its run record has no frame history with the entries {', '.join(_HISTORY_KEYS)}{damaged}"
    contacts = rec.get("frame_contacts")
    frames = len(contacts) if isinstance(contacts, list) else -1
    if frames < 0 or not all(isinstance(c, int) and not isinstance(c, bool) and c >= 0 for c in contacts):
        return f"frame_contacts of its run record is not a list of contact counts{damaged}"
    for key in _HISTORY_KEYS:
        values = history[key]
        if not isinstance(values, list) or len(values) != frames or not all(v is None or number(v) for v in values):
            return f"history.{key} of its run record is not a list of {frames} numbers{damaged}"
    times = history["time"]
    if None in times or any(b <= a for a, b in zip(times, times[1:], strict=False)):
        return f"history.time of its run record is not increasing{damaged}"
    if times and times[-1] > time_s + 0.5 * dt:
        return f"its run record has a frame at t = {times[-1]:.6g} s, after the checkpoint's {time_s:.6g} s{damaged}"
    energy = rec.get("energy_initial")
    if not (
        isinstance(energy, dict) and all(k in energy and (energy[k] is None or number(energy[k])) for k in _ENERGY_KEYS)
    ):
        return f"energy_initial of its run record is not a table of energies{damaged}"
    if not (number(rec.get("frame_overlap"), 0.0) and number(rec.get("wall_time"), 0.0)):
        return f"frame_overlap or wall_time of its run record is not a number >= 0{damaged}"
    if not (strings(rec.get("pictures")) and strings(rec.get("checkpoints"))):
        return f"pictures or checkpoints of its run record is not a list of file names{damaged}"
    parts = rec.get("parts")

    def part(p):
        steps = (p.get("from_step"), p.get("to_step"))
        whole = all(isinstance(x, int) and not isinstance(x, bool) and x >= 0 for x in steps)
        return whole and isinstance(p.get("folder"), str) and number(p.get("wall_time"), 0.0)

    if not (isinstance(parts, list) and parts and all(isinstance(p, dict) and part(p) for p in parts)):
        return f"parts of its run record is not a list of the parts of the run{damaged}"
    if not number(rec.get("fps"), 0.0) or not math.isclose(rec["fps"], fps, rel_tol=1e-12):
        return (
            f"the run recorded its frames at {rec.get('fps')!r} per simulated second, this one would at {fps:g}: its "
            f"frame history and USD time codes would not fit; give --fps {rec.get('fps')!r} (or leave --fps out)"
        )
    return None


def _resume(sim, scene, path: Path, ck, args) -> None:
    """Put the checkpoint ``ck`` (read from ``path``) into ``sim`` after checking it against ``scene``."""
    from polydem.checkpoint import CheckpointError, check_scene, restore_checkpoint

    fix = "resume with the scene the checkpoint was written from: polydem run SCENE --resume CHECKPOINT"
    _check_poses(path, ck.arrays["body_q"][:, :3], scene, args.scene, "checkpoint", fix, "--resume")
    try:
        check_scene(ck, sim, fix=f"{fix} (or leave --resume out to run this scene from t = 0)")
    except CheckpointError as err:
        raise CliError(err.message, path, "--resume") from None
    fps = args.fps if args.fps is not None else scene.output.fps
    problem = _run_record_problem(ck.run, fps, ck.time, sim.dt) if ck.run is not None else None
    if problem is not None:
        raise CliError(problem, path, "--resume")
    if ck.physics is None:
        sys.stderr.write(
            f"polydem: warning: {path}: a checkpoint of the older format {ck.format!r} holds no record of its "
            "scene's physics or of the run so far: it cannot be checked to come from this scene, and the summary "
            "covers the resumed part only\n"
        )
        sys.stderr.flush()
    restore_checkpoint(sim, ck)


# ---------------------------------------------------------------------- polydem validate


def cmd_validate(args) -> int:
    import warnings

    from polydem.scene import SceneWarning

    out, err = sys.stdout, sys.stderr
    status = EXIT_OK
    for k, path in enumerate(args.scenes):
        # Host-only: the scene's checks and time step need neither Warp nor a device.
        try:
            with warnings.catch_warnings(record=True) as caught:
                warnings.simplefilter("always", SceneWarning)
                scene = _load_scene(path)
                ts = scene.time_step()
        except SceneError as exc:
            err.write(f"polydem: error: {exc}\n")
            err.flush()
            status = EXIT_USER_ERROR
            continue
        for w in caught:
            if issubclass(w.category, SceneWarning):
                err.write(f"polydem: warning: {w.message}\n")
            else:
                warnings.warn_explicit(w.message, w.category, w.filename, w.lineno)
        err.flush()
        dt = ts.dt
        if scene.duration is not None:
            steps, how = max(1, _steps_at(scene.duration, dt)), f"duration {scene.duration:g} s"
        elif scene.steps is not None:
            steps, how = scene.steps, "steps"
        else:
            steps, how = DEFAULT_STEPS, "no steps or duration given: the default"
        usd = _usd_setting(scene)
        if args.quiet:
            out.write(f"{path}: OK, {_n(scene.num_bodies, 'body', 'bodies')}, dt {dt:.4g} s, {steps} steps\n")
            continue
        if k:
            out.write("\n")
        lines = [scene.describe()]
        auto = "auto" if scene.dt == "auto" else "given"
        lines.append(
            f"  time step: {dt:.4g} s ({auto}; recommended {ts.recommended:.4g} s, stable limit {ts.limit:.4g} s)"
        )
        frames = math.floor(steps * dt * scene.output.fps + 1e-9) + 1
        lines.append(
            f"  a run: {steps} steps to t = {steps * dt:.6g} s ({how}); {frames} frames at {scene.output.fps:g} fps"
            + (f" in {usd}" if usd else " (no USD file)")
        )
        lines.append(f"OK: {path} is a valid scene")
        out.write("\n".join(lines) + "\n")
    out.flush()
    return status


# ---------------------------------------------------------------------- polydem render


def cmd_render(args) -> int:
    from polydem.render import render_simulation

    out_png = Path(args.out)
    if out_png.suffix.lower() != ".png":
        raise CliError("the picture must be a .png file, e.g. --out frame.png", out_png, "--out")
    source = Path(args.source)
    suffix = source.suffix.lower()
    if suffix not in (".toml", ".npz", *_USD_SUFFIXES):
        raise CliError(
            "give a scene file (.toml, frame 0), a checkpoint (.npz) or a USD file written by polydem run "
            "(.usd, .usda, .usdc)",
            source,
        )
    try:
        found = source.is_file()
    except OSError as exc:  # a name too long for the file system
        raise CliError(f"cannot read the file ({_why(exc)}); check the path", _short(source)) from None
    if not found:
        raise CliError(f"file not found (looked for '{source.absolute()}'); check the path", source)
    device = _device(args.device)
    fix = "give the scene it was written from with --scene SCENE"
    if suffix == ".toml":
        if args.scene is not None:
            raise CliError("--scene is for checkpoints and USD files; a scene file renders itself", key="--scene")
        if args.frame not in (None, 0):
            raise CliError(
                f"a scene file holds frame 0 only (its initial state), not frame {args.frame}; run it with "
                "polydem run and render a frame of its USD file or a checkpoint",
                source,
                "--frame",
            )
        scene = _load_scene(source)
        positions, orientations = scene.body_position, scene.body_orientation
        what = f"frame 0 of {source}"
    elif suffix == ".npz":
        if args.frame is not None:
            raise CliError(
                "a checkpoint holds one state: leave --frame out (or render a frame of the run's USD file)",
                source,
                "--frame",
            )
        scene = _load_scene(args.scene)
        body_q = _read_checkpoint_poses(source)
        _check_poses(source, body_q[:, :3], scene, args.scene, "checkpoint", fix)
        positions, orientations = body_q[:, :3], body_q[:, 3:7]
        what = f"the checkpoint {source}"
    else:
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
        scene = _load_scene(scene_arg)
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
        _check_poses(source, positions, scene, scene_arg, "USD file", fix)
        what = f"frame {frame} of {source}"
    poses = _Poses(scene, positions, orientations, device)
    _signals.check()
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
        raise CliError(f"cannot write the picture ({_why(exc)})", _short(out_png), "--out") from None
    sys.stdout.write(
        f"wrote {out_png} ({args.width} x {args.height}): {what}, {_n(scene.num_bodies, 'body', 'bodies')}\n"
    )
    return EXIT_OK


# ---------------------------------------------------------------------- polydem info


def cmd_info(args) -> int:
    import platform

    import polydem

    wp = _warp()
    lines = [f"polydem {polydem.__version__}", f"  Python {platform.python_version()}, numpy {np.__version__}"]
    lines.append(f"  Warp {wp.config.version}, kernel cache {wp.config.kernel_cache_dir}")
    try:
        from pxr import Usd

        lines.append(f"  usd-core (OpenUSD) {'.'.join(map(str, Usd.GetVersion()))}")
    except ImportError:
        lines.append("  usd-core: not installed (no USD output)")
    default = wp.get_device()
    lines.append(f"devices (default {default.alias}):")
    for d in wp.get_devices():
        extra = ""
        if d.is_cuda:
            extra = f", sm_{d.arch}, {d.total_memory / 2**30:.1f} GiB"
        lines.append(f"  {d.alias:<8} {d.name}{extra}")
    if not wp.get_cuda_device_count():
        lines.append("  no CUDA device: runs use the CPU")
    for note in _WARP_NOTES:
        lines.append(f"  note: {note}")
    sys.stdout.write("\n".join(lines) + "\n")
    return EXIT_OK


# ---------------------------------------------------------------------- the parser


class _Parser(argparse.ArgumentParser):
    """An ArgumentParser whose errors are one line (a CliError: exit code 2)."""

    def error(self, message):
        raise CliError(f"{message} (see '{self.prog} --help')", key=None)


_RUN_EPILOG = """\
outputs (in --out, default polydem_out/<scene name>/; the scene's [output] table names them, as
paths inside that folder; the closing lines name every file written):
  USD animation   output.usd (trajectory.usdc when the scene file does not mention usd; none for
                  usd = false). Frame k is the state at simulated time k / fps, time code k. It
                  records the scene file, so that polydem render finds the scene.
  summary         output.summary (summary.json): steps, simulated and wall time, bodies, contacts
                  (final, mean and max over the frames), energies (start and end), the largest
                  overlap relative to the smaller body's volume, and the packing fraction and mean
                  coordination number of the settled region. That region is a box: horizontally the
                  bounding box of the free bodies' centres shrunk by 2 mean body diameters (of
                  equal-volume spheres) on each side, vertically from the lowest point of any free
                  body to the 80th percentile of their centre heights. Packing fraction = volume of
                  the free bodies whose centres lie in it / its volume; coordination number = mean
                  number of contacts (with bodies or walls) of those bodies.
  pictures        pictures/last.png, the final state (unless the scene sets output.pictures: frame
                  numbers for pictures/frame_NNNNNN.png, "last", or false for none).
  plots           energy.png and packing.png (energies, contacts, packing fraction against time)
                  when matplotlib is installed: pip install "polydem[plot]".
  VTK (ParaView)  --vtk or output.vtk = true: vtk/particles.pvd (the polyhedra), vtk/centres.pvd
                  (one point per body), vtk/contacts.pvd (a line per contact with its forces: the
                  force chains), each a series of frames (vtk/<series>/<series>_NNNNNN.vtu), and
                  vtk/walls.vtu. Open the .pvd files in ParaView.
  checkpoints     checkpoints/final.npz at the end, checkpoints/interrupted.npz when the run stops
                  early; with output.checkpoint = {steps = N} or {seconds = T} also
                  checkpoints/step_NNNNNNNNN.npz.
  An output that cannot be written (a name too long, a file in the way of a folder, no
  permission) stops the command before the run (exit code 2); after the start, the others are
  still written (exit code 1).

progress: one line per 5% of the steps on stderr (one line kept up to date on a terminal), with
the wall time left once it can be estimated.

interruption and resuming:
  Ctrl-C, or SIGTERM (what a batch scheduler sends), stops after the steps under way (a second one
  at once); the USD file keeps the frames so far, the summary says "interrupted": true, and
  interrupted.npz holds the state. While the command starts (imports, Warp, kernel compilation)
  either stops it at once, writing nothing. Add --resume CHECKPOINT to the same command to
  continue: --steps and --duration count from t = 0, and the result equals that of an unbroken
  run bit for bit (same device). The resumed frames go to a new USD file,
  <usd name>.from_step_<N>.<ext>, with the same time codes as before. A checkpoint of other
  physics (materials, shapes, walls, bodies, gravity, dt) is refused, naming what differs; the
  summary of a resumed run covers the whole run from t = 0 ("parts": which steps and frames each
  part wrote, and where).

exit codes: 0 done; 1 the simulation failed or an output could not be written (the other outputs
written), or an internal error; 2 a user error (bad option, scene or checkpoint: one message
naming the file, the key and the fix); 130 Ctrl-C (SIGINT); 143 SIGTERM.

examples:
  polydem run                                   the built-in default scene (300 polyhedra)
  polydem run scenes/cube_drop.toml --device cpu --duration 0.6 --out results/
  polydem run scenes/drum.toml --resume polydem_out/drum/checkpoints/interrupted.npz
"""


def _para(text: str) -> str:
    return textwrap.fill(text, 100)


def build_parser() -> argparse.ArgumentParser:
    fmt = argparse.RawDescriptionHelpFormatter
    parser = _Parser(
        prog="polydem",
        formatter_class=fmt,
        description=_para(
            "Discrete element simulation of rigid convex polyhedra (energy-based volume contact model) "
            "with NVIDIA Warp."
        ),
        epilog=_para(
            "Run 'polydem COMMAND --help' for the options of a command. Exit codes: 0 success, 1 simulation "
            "failure, an output not written or internal error, 2 user error, 130 interrupted (Ctrl-C), 143 stopped "
            "by SIGTERM."
        ),
    )
    sub = parser.add_subparsers(dest="command", metavar="COMMAND", required=True, parser_class=_Parser)

    run = sub.add_parser(
        "run",
        help="run a scene (the built-in default when none is given)",
        description=_para(
            "Run a scene: progress on stderr, a USD animation, a summary, pictures and checkpoints in "
            "the output folder, and a short summary at the end."
        ),
        epilog=_RUN_EPILOG,
        formatter_class=fmt,
    )
    run.add_argument(
        "scene", nargs="?", default=None, metavar="SCENE", help="scene file (TOML); default: the built-in default scene"
    )
    run.add_argument(
        "--device",
        default=None,
        metavar="DEV",
        help='Warp device: "cpu", "cuda" or "cuda:N"; default: the scene\'s [simulation] device, else the GPU '
        "when there is one",
    )
    length = run.add_mutually_exclusive_group()
    length.add_argument(
        "--steps",
        type=_count("steps", "--steps 10000", "step"),
        default=None,
        metavar="N",
        help="run until step N (counted from t = 0, also when resuming); default: the scene's duration or steps, "
        f"else {DEFAULT_STEPS}",
    )
    length.add_argument(
        "--duration",
        type=_positive("a simulated time in seconds", "--duration 0.5"),
        default=None,
        metavar="T",
        help="run until simulated time T [s] (counted from t = 0, also when resuming); replaces the scene's "
        "duration or steps",
    )
    run.add_argument(
        "--out",
        default=None,
        metavar="DIR",
        help="output folder (made if missing); default: polydem_out/<scene name>/",
    )
    run.add_argument(
        "--fps",
        type=_positive("frames per simulated second", "--fps 60"),
        default=None,
        metavar="F",
        help="frames per simulated second of the USD file, the picture frames and the contact statistics; "
        "default: the scene's output.fps (60)",
    )
    run.add_argument(
        "--precision",
        choices=("float32", "float64"),
        default=None,
        help="floating-point precision of the simulation; the simulator runs float32 only (the default)",
    )
    run.add_argument(
        "--resume",
        default=None,
        metavar="CHECKPOINT",
        help="continue from a checkpoint (.npz) written by a run of the same scene; the result equals an "
        "unbroken run's",
    )
    run.add_argument(
        "--picture-size",
        type=_size,
        default=(800, 600),
        metavar="WxH",
        help="size of the pictures (pictures/last.png and those of output.pictures) in pixels (default 800x600)",
    )
    run.add_argument(
        "--vtk",
        action="store_true",
        help="also write every frame as VTK files for ParaView in vtk/ of the output folder (as output.vtk = true)",
    )
    run.add_argument(
        "-q", "--quiet", action="store_true", help="no progress on stderr (the closing summary is still printed)"
    )
    run.set_defaults(func=cmd_run)

    validate = sub.add_parser(
        "validate",
        help="check scene files without running them",
        description=_para(
            "Check scene files without running them: load each one (every key and value), build the "
            "model on the CPU to check the time step against the stable limit, and print a short description."
        ),
        epilog=_para(
            "exit codes: 0 every scene is valid; 2 some scene is not (one message per bad file on stderr, "
            "naming the file, the key and the fix)."
        ),
        formatter_class=fmt,
    )
    validate.add_argument("scenes", nargs="+", metavar="SCENE", help="scene file(s) (TOML)")
    validate.add_argument(
        "-q", "--quiet", action="store_true", help="one line per valid scene instead of a description"
    )
    validate.set_defaults(func=cmd_validate)

    render = sub.add_parser(
        "render",
        help="write a PNG picture of a scene, a checkpoint or a frame of a USD file",
        description=_para(
            "Write a PNG picture of bodies and walls (ray cast with Warp). SOURCE is a scene file "
            "(its initial state, frame 0), a checkpoint (.npz) or a USD file written by polydem run (any of its "
            "frames). Checkpoints and USD files hold poses only: --scene names the scene they come from (a USD file "
            "written by polydem run records it). Fixed and kinematic bodies between the camera and the free bodies "
            "are left out, so the inside of a container shows."
        ),
        epilog="examples:\n"
        "  polydem render scenes/drum.toml --out drum.png\n"
        "  polydem render polydem_out/drum/drum.usd --frame 30 --out drum_1s.png\n"
        "  polydem render scenes/drum.toml --elevation 90 --out drum_top.png\n"
        "  polydem render polydem_out/default/checkpoints/final.npz --out settled.png",
        formatter_class=fmt,
    )
    render.add_argument("source", metavar="SOURCE", help="scene file (.toml), checkpoint (.npz) or USD file")
    render.add_argument("--out", required=True, metavar="IMAGE.png", help="the PNG file to write")
    render.add_argument(
        "--scene",
        default=None,
        metavar="SCENE",
        help="scene file of a checkpoint or USD file (for the shapes, walls and colours); default: for a USD file "
        "written by polydem run, the scene it records (its file, or the built-in default scene), else the built-in "
        "default scene",
    )
    render.add_argument(
        "--frame",
        type=int,
        default=None,
        metavar="K",
        help="frame of a USD file (time code K: simulated time K / fps); default: its last frame. A scene file "
        "has frame 0 only; a checkpoint one state",
    )
    render.add_argument(
        "--width", type=_count("pixels", "--width 800", "pixel"), default=800, help="width in pixels (800)"
    )
    render.add_argument(
        "--height", type=_count("pixels", "--height 600", "pixel"), default=600, help="height in pixels (600)"
    )
    render.add_argument(
        "--supersample",
        type=_count("rays per pixel side", "--supersample 2", "ray per pixel side"),
        default=1,
        metavar="S",
        help="S x S rays per pixel, for smoother edges (default 1)",
    )
    render.add_argument(
        "--azimuth",
        type=_angle(-math.inf, math.inf, "--azimuth 30"),
        default=-60.0,
        help="camera direction about the vertical [degrees] (default -60)",
    )
    render.add_argument(
        "--elevation",
        type=_angle(-90.0, 90.0, "--elevation 90 (from above) or --elevation -90 (from below)"),
        default=50.0,
        help="camera height above the horizontal [degrees], from -90 (from straight below) to 90 (from straight "
        "above) (default 50)",
    )
    render.add_argument(
        "--device",
        default=None,
        metavar="DEV",
        help='Warp device that renders: "cpu", "cuda" or "cuda:N" (default: the GPU when there is one)',
    )
    render.set_defaults(func=cmd_render)

    info = sub.add_parser(
        "info",
        help="print the versions and the Warp devices",
        description=_para("Print the versions of polydem, Python, numpy, Warp and usd-core, and the Warp devices."),
        formatter_class=fmt,
    )
    info.set_defaults(func=cmd_info)
    return parser


def main(argv=None) -> int:
    """Run the ``polydem`` command with ``argv`` (default ``sys.argv[1:]``); returns the exit code."""
    import warnings

    _signals.install()
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
        _signals.uninstall()


def _is_ours(category, filename) -> bool:
    package = Path(__file__).resolve().parent
    return category.__module__.startswith("polydem") or Path(filename).resolve().is_relative_to(package)


def _main(argv) -> int:
    parser = build_parser()
    try:
        try:
            args = parser.parse_args(argv)
        except SystemExit as exc:  # --help
            return int(exc.code or 0) if not isinstance(exc.code, str) else EXIT_USER_ERROR
        _signals.check()
        return args.func(args)
    except (SceneError, CliError) as err:
        sys.stdout.flush()
        print(f"polydem: error: {err}", file=sys.stderr)
        return EXIT_USER_ERROR
    except KeyboardInterrupt:  # a signal before the run started, or a second one while it wrote its outputs
        sys.stdout.flush()
        what = "nothing was written" if not _signals.started() else "while writing the outputs, some may be missing"
        print(f"polydem: stopped by {_signals.name()}; {what}", file=sys.stderr)
        return _signals.exit_code()


if __name__ == "__main__":
    sys.exit(main())
