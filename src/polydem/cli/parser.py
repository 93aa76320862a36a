"""The command line of ``polydem``: one function per command adds its options, help and epilog.

Nothing heavy is imported here (no numpy, Warp or trimesh), so that ``polydem --help`` is quick;
each command's module is imported only when the command runs.
"""

from __future__ import annotations

import argparse
import math
import re
import textwrap

from polydem.cli.errors import CliError
from polydem.cli.settings import DEFAULT_STEPS
from polydem.kernels.precision import PRECISIONS

__all__ = ["RUN_EPILOG", "build_parser"]


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


def _optional_number(text: str, ok, expected: str, example: str) -> float | None:
    """A number that ``ok`` accepts, or None for off/none/false."""
    if text.strip().lower() in ("off", "none", "false"):
        return None
    try:
        value = float(text)
    except ValueError:
        value = math.nan
    if not (math.isfinite(value) and ok(value)):
        raise argparse.ArgumentTypeError(f"expected {expected}, or off, got {text!r}; e.g. {example}")
    return value


def _fraction(text: str) -> float | None:
    return _optional_number(
        text,
        lambda v: 0.0 < v < 1.0,
        "a fraction between 0 and 1 (exclusive) of the gravitational energy released",
        "--settle-kinetic 1e-4",
    )


def _speed_fraction(text: str) -> float | None:
    return _optional_number(
        text,
        lambda v: v > 0.0,
        "a fraction > 0 of sqrt(g r_min) (r_min the smallest grain's bounding radius)",
        "--settle-speed-fraction 3e-4",
    )


def _nonnegative(what: str, example: str):
    def parse(text: str) -> float:
        try:
            value = float(text)
        except ValueError:
            value = math.nan
        if not (math.isfinite(value) and value >= 0.0):
            raise argparse.ArgumentTypeError(f"expected {what} >= 0, got {text!r}; e.g. {example}")
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


class _Parser(argparse.ArgumentParser):
    """An ArgumentParser whose errors are one line (a CliError: exit code 2)."""

    def error(self, message):
        raise CliError(f"{message} (see '{self.prog} --help')", key=None)

    def parse_args(self, args=None, namespace=None):
        parsed = super().parse_args(args, namespace)
        if getattr(parsed, "command", None) == "run":
            _check_picture_size(parsed)
        return parsed


def _check_picture_size(args) -> None:
    """CliError for a --picture-size the memory cannot hold. Checked here, before the run, because
    the pictures are drawn during the run and at its end: a picture refused then would cost the run."""
    from polydem.picture_memory import PictureSizeError, check_picture_size

    width, height = args.picture_size
    try:
        # The host's memory holds the picture on any device: on the CPU (the default where there is
        # no GPU) the ray caster's buffers too. A GPU's memory is checked when it draws.
        check_picture_size(width, height, gpu=str(args.device or "cpu").startswith("cuda"))
    except PictureSizeError as exc:
        raise CliError(f"{exc}; give a smaller --picture-size", key="--picture-size") from None


RUN_EPILOG = """\
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

until settled: with --until-settled (or [simulation] until_settled = true in the scene) the run
stops once the pile has settled: the kinetic energy of the free bodies below --settle-kinetic
(default 1e-4) of the gravitational energy released since t = 0, and no free body's fastest point
(|v| + |w| r) at the speed limit or faster: --settle-speed-fraction (default 3e-4) of sqrt(g r_min),
r_min the smallest bounding radius of a free body (0.087 mm/s for 1 cm cubes), or --settle-speed V
m/s instead; at every check for --settle-hold seconds (default 0.02 s); checks every 64 steps.
--steps or --duration is then the maximum. The summary's "settle" entry and the closing lines give
the time, the steps and the wall time it took (or say it did not settle); a resumed run continues
the check.

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

several processes: mpiexec -n R polydem run SCENE (pip install "polydem[mpi]") steps the scene over R
ranks, one GPU each (the CPU with --device cpu), each owning a slab of the pile; rank 0 prints and
writes the outputs, of the whole scene, as one process would: the same results bit for bit, and
checkpoints that resume on any number of ranks. An error on one rank ends them all; Ctrl-C stops
them after the steps under way (README.md, "Several processes and GPUs").

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
    for add in (_add_run, _add_validate, _add_render, _add_tap, _add_compress, _add_anneal, _add_info):
        add(sub, fmt)
    return parser


def _add_run(sub, fmt) -> None:
    run = sub.add_parser(
        "run",
        help="run a scene (the built-in default when none is given)",
        description=_para(
            "Run a scene: progress on stderr, a USD animation, a summary, pictures and checkpoints in "
            "the output folder, and a short summary at the end."
        ),
        epilog=RUN_EPILOG,
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
    run.add_argument(
        "--exchange",
        choices=("auto", "host", "nccl"),
        default="auto",
        help="under mpiexec: how the ranks' ghost rows travel: through host memory over MPI (host) or from GPU to "
        'GPU with NCCL (nccl: a GPU per rank, pip install "polydem[nccl]"); auto (the default): nccl where each '
        "rank has a GPU of its own and nccl4py, else host. A run of one process has none",
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
        "--until-settled",
        action="store_true",
        help="stop once the pile has settled (see 'until settled' below); --steps or --duration is then the maximum",
    )
    run.add_argument(
        "--settle-kinetic",
        type=_fraction,
        default=False,
        metavar="F",
        help="with --until-settled: settled when the kinetic energy is below F of the gravitational energy released "
        "(default: the scene's, else 1e-4); off to check the speed alone",
    )
    run.add_argument(
        "--settle-speed-fraction",
        type=_speed_fraction,
        default=False,
        metavar="F",
        help="with --until-settled: also require every free body's fastest point to move slower than F sqrt(g r_min), "
        "r_min the smallest bounding radius of a free body (default: the scene's, else 3e-4); off for no speed limit",
    )
    run.add_argument(
        "--settle-speed",
        type=_positive("a speed in m/s", "--settle-speed 0.01"),
        default=None,
        metavar="V",
        help="with --until-settled: require every free body's fastest point to move slower than V [m/s], in place "
        "of the limit of --settle-speed-fraction",
    )
    run.add_argument(
        "--settle-hold",
        type=_nonnegative("a simulated time in seconds", "--settle-hold 0.05"),
        default=None,
        metavar="S",
        help="with --until-settled: how long the criterion must hold without a break [s] (default: the scene's, "
        "else 0.02)",
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
        choices=PRECISIONS,
        default=None,
        help="floating-point precision of the simulation (overrides the scene's): mixed, float64 positions, "
        "velocities and force sums with float32 contact geometry local to each contact; float32 everywhere (less "
        "memory, a little faster, coarse far from the origin); float64 everywhere. Default: the scene's (mixed "
        "unless the scene gives one)",
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
        help="size of the pictures (pictures/last.png and those of output.pictures) in pixels (default 800x600); "
        "one the memory available cannot hold (about 60 bytes per pixel on the CPU) is refused before the run",
    )
    run.add_argument(
        "--vtk",
        action="store_true",
        help="also write every frame as VTK files for ParaView in vtk/ of the output folder (as output.vtk = true)",
    )
    run.add_argument(
        "--vtk-contact-types",
        nargs="?",
        const="features",
        default=None,
        choices=("features", "overlap"),
        metavar="METHOD",
        help="with the VTK files (implies --vtk): the contacts' contact_type (0 face-face, 1 edge-face, 2 "
        "vertex-face, 3 edge-edge, -1 unclassified), classified by the features the bodies present (features, the "
        "default) or by the overlap's shape (overlap); costs two to three times the writing of a frame",
    )
    run.add_argument(
        "-q", "--quiet", action="store_true", help="no progress on stderr (the closing summary is still printed)"
    )


def _add_validate(sub, fmt) -> None:
    validate = sub.add_parser(
        "validate",
        help="check scene files without running them",
        description=_para(
            "Check scene files without running them: load each one (every key and value), check what a run "
            "could not honour (float32 ranges, the time step against the stable limit, initial overlaps), "
            "and print a short description. Needs no Warp and no device."
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


def _add_render(sub, fmt) -> None:
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
        help="S x S rays per pixel, for smoother edges (default 1); the memory grows as S^2 (20 bytes per ray): a "
        "picture the memory available cannot hold is refused, naming the largest S that fits",
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


def _between_0_and_1(what: str, example: str):
    def parse(text: str) -> float:
        try:
            value = float(text)
        except ValueError:
            value = math.nan
        if not (math.isfinite(value) and 0.0 < value < 1.0):
            raise argparse.ArgumentTypeError(
                f"expected {what} between 0 and 1 (exclusive), got {text!r}; e.g. {example}"
            )
        return value

    return parse


PROTOCOL_EPILOG = (
    "Writes COMMAND.json (the options and the records, SI units), COMMAND.csv and checkpoints/final.npz (the "
    "packing; interrupted.npz when stopped early) into the output folder. The first Ctrl-C or SIGTERM stops after "
    "the record under way, a second at once; the records so far are written either way. Exit codes as for "
    "'polydem run'."
)


def _add_protocol_common(p) -> None:
    p.add_argument("scene", metavar="SCENE", help="scene file (TOML)")
    p.add_argument(
        "--device", default=None, metavar="DEV", help='Warp device: "cpu", "cuda" or "cuda:N"; default as for run'
    )
    p.add_argument("--precision", choices=PRECISIONS, default=None, help="as for run (default: the scene's)")
    p.add_argument(
        "--out", default=None, metavar="DIR", help="output folder (made if missing); default: polydem_out/<scene name>/"
    )
    p.add_argument("-q", "--quiet", action="store_true", help="no table of the records on stdout")


def _add_margin(p) -> None:
    p.add_argument(
        "--margin",
        type=_nonnegative("a number of grain sizes", "--margin 2"),
        default=2.0,
        metavar="M",
        help="the packing fraction is measured in the box around the free grains moved in by M grain sizes, away "
        "from the walls and the loose top (default 2)",
    )


def _add_tap(sub, fmt) -> None:
    tap = sub.add_parser(
        "tap",
        help="tap a container and record the packing fraction after each tap",
        description=_para(
            'Run a scene whose container follows a train of taps ([motions.NAME] of kind "cycle" with a count and '
            "a period longer than one cycle) and measure the exact packing fraction just before each tap and after "
            "the last (polydem.protocols.tap)."
        ),
        epilog="examples:\n  polydem tap scenes/tapping.toml\n  polydem tap scenes/tapping.toml --motion taps "
        "--margin 3 --out taps/\n\n" + textwrap.fill(PROTOCOL_EPILOG, 100),
        formatter_class=fmt,
    )
    _add_protocol_common(tap)
    tap.add_argument(
        "--motion", default=None, metavar="NAME", help="the motion of taps (default: the scene's only one)"
    )
    _add_margin(tap)
    tap.add_argument(
        "--lead",
        type=_between_0_and_1("a fraction of the rest between taps", "--lead 0.1"),
        default=0.1,
        metavar="F",
        help="measure this fraction of the rest between taps before the next tap (default 0.1)",
    )
    tap.add_argument(
        "--resume",
        default=None,
        metavar="CHECKPOINT",
        help="go on from a checkpoint of this scene (checkpoints/interrupted.npz of a stopped tap run): the taps "
        "before its time are not made again, and the records of the run it came from come first in tap.json",
    )


def _add_compress(sub, fmt) -> None:
    compress = sub.add_parser(
        "compress",
        help="press grains with a piston (ramp or servo) and record the stress-strain curve",
        description=_para(
            "Run a scene whose piston (a kinematic body or box wall) follows a ramp (set speed) or servo (set "
            "stress) motion and record, every interval, its displacement, the force the grains push it back with, "
            "that force over its area, the strain and the packing fraction (polydem.protocols.compress). Several "
            "motions (six servo walls: isotropic compression) are recorded side by side."
        ),
        epilog="examples:\n  polydem compress scenes/compression.toml\n  polydem compress scenes/compression.toml "
        "--duration 0.8 --interval 0.01\n\n" + textwrap.fill(PROTOCOL_EPILOG, 100),
        formatter_class=fmt,
    )
    _add_protocol_common(compress)
    compress.add_argument(
        "--motion",
        action="append",
        default=None,
        metavar="NAME",
        help="a ramp or servo motion to record; repeat for several (default: every ramp and servo that drives a body)",
    )
    compress.add_argument(
        "--duration",
        type=_positive("a simulated time in seconds", "--duration 1.2"),
        default=None,
        metavar="T",
        help="how long to run [s] (default: the scene's duration)",
    )
    compress.add_argument(
        "--interval",
        type=_positive("a simulated time in seconds", "--interval 0.01"),
        default=None,
        metavar="S",
        help="time between records [s], rounded to whole steps (default: the duration / 50)",
    )


def _add_anneal(sub, fmt) -> None:
    anneal = sub.add_parser(
        "anneal",
        help="fill at one friction, then restore the final one, and record the packing fraction",
        description=_para(
            "Friction annealing (polydem.protocols.anneal): give the grains the friction --mu-fill and run until "
            "they have settled, then give them the final friction and run until they have settled again; the "
            "packing fraction at the end of each stage. A fill below the final friction packs denser than a fill "
            "at it, one above it looser."
        ),
        epilog="examples:\n  polydem anneal scenes/anneal.toml --mu-fill 0 --fill-time 1.5 --settle-time 0.5\n"
        "  polydem anneal scenes/anneal.toml --mu-fill 1.0 --mu-final 0.5 --fill-time 1.5 --settle-time 0.5\n\n"
        + textwrap.fill(PROTOCOL_EPILOG, 100),
        formatter_class=fmt,
    )
    _add_protocol_common(anneal)
    anneal.add_argument(
        "--mu-fill",
        type=_nonnegative("a friction coefficient", "--mu-fill 0.1"),
        required=True,
        metavar="MU",
        help="friction coefficient of the fill",
    )
    anneal.add_argument(
        "--mu-final",
        type=_nonnegative("a friction coefficient", "--mu-final 0.5"),
        default=None,
        metavar="MU",
        help="friction coefficient after the fill (default: each material's in the scene)",
    )
    anneal.add_argument(
        "--fill-time",
        type=_positive("a simulated time in seconds", "--fill-time 1.5"),
        required=True,
        metavar="T",
        help="the longest the fill may take to settle [s]",
    )
    anneal.add_argument(
        "--settle-time",
        type=_positive("a simulated time in seconds", "--settle-time 0.5"),
        required=True,
        metavar="T",
        help="the longest the grains may take to settle again at the final friction [s]",
    )
    anneal.add_argument(
        "--material", default=None, metavar="NAME", help="anneal only this material (default: every material)"
    )
    _add_margin(anneal)


def _add_info(sub, fmt) -> None:
    sub.add_parser(
        "info",
        help="print the versions and the Warp devices",
        description=_para("Print the versions of polydem, Python, numpy, Warp and usd-core, and the Warp devices."),
        formatter_class=fmt,
    )
