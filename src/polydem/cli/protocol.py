"""``polydem tap``, ``polydem compress`` and ``polydem anneal``: the packing protocols of
:mod:`polydem.protocols` from the command line.

Each command loads a scene, checks its options against it before anything compiles, runs the protocol
and prints one line per record as it is taken. It writes into the output folder (``--out``, default
``polydem_out/<scene name>/``):

* ``<command>.json``: the scene, device, precision, time step and options, the records (each field in SI
  units) and, where the run stopped early, why;
* ``<command>.csv``: the records, one row each (a compression with several walls has one column per wall);
* ``checkpoints/final.npz`` (``interrupted.npz`` when it stopped early): the packing, for ``polydem render``
  or ``polydem run --resume``. A checkpoint records the scene's friction: after ``polydem anneal`` with a
  ``--mu-final`` other than the scene's, a resumed run goes on with the scene's.

Nothing measured is lost when a run stops early: the first Ctrl-C or SIGTERM stops it after the record
under way (a tap's relaxation, a compression interval, an annealing stage) and a second one at once; a
:class:`~polydem.SimulationError` stops it too. The records so far are written either way.
"""

from __future__ import annotations

import csv
import dataclasses
import json
import math
import sys
import time
from collections.abc import Callable
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from polydem import signals
from polydem.cli.common import plural, relative
from polydem.cli.device import warp
from polydem.cli.errors import EXIT_FAILED, EXIT_INTERRUPTED, EXIT_OK, EXIT_USER_ERROR, CliError, why
from polydem.cli.run import check_resume, checkpoint_to_resume, output_folder, roll_back, scene_and_device

if TYPE_CHECKING:
    import argparse

    from polydem.scene import Scene
    from polydem.simulation import Simulation

__all__ = ["cmd_anneal", "cmd_compress", "cmd_tap"]

Protocol = Callable[["Simulation", Callable[[Any], None]], list]


@dataclasses.dataclass(frozen=True)
class Plan:
    """A protocol checked against its scene: what to run, its options for the record, and its columns."""

    command: str
    run: Protocol
    options: dict
    columns: tuple[tuple[str, str, str], ...]  # (field, heading, format)


# -- the three protocols: options checked against the scene, before the simulation is built


def _cycle_motions(scene: Scene) -> list[str]:
    return [name for name, m in scene.motions.items() if m.kind == "cycle" and m.count > 0]


def _tap_plan(args: argparse.Namespace, scene: Scene) -> Plan:
    from polydem.protocols import tap

    name = args.motion
    if name is None:
        taps = _cycle_motions(scene)
        if len(taps) != 1:
            found = f"it has {len(taps)}: {', '.join(taps)}" if taps else "it has none"
            raise CliError(
                f'the scene must have one motion of taps (kind = "cycle" with a count) to tap with, and {found}; '
                "name it with --motion",
                scene.file,
                "--motion" if taps else "motions",
            )
        name = taps[0]
    _known_motion(scene, name)
    m = scene.motions[name]
    if m.kind != "cycle" or m.count < 1 or not m.cycle_period() > 1.0 / m.frequency:
        raise CliError(
            f'motion {name!r} is not a train of taps: taps need kind = "cycle" (it is {m.kind!r}), a count of taps '
            "and a period longer than one cycle (the rest between taps)",
            scene.file,
            "--motion",
        )
    walls = [w.motion for w in (*scene.planes, *scene.mesh_walls)]
    if name not in (*scene.body_motion.values(), *walls):
        raise CliError(
            f"motion {name!r} drives no container: give a box, plane or mesh wall motion = {name!r}", scene.file,
            "--motion",
        )  # fmt: skip
    options = {"motion": name, "margin": args.margin, "lead": args.lead, "taps": m.count}
    return Plan(
        "tap",
        lambda sim, on: tap(sim, name, margin=args.margin, lead=args.lead, on_record=on),
        options,
        (
            ("tap", "tap", "{:>5d}"),
            ("time", "time [s]", "{:>10.4f}"),
            ("packing_fraction", "packing fraction", "{:>17.4f}"),
            ("kinetic", "kinetic [J]", "{:>12.3e}"),
            ("fastest", "fastest [m/s]", "{:>14.3e}"),
        ),
    )


def _compress_plan(args: argparse.Namespace, scene: Scene) -> Plan:
    from polydem.protocols import compress

    names = args.motion
    if not names:
        names = [n for n, m in scene.motions.items() if m.kind != "cycle" and n in scene.body_motion.values()]
        if not names:
            raise CliError(
                "the scene has no piston to compress with: give a kinematic body or box wall a motion of kind = "
                '"ramp" (a set speed) or "servo" (a set stress)',
                scene.file,
                "motions",
            )
    for name in names:
        _known_motion(scene, name)
        m = scene.motions[name]
        if m.kind == "cycle":
            raise CliError(
                f"motion {name!r} is a cycle (vibration, taps): a compression needs a ramp or a servo", scene.file,
                "--motion",
            )  # fmt: skip
        if name not in scene.body_motion.values():
            raise CliError(f"motion {name!r} drives no body: give a kinematic body motion = {name!r}", scene.file,
                           "--motion")  # fmt: skip
    duration = args.duration if args.duration is not None else scene.duration
    if duration is None:
        raise CliError("how long to compress? The scene gives no duration: give --duration T (seconds)", scene.file,
                       "--duration")  # fmt: skip
    interval = args.interval if args.interval is not None else duration / 50.0
    target = names if len(names) > 1 else names[0]
    options = {"motions": list(names), "duration": duration, "interval": interval}
    return Plan(
        "compress",
        lambda sim, on: compress(sim, target, duration, interval, on_record=on),
        options,
        (
            ("time", "time [s]", "{:>10.4f}"),
            ("displacement", "displacement [m]", "{:>17.4e}"),
            ("force", "force [N]", "{:>11.4e}"),
            ("stress", "stress [Pa]", "{:>12.4e}"),
            ("strain", "strain", "{:>11.4e}"),
            ("packing_fraction", "packing fraction", "{:>17.4f}"),
            ("kinetic", "kinetic [J]", "{:>12.3e}"),
        ),
    )


def _anneal_plan(args: argparse.Namespace, scene: Scene) -> Plan:
    from polydem.protocols import anneal

    if args.material is not None and args.material not in scene.materials:
        raise CliError(
            f"unknown material {args.material!r}; the scene's materials are {', '.join(scene.material_names)}",
            scene.file,
            "--material",
        )
    names = scene.material_names if args.material is None else [args.material]
    if not any(scene.materials[n].friction > 0.0 for n in scene.material_names):
        raise CliError(
            "the scene has no friction (every material's friction is 0), so the grains have no friction "
            "springs to anneal: give the materials their final friction in the scene",
            scene.file,
            "materials",
        )
    mu_final = args.mu_final
    options = {
        "mu_fill": args.mu_fill,
        "mu_final": mu_final if mu_final is not None else {n: scene.materials[n].friction for n in names},
        "material": args.material,
        "fill_time": args.fill_time,
        "settle_time": args.settle_time,
        "margin": args.margin,
    }

    def run(sim, on):
        return anneal(
            sim, args.mu_fill, mu_final, args.fill_time, args.settle_time, material=args.material,
            margin=args.margin, on_record=on,
        )  # fmt: skip

    return Plan(
        "anneal",
        run,
        options,
        (
            ("stage", "stage", "{:>6s}"),
            ("friction", "friction", "{:>9.3f}"),
            ("time", "time [s]", "{:>10.4f}"),
            ("settled", "settled", "{!s:>8}"),
            ("packing_fraction", "packing fraction", "{:>17.4f}"),
            ("kinetic", "kinetic [J]", "{:>12.3e}"),
        ),
    )


def _known_motion(scene: Scene, name: str) -> None:
    if name not in scene.motions:
        have = ", ".join(scene.motions) or "none"
        raise CliError(f"no motion named {name!r}; the scene's motions: {have}", scene.file, "--motion")


PLANS = {"tap": _tap_plan, "compress": _compress_plan, "anneal": _anneal_plan}


# -- running one


def _plain(value):
    """A record's value for JSON: arrays as lists, nan and inf as None."""
    if isinstance(value, np.ndarray):
        return [_plain(v) for v in value.tolist()]
    if isinstance(value, float | np.floating):
        return float(value) if math.isfinite(value) else None
    if isinstance(value, np.integer | np.bool_):
        return value.item()
    return value


def _row(record, columns) -> str:
    cells = []
    for field, heading, fmt in columns:
        value = getattr(record, field)
        width = len(heading) + 2
        if isinstance(value, np.ndarray):  # several walls: one value each
            text = " ".join(f"{v:.3e}" for v in value)
        else:
            try:
                text = fmt.format(value).strip()
            except (TypeError, ValueError):
                text = str(value)
        cells.append((" " + text).rjust(width))
    return "".join(cells)


def _csv_rows(records: list[dict], columns) -> tuple[list[str], list[list]]:
    header: list[str] = []
    for field, _, _ in columns:
        values = [r[field] for r in records]
        k = max((len(v) for v in values if isinstance(v, list)), default=0)
        header += [f"{field}_{i}" for i in range(k)] if k else [field]
    rows = []
    for r in records:
        row = []
        for field, _, _ in columns:
            v = r[field]
            row += v if isinstance(v, list) else [v]
        rows.append(["" if v is None else v for v in row])
    return header, rows


class ProtocolRun:
    """One ``polydem tap|compress|anneal`` of ``sim`` by ``plan``, writing into ``out_dir``."""

    def __init__(self, args: argparse.Namespace, scene: Scene, sim: Simulation, plan: Plan, out_dir: Path) -> None:
        self.args, self.scene, self.sim, self.plan, self.out_dir = args, scene, sim, plan, out_dir
        self.records: list[dict] = []
        self.errors: list[str] = []
        self.resumed_from: Path | None = None

    def on_record(self, record) -> None:
        row = {k: _plain(v) for k, v in dataclasses.asdict(record).items()}
        if "tap" in row:  # a resumed run measures again at the checkpoint's time when it fell on a step
            self.records = [r for r in self.records if r.get("tap") != row["tap"]]
        self.records.append(row)
        if not self.args.quiet:
            print(_row(record, self.plan.columns), flush=True)
        if signals.received():
            raise KeyboardInterrupt

    def execute(self) -> int:
        from polydem.simulation import SimulationError

        plan, sim = self.plan, self.sim
        if not self.args.quiet:
            print(f"polydem {plan.command}: {self.scene.name}, {plural(sim.num_bodies, 'body', 'bodies')} on "
                  f"{sim.device}, dt = {sim.dt:.3e} s")  # fmt: skip
            print("".join(heading.rjust(len(heading) + 2) for _, heading, _ in plan.columns), flush=True)
        t0 = time.perf_counter()
        reason, status = None, EXIT_OK
        signals.running()
        try:
            plan.run(sim, self.on_record)
        except KeyboardInterrupt:
            status = signals.exit_code()
            reason = "interrupted by the user (Ctrl-C)" if status == EXIT_INTERRUPTED else "stopped by SIGTERM"
        except SimulationError as exc:
            reason, status = f"SimulationError: {exc}", EXIT_FAILED
        except ValueError as exc:  # what the protocol cannot measure (a margin that leaves no box, say)
            reason, status = str(exc), EXIT_USER_ERROR
            self.errors.append(str(exc).replace("margin", "--margin"))
        finally:
            signals.finishing()
        wall = time.perf_counter() - t0
        checkpoint = self._checkpoint(reason)
        files = self._write(reason, wall, checkpoint)
        out = sys.stdout
        if reason is not None:
            out.write(f"stopped early: {reason}; {plural(len(self.records), 'record')} kept\n")
        for f in files:
            out.write(f"wrote {f}\n")
        out.flush()
        for e in self.errors:
            print(f"polydem: error: {e}", file=sys.stderr)
        return EXIT_FAILED if self.errors and status == EXIT_OK else status  # a record or file not written

    def _checkpoint(self, reason: str | None) -> Path | None:
        from polydem.checkpoint import save_checkpoint

        if reason is not None and not roll_back(self.sim):
            self.errors.append("no checkpoint: the state could not be brought back to a completed step")
            return None
        path = self.out_dir / "checkpoints" / ("final.npz" if reason is None else "interrupted.npz")
        try:
            path.parent.mkdir(parents=True, exist_ok=True)
            run = {"protocol": self.plan.command, "options": _plain(self.plan.options), "records": self.records}
            save_checkpoint(self.sim, path, run=run)
        except OSError as exc:
            self.errors.append(f"cannot write the checkpoint {relative(path, self.out_dir)}: {why(exc)}")
            return None
        return path

    def _write(self, reason: str | None, wall: float, checkpoint: Path | None) -> list[str]:
        sim, plan = self.sim, self.plan
        doc = {
            "protocol": plan.command,
            "scene": str(Path(self.scene.file).resolve()) if self.scene.file else None,
            "scene_name": self.scene.name,
            "device": str(sim.device),
            "precision": str(self.scene.precision),
            "dt": sim.dt,
            "num_bodies": sim.num_bodies,
            "options": {k: _plain(v) for k, v in plan.options.items()},
            "resumed_from": str(self.resumed_from.resolve()) if self.resumed_from is not None else None,
            "interrupted": reason is not None,
            "reason": reason,
            "wall_time": wall,
            "checkpoint": str(checkpoint.resolve()) if checkpoint is not None else None,
            "records": self.records,
        }
        written = []
        path = self.out_dir / f"{plan.command}.json"
        try:
            path.write_text(json.dumps(doc, indent=1, allow_nan=False) + "\n")
            written.append(str(path))
        except OSError as exc:
            self.errors.append(f"cannot write {path.name}: {why(exc)}")
        path = self.out_dir / f"{plan.command}.csv"
        header, rows = _csv_rows(self.records, plan.columns)
        try:
            with path.open("w", newline="") as f:
                w = csv.writer(f)
                w.writerow(header)
                w.writerows(rows)
            written.append(str(path))
        except OSError as exc:
            self.errors.append(f"cannot write {path.name}: {why(exc)}")
        if checkpoint is not None:
            written.append(str(checkpoint))
        return written


def _resume(args: argparse.Namespace, scene: Scene, sim: Simulation, plan: Plan, path: Path, ck) -> list[dict]:
    """Put the checkpoint ``ck`` of ``--resume`` into ``sim`` after checking it against ``scene``; the records of
    the tap run that wrote it (none for a checkpoint of another command)."""
    from polydem.checkpoint import restore_checkpoint

    check_resume(sim, scene, path, ck, args, "tap")
    run = ck.run if isinstance(ck.run, dict) else {}
    if run.get("protocol") != "tap":
        restore_checkpoint(sim, ck)
        return []  # the state of another command or run: this tap run's records start here
    # The records of the run it came from join this one's only where they were measured alike.
    before = run.get("options") if isinstance(run.get("options"), dict) else {}
    for key in ("motion", "margin", "lead"):
        old, value = before.get(key), plan.options[key]
        if old is not None and old != value:
            raise CliError(
                f"the tap run that wrote this checkpoint used --{key} {old}, this one --{key} {value}; give the same "
                f"--{key} to go on with its records",
                path,
                "--resume",
            )
    records = run.get("records")
    if not isinstance(records, list) or not all(isinstance(r, dict) and "tap" in r for r in records):
        raise CliError("the checkpoint's record of its tap run is damaged (records without a tap)", path, "--resume")
    restore_checkpoint(sim, ck)
    return [dict(r) for r in records]


def _cmd(args: argparse.Namespace, command: str) -> int:
    warp()
    signals.check()
    resume = checkpoint = None
    if getattr(args, "resume", None) is not None:
        resume, checkpoint = checkpoint_to_resume(args)  # a damaged file fails before anything is built
    scene, dev = scene_and_device(args)
    plan = PLANS[command](args, scene)
    out_dir = output_folder(args, scene)
    signals.check()

    from polydem.simulation import Simulation

    sim = Simulation(scene, device=dev)
    earlier = _resume(args, scene, sim, plan, resume, checkpoint) if resume is not None else []
    signals.check()
    run = ProtocolRun(args, scene, sim, plan, out_dir)
    # The records of the run resumed from stay in this one's files, before the new ones.
    run.records = earlier
    run.resumed_from = resume
    return run.execute()


def cmd_tap(args: argparse.Namespace) -> int:
    return _cmd(args, "tap")


def cmd_compress(args: argparse.Namespace) -> int:
    return _cmd(args, "compress")


def cmd_anneal(args: argparse.Namespace) -> int:
    return _cmd(args, "anneal")
