"""``polydem run``: set up a run (scene, device, output folder, resuming) and drive it.

:class:`Run` steps the simulation from stop to stop of its :class:`~polydem.cli.schedule.Schedule`;
at each stop it records the frames due (:class:`~polydem.cli.record.RunLog` and
:class:`~polydem.cli.outputs.Outputs`), writes a checkpoint when one is due and updates the
progress line. Whatever stops the run, it then writes the outputs, the summary and the closing
lines (:class:`~polydem.cli.report.Report`).
"""

from __future__ import annotations

import errno
import os
import sys
import time
from pathlib import Path
from typing import TYPE_CHECKING, NoReturn, TextIO

import numpy as np

from polydem import signals
from polydem.cli.common import plural, safe_name, shorten, steps_at
from polydem.cli.device import device, warp
from polydem.cli.errors import EXIT_FAILED, EXIT_INTERRUPTED, EXIT_OK, EXIT_USER_ERROR, CliError, OutputError, why
from polydem.cli.outputs import Outputs, scene_metadata
from polydem.cli.poses import check_poses, read_checkpoint
from polydem.cli.progress import Progress
from polydem.cli.record import RunLog, finite, run_record_problem
from polydem.cli.report import Report
from polydem.cli.schedule import Schedule
from polydem.cli.settings import DEFAULT_STEPS, check_outputs, load_scene, pictures_setting
from polydem.scene.bodies import BodyKind

if TYPE_CHECKING:
    import argparse

    import warp as wp

    from polydem.checkpoint import Checkpoint
    from polydem.distributed.comm import Comm
    from polydem.fronts import RunFront
    from polydem.scene import Scene
    from polydem.settle import SettleCheck, SettleCriterion

__all__ = ["Run", "cmd_run", "output_folder", "roll_back", "scene_and_device"]


def roll_back(sim: RunFront) -> bool:
    """Bring ``sim`` back to a consistent state after an exception inside ``Simulation.step``.

    A step interrupted part-way through a chunk has advanced the device state beyond
    ``sim.steps_done`` (and a SimulationError leaves a non-finite state); the copy saved at the
    start of that chunk is restored. Returns whether the state now matches ``sim.steps_done``.
    """
    try:
        return sim.restore_last_good()
    except Exception:
        return False


class Run:
    """One ``polydem run`` of ``sim`` (a :class:`~polydem.Simulation`, or rank 0's view of a decomposed run)
    to step ``target``, writing into ``out_dir``."""

    def __init__(
        self,
        args: argparse.Namespace,
        scene: Scene,
        sim: RunFront,
        out_dir: Path,
        target: int,
        resumed_from: Path | None,
        settle: SettleCheck | None = None,
    ) -> None:
        from polydem.simulation import CHUNK_STEPS

        self.args = args
        self.scene = scene
        self.sim = sim
        self.start = sim.steps_done
        self.settle = settle  # a polydem.settle.SettleCheck in a run until settled
        self.settle_wall: float | None = None
        o = scene.output
        fps = args.fps if args.fps is not None else o.fps
        every = CHUNK_STEPS if settle is not None else None
        self.schedule = Schedule(
            sim.dt, fps, target, self.start, o.checkpoint_steps, o.checkpoint_seconds, check_every=every
        )
        self.outputs = Outputs(
            scene,
            out_dir,
            self.start,
            resumed_from,
            vtk=bool(args.vtk or o.vtk or args.vtk_contact_types),
            picture_size=args.picture_size,
            vtk_contact_types=args.vtk_contact_types or False,
        )
        self.log = RunLog(scene, fps)
        self.pictures = pictures_setting(scene)
        self.progress: Progress | None = None
        self.report: Report | None = None
        self.t0 = time.perf_counter()

    @property
    def fps(self) -> float:
        return self.schedule.fps

    def continue_record(self, checkpoint: Checkpoint) -> None:
        """Continue the record of the run that wrote ``checkpoint`` (see :meth:`RunLog.continue_from`)."""
        self.log.continue_from(checkpoint)

    def run_record(self, writing: Path | None = None) -> dict:
        """The record of the run up to now, kept in its checkpoints (``writing``: the checkpoint
        being written). Paths are absolute, so a run resumed into another folder still finds them."""
        o = self.outputs
        wall = time.perf_counter() - self.t0
        checkpoints = o.absolute(o.checkpoints)
        if writing is not None:
            checkpoints.append(str(Path(writing).resolve()))
        rec = self.log.record(wall, o.part(self.sim.steps_done, wall), o.absolute(o.picture_files), checkpoints)
        if self.settle is not None:
            rec["settle"] = finite(self.settle.record())
        return rec

    def check_settled(self) -> bool:
        """In a run until settled, check the criterion when a check is due; returns whether the pile settled."""
        sim = self.sim
        if self.settle is None or not self.schedule.settle_check_due(sim.steps_done):
            return False
        if sim.steps_done % self.schedule.check_every:
            # The end of a run off the check cadence: measure for the report, but leave the hold as it
            # is, so that a run resumed from this step holds from where the unbroken run would.
            self.settle.holds(*sim.settle_measures())
            settled = False
        else:
            settled = self.settle.update(sim.steps_done, sim.dt, *sim.settle_measures())
        frac, limit = self.settle.kinetic_fraction, self.settle.speed_limit
        if self.progress is not None:
            note = f"  kinetic/released {frac:.2e}" if frac is not None else ""
            if limit is not None:
                note += f"  largest speed {self.settle.largest_speed:.2e} m/s (limit {limit:.2e})"
            self.progress.settle_note = note
        if settled:
            self.settle_wall = time.perf_counter() - self.t0
        return settled

    def settle_summary(self) -> dict | None:
        """The summary's ``settle`` entry (None in a run of fixed length)."""
        c = self.settle
        if c is None:
            return None
        sim = self.sim
        earlier = (self.log.earlier or {}).get("wall_time", 0.0)
        settled = c.settled_at is not None
        return finite(
            {
                "criterion": c.criterion.to_dict(),
                "settled": settled,
                "time_s": c.settled_at * sim.dt if settled else None,
                "steps": c.settled_at if settled else None,
                "wall_s": earlier + self.settle_wall if settled and self.settle_wall is not None else None,
                "held_from_s": c.held_since * sim.dt if c.held_since is not None else None,
                "max_steps": self.schedule.target,
                "max_time_s": self.schedule.target * sim.dt,
                "kinetic": c.kinetic,
                "released": c.released,
                "kinetic_fraction": c.kinetic_fraction,
                "largest_speed": c.largest_speed,
                "speed_limit": c.speed_limit,
            }
        )

    # -- at each stop

    def record_frames(self) -> None:
        """Record the frame due at this step, if any (and pass the frames up to it, with their pictures)."""
        sim, schedule = self.sim, self.schedule
        steps = sim.steps_done
        if not schedule.at_frame(steps):
            return
        contacts = sim.contacts()
        if not self.log.holds(sim.time, sim.dt):
            energy = self.log.add_frame(sim, contacts)
            if self.progress is not None:
                self.progress.note(steps, len(contacts["volume"]), energy["kinetic"])
        self.outputs.record_frame(sim, contacts, schedule.frame)
        while schedule.frame_step(schedule.frame) <= steps:
            if isinstance(self.pictures, tuple) and schedule.frame in self.pictures:
                self.outputs.picture(sim, f"frame_{schedule.frame:06d}.png")
            schedule.frame += 1

    def periodic_checkpoint(self) -> None:
        steps = self.sim.steps_done
        if self.schedule.checkpoint_due(steps):
            self.outputs.checkpoint(self.sim, f"step_{steps:09d}.npz", self.run_record)

    # -- the run

    def execute(self, out: TextIO, err: TextIO) -> int:
        """Run to the target step; whatever stops the run, write the outputs. Returns the exit code."""
        self.outputs.out_dir.mkdir(parents=True, exist_ok=True)
        self.progress = Progress(err, self.start, self.schedule.target, self.sim.dt, enabled=not self.args.quiet)
        energy = self.sim.energy()
        log = self.log
        log.energy_initial = energy if log.earlier is None else log.earlier["energy_initial"]
        self.report = Report(
            self.args,
            self.scene,
            self.sim,
            log=log,
            outputs=self.outputs,
            schedule=self.schedule,
            pictures=self.pictures,
            energy_at_start=energy,
        )
        self.t0 = time.perf_counter()
        return self._execute(out, err)

    def _steps(self) -> None:
        sim, progress = self.sim, self.progress
        self.outputs.open(self.fps, self.schedule.frame_dt, scene_metadata(self.args.scene))
        self.record_frames()
        while sim.steps_done < self.schedule.target:
            sim.step(self.schedule.next_stop(sim.steps_done, progress.next_mark(sim.steps_done)) - sim.steps_done)
            # Before the checkpoint: it keeps the check at its step, as a resumed run expects.
            settled = self.check_settled()
            self.record_frames()
            self.periodic_checkpoint()
            progress.update(sim, force=settled)
            if settled:
                break
            if signals.received():
                raise KeyboardInterrupt

    def _execute(self, out: TextIO, err: TextIO) -> int:
        from polydem.simulation import SimulationError

        reason = failure = internal = None
        status = EXIT_OK
        signals.running()
        try:
            self._steps()
        except CliError:
            raise
        except KeyboardInterrupt:
            status = signals.exit_code()
            reason = "interrupted by the user (Ctrl-C)" if status == EXIT_INTERRUPTED else "stopped by SIGTERM"
        except SimulationError as exc:
            reason = f"SimulationError: {exc}"
            failure = f"the simulation failed: {exc}"
            status = EXIT_FAILED
        except OutputError as exc:
            reason = f"an output could not be written: {exc}"
            self.outputs.errors.append(str(exc))
            status = EXIT_FAILED
        except Exception as exc:
            reason = f"internal error: {type(exc).__name__}: {exc}"
            internal = exc
            status = EXIT_FAILED
        finally:
            signals.finishing()
            self.outputs.close()
        try:
            self._finish(out, err, reason, status)
        except Exception:
            if internal is None:
                raise
            err.write("polydem: the outputs could not be completed after the internal error below\n")
        if internal is not None:
            raise internal
        errors = ([failure] if failure else []) + self.outputs.errors
        if errors:
            more = f" (and {plural(len(errors) - 1, 'other error')}: see the lines above)" if len(errors) > 1 else ""
            err.write(f"polydem: error: {errors[0]}{more}\n")
            err.flush()
            if status == EXIT_OK:
                status = EXIT_FAILED
        return status

    def _finish(self, out: TextIO, err: TextIO, reason: str | None, status: int) -> None:
        """Final checkpoint and picture, plots, the summary, and the closing lines (also after an interruption)."""
        sim, o = self.sim, self.outputs
        wall = time.perf_counter() - self.t0
        notes = []
        consistent = True if reason is None else roll_back(sim)
        self.progress.finish(sim if consistent else None)
        cp_path = None
        if consistent:
            name = "final.npz" if reason is None else "interrupted.npz"
            cp_path = o.attempt(o.checkpoint, sim, name, self.run_record)
            if self.pictures == "last":
                o.attempt(o.picture, sim, "last.png")
        else:
            notes.append("no checkpoint: the state could not be brought back to a completed step")
        note = o.write_plots(self.log.history)
        if note is not None:
            notes.append(note)
        summary = self.report.summary(wall, reason, notes, consistent)
        if consistent and note is None:  # the history's plots were written: matplotlib is there
            more = o.write_measure_plots(self.scene, sim, summary.get("measures"))
            if more is not None:
                summary.setdefault("notes", []).append(more)
        if self.settle is not None:
            summary["settle"] = self.settle_summary()
        summary["outputs"]["plots"] = o.plot_files
        if o.errors:
            summary["not_written"] = list(o.errors)
        summary["history"] = self.log.history
        o.write_summary(summary)
        self.report.report(out, err, summary, cp_path, reason, status)


def _target_steps(args: argparse.Namespace, scene: Scene, dt: float) -> tuple[int, str]:
    """Total steps from t = 0 and where they come from."""
    if args.steps is not None:
        return args.steps, "--steps"
    if args.duration is not None:
        return max(1, steps_at(args.duration, dt)), f"--duration {args.duration:g} s"
    if scene.duration is not None:
        return max(1, steps_at(scene.duration, dt)), f"duration {scene.duration:g} s"
    if scene.steps is not None:
        return scene.steps, "the scene's steps"
    return DEFAULT_STEPS, "the default"


def checkpoint_to_resume(args: argparse.Namespace) -> tuple[Path | None, Checkpoint | None]:
    """The path and the checked checkpoint of ``--resume`` (None, None without it)."""
    if args.resume is None:
        return None, None
    resume = Path(args.resume)
    if not resume.is_file():
        raise CliError(
            f"checkpoint not found (looked for '{resume.absolute()}'); give a .npz file from a run's "
            "checkpoint folder, e.g. polydem_out/<scene>/checkpoints/final.npz",
            resume,
            "--resume",
        )
    return resume, read_checkpoint(resume, "--resume")


def output_folder(args: argparse.Namespace, scene: Scene) -> Path:
    """The output folder (``--out``, default ``polydem_out/<scene name>/``), made if missing."""
    if args.out is not None:
        out_dir = Path(args.out)
        try:
            if out_dir.exists() and not out_dir.is_dir():
                raise CliError("the output folder is a file; give a folder with --out", out_dir, "--out")
            out_dir.mkdir(parents=True, exist_ok=True)
        except OSError as exc:
            raise CliError(f"cannot create the output folder ({why(exc)})", shorten(out_dir), "--out") from None
        return out_dir
    # No --out: the folder is named after the scene, so a failure is the name's or the current folder's.
    out_dir = Path("polydem_out") / safe_name(scene.name)
    made = not out_dir.parent.exists()
    try:
        if out_dir.exists() and not out_dir.is_dir():
            raise CliError(
                f"the default output folder {shorten(out_dir)} is a file; remove it or give a folder with --out",
                key=None,
            )
        out_dir.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        if made:
            try:
                out_dir.parent.rmdir()  # made for this run, which writes nothing
            except OSError:
                pass
        if exc.errno == errno.ENAMETOOLONG:
            raise CliError(
                f"the name ({len(scene.name)} characters) is too long for the name of the default output folder "
                f"polydem_out/NAME/ ({exc.strerror}); give a shorter simulation.name, or an output folder with --out",
                scene.file,
                "simulation.name",
            ) from None
        raise CliError(f"cannot create the default output folder {shorten(out_dir)} ({why(exc)})", key=None) from None
    return out_dir


def cmd_run(args: argparse.Namespace) -> int:
    from polydem.distributed.comm import launched_size

    if launched_size() > 1:
        return _cmd_run_decomposed(args)
    warp()
    signals.check()
    resume, checkpoint, scene, dev = _load(args, pairs_later=True)
    out_dir = output_folder(args, scene)
    check_outputs(args, scene, out_dir)  # before the kernels compile and the run starts
    criterion = _settle_criterion(args, scene)
    signals.check()

    from polydem.simulation import Simulation

    # validated by _load; the body pairs' overlaps, where left to the device, checked in the Simulation's build
    sim: RunFront = Simulation(scene, device=dev, validate=False)
    return _run(args, scene, sim, out_dir, resume, checkpoint, criterion)


def _load(
    args: argparse.Namespace, pairs_later: bool = False
) -> tuple[Path | None, Checkpoint | None, Scene, wp.DeviceLike]:
    """The checkpoint to resume (path and contents, or None), the scene with the options applied, and the device
    (``pairs_later``: see :func:`scene_and_device`)."""
    resume, checkpoint = checkpoint_to_resume(args)  # a damaged file fails before the model is built
    scene, dev = scene_and_device(args, pairs_later)
    return resume, checkpoint, scene, dev


def scene_and_device(args: argparse.Namespace, pairs_later: bool = False) -> tuple[Scene, wp.DeviceLike]:
    """The scene of ``args.scene`` with ``--precision`` applied, validated, and the device: ``--device``, else the
    scene's (None: Warp's default). ``pairs_later``: the initial overlaps of body pairs are left to the Simulation
    where it checks them on its device (a large scene on CUDA: :mod:`polydem.overlap_check`), which then
    finishes the scene's validation; validated once, after the options."""
    scene = load_scene(args.scene, validate=not pairs_later)
    if args.precision is not None:
        scene.precision = args.precision
    dev = device(args.device) if args.device is not None else None
    if dev is None and scene.device is not None:
        dev = device(scene.device, file=scene.file, key="simulation.device")
    if pairs_later:
        from polydem.overlap_check import device_check_applies

        scene.validate(pair_overlaps=not device_check_applies(scene, dev))
    return scene, dev


def _cmd_run_decomposed(args: argparse.Namespace) -> int:
    """``mpiexec -n R polydem run``: rank 0 runs the command on a RootSimulation, the others follow it
    (:mod:`polydem.distributed.root`).

    Before the run every rank checks what it loads (the scene, the checkpoint, the settings; rank 0 also
    the output folder) and then all agree (:func:`_agree`): where some rank failed, rank 0 prints the
    error once, as a run of one process would (naming the rank when it is another's), and every rank
    exits normally with the same code, with nothing written. A rank that fails during the run, while
    the others wait for it, aborts every rank instead (MPI_Abort), with one line naming it.
    """
    import warnings

    from polydem.distributed import DistributedSimulation, world
    from polydem.distributed.comm import launched_rank
    from polydem.distributed.root import RootSimulation, device_for_rank, serve

    warp()
    signals.check()
    try:
        comm = world()
    except RuntimeError as exc:  # no mpi4py: every rank fails alike, before MPI
        if launched_rank() != 0:
            return EXIT_USER_ERROR
        raise CliError(str(exc), key=None) from None
    root = comm.Get_rank() == 0
    if not root:
        warnings.simplefilter("ignore")  # rank 0 says it once
    failure = None
    resume = checkpoint = scene = dev = out_dir = criterion = None
    try:
        resume, checkpoint, scene, dev = _load(args)
        if args.exchange == "nccl":
            _check_nccl(dev)
        if root:
            out_dir = output_folder(args, scene)
            check_outputs(args, scene, out_dir)
        criterion = _settle_criterion(args, scene)
    except Exception as exc:
        failure = exc
    code = _agree(comm, failure)
    if code is not None:
        return code
    # Split_type in device_for_rank is collective: only once every rank is known to get there.
    dev = device_for_rank(dev, comm)
    try:
        import warp as wp

        wp.get_device(dev)  # a device missing on some node fails here, not inside the collective constructor
    except Exception as exc:
        failure = exc
    code = _agree(comm, failure)
    if code is not None:
        return code
    ds = None
    try:
        ds = DistributedSimulation(scene, device=dev, comm=comm, exchange=args.exchange)
    except Exception as exc:  # after its collective steps (the partition): building the rank's Simulation
        failure = exc
    code = _agree(comm, failure)
    if code is not None:
        return code
    if not root:
        # Ctrl-C and SIGTERM reach every rank: rank 0 decides (it stops after the steps under way and
        # writes the outputs with the others' help); a follower that died of them would leave it waiting.
        import signal

        signal.signal(signal.SIGINT, signal.SIG_IGN)
        signal.signal(signal.SIGTERM, signal.SIG_IGN)
        try:
            return serve(ds)
        except Exception as exc:
            _abort(comm, exc)
    sim = RootSimulation(ds, on_error=lambda exc: _abort(comm, exc))
    code = EXIT_FAILED
    try:
        owned, _ = sim.balance()
        sys.stdout.write(
            f"{scene.name}: decomposed over {ds.size} ranks (slabs along {'xyz'[ds.axis]}, "
            f"{int(owned.min())} to {int(owned.max())} bodies each; ghosts exchanged through "
            f"{'NCCL, GPU to GPU' if ds.exchange == 'nccl' else 'host memory'})\n"
        )
        code = _run(args, scene, sim, out_dir, resume, checkpoint, criterion)
        return code
    except KeyboardInterrupt:
        code = signals.exit_code()
        raise
    except Exception as exc:
        code = EXIT_USER_ERROR if _user_error(exc) else EXIT_FAILED
        raise
    finally:
        sim.stop(code)  # the others exit with rank 0's code


def _check_nccl(dev) -> None:
    """``--exchange nccl`` can work on this rank's device ``dev`` (None: the default): a GPU, and nccl4py installed
    (else a CliError naming the option)."""
    import warp as wp

    from polydem.distributed.nccl import load_nccl

    if dev is None:
        dev = "cuda:0" if wp.get_cuda_device_count() else "cpu"
    dev = wp.get_device(dev)
    if not dev.is_cuda:
        raise CliError(
            f"nccl sends the ghost rows from GPU to GPU, but this rank runs on {dev}: run on GPUs "
            "(--device cuda, one per rank) or leave --exchange at host",
            key="--exchange",
        )
    try:
        load_nccl()
    except RuntimeError as exc:
        raise CliError(
            "nccl needs nccl4py (NVIDIA's NCCL bindings): pip install 'polydem[nccl]' (NCCL for CUDA 13) or "
            "pip install 'nccl4py[cu12]' (CUDA 12); or leave --exchange at host",
            key="--exchange",
        ) from exc


def _user_error(exc: BaseException) -> bool:
    return isinstance(exc, CliError) or type(exc).__name__ == "SceneError"


def _agree(comm: Comm, failure: Exception | None) -> int | None:
    """Whether some rank failed (``failure``: this rank's exception, or None), agreed by all (collective).

    None where none did. Else rank 0 raises its own exception (printed as a run of one process prints it)
    or, where only another rank failed, that rank's error naming it (the lowest such rank's; an internal
    error with its traceback); the other ranks return the exit code rank 0 ends with (2 for a user error,
    1 for an internal one) without printing: each would otherwise print the same line, and an MPI_Abort
    adds lines of its own.
    """
    import traceback

    mine = None
    if failure is not None:
        user = _user_error(failure)
        line = str(failure) if user else f"{type(failure).__name__}: {failure}"
        text = "" if user else "".join(traceback.format_exception(failure))
        mine = (user, line, text)
    reports = comm.allgather(mine)
    failed = [(r, rep) for r, rep in enumerate(reports) if rep is not None]
    if not failed:
        return None
    rank, (user, line, text) = failed[0]
    code = EXIT_USER_ERROR if user else EXIT_FAILED
    if comm.Get_rank() != 0:
        return code
    if rank == 0:
        raise failure
    where = f"rank {rank} of {comm.Get_size()}"
    if user:
        raise CliError(f"{where}: {line}", key=None)
    sys.stdout.flush()
    sys.stderr.write(f"{text}polydem: error: {where}: internal error: {line}\n")
    sys.stderr.flush()
    return code


def _abort(comm: Comm, exc: BaseException) -> NoReturn:
    """Print ``exc`` as this rank's error and abort every rank (MPI_Abort, exit code 2): during the run,
    where the others may be waiting for this rank inside a collective call and cannot agree."""
    message = str(exc) if _user_error(exc) else f"{type(exc).__name__}: {exc}"
    sys.stderr.write(f"polydem: error: rank {comm.Get_rank()} of {comm.Get_size()}: {message}\n")
    sys.stderr.flush()
    comm.Abort(2)
    # MPICH's MPI_Abort may return to the caller before the process manager ends the ranks: carrying on
    # would fail again on state that was never built (and print a second error).
    os._exit(2)


def _run(
    args: argparse.Namespace,
    scene: Scene,
    sim: RunFront,
    out_dir: Path,
    resume: Path | None,
    checkpoint: Checkpoint | None,
    criterion: SettleCriterion | None,
) -> int:
    out, err = sys.stdout, sys.stderr
    signals.check()
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
    else:
        _warn_run_span(scene, sim.dt, target, source)
    settle = _settle_check(sim, criterion, checkpoint, resume) if criterion is not None else None
    run = Run(args, scene, sim, out_dir, target, resume, settle)
    if checkpoint is not None:
        run.continue_record(checkpoint)
    kind = np.asarray(scene.body_kind)
    what = f"from step {sim.steps_done} (t = {sim.time:.6g} s) " if resume is not None else ""
    if criterion is not None:
        what += f"until settled ({criterion.describe(scene)}), at most "
    out.write(
        f"{scene.name}: {plural(sim.num_bodies, 'body', 'bodies')} ({int(np.sum(kind == BodyKind.FREE))} free) on "
        f"{sim.device}, dt {sim.dt:.4g} s; "
        f"{what}to step {target} (t = {target * sim.dt:.6g} s, {source}); frames at {run.fps:g} per simulated s; "
        f"output in {out_dir}{os.sep}\n"
    )
    out.flush()
    return run.execute(out, err)


def _warn_run_span(scene: Scene, dt: float, target: int, source: str) -> None:
    """A warning where the run would change nothing or, of the default length, covers next to no time
    (:meth:`Scene.check_run_span`): the scene is sound, but the run is most likely not what was meant."""
    import warnings

    from polydem.scene import SceneWarning

    for message in scene.check_run_span(dt, target, source, default=source == "the default"):
        warnings.warn(f"{scene.file}: {message}" if scene.file else message, SceneWarning, stacklevel=2)


_SETTLE_OPTIONS = (
    ("--settle-kinetic", "settle_kinetic"),
    ("--settle-speed-fraction", "settle_speed_fraction"),
    ("--settle-speed", "settle_speed"),
    ("--settle-hold", "settle_hold"),
)


def _settle_criterion(args: argparse.Namespace, scene: Scene) -> SettleCriterion | None:
    """The SettleCriterion of a run until settled (``--until-settled`` or the scene's), None for a run
    of fixed length; a setting that cannot work is a CliError naming the option."""
    from dataclasses import replace

    from polydem.settle import SettleCriterion

    given = [
        (option, getattr(args, dest))
        for option, dest in _SETTLE_OPTIONS
        if getattr(args, dest, None) is not (False if dest in ("settle_kinetic", "settle_speed_fraction") else None)
    ]
    base = scene.settle if scene.settle is not None else SettleCriterion() if args.until_settled else None
    if base is None:
        if given:
            raise CliError(
                f"{given[0][0]} sets the criterion of a run until settled: add --until-settled (or set [simulation] "
                "until_settled = true in the scene)",
                key=given[0][0],
            )
        return None
    fields = {
        "--settle-kinetic": "kinetic_fraction",
        "--settle-speed-fraction": "speed_fraction",
        "--settle-speed": "max_speed",
        "--settle-hold": "hold",
    }
    try:
        criterion = replace(base, **{fields[option]: value for option, value in given})
    except ValueError:
        raise CliError(
            "--settle-kinetic off with no speed limit (--settle-speed-fraction off) leaves nothing to check: give "
            "--settle-speed V (the largest speed in m/s) or a --settle-speed-fraction",
            key="--settle-kinetic" if args.settle_kinetic is None else "--settle-speed-fraction",
        ) from None
    if not np.any(np.asarray(scene.body_kind) == BodyKind.FREE):
        raise CliError("the scene has no free bodies: there is nothing to settle; leave --until-settled out", key=None)
    try:
        criterion.check_gravity(scene.gravity)
    except ValueError:
        raise CliError(
            "the scene has no gravity, so no gravitational energy is released to compare the kinetic energy with: "
            "give --settle-kinetic off --settle-speed V (the largest speed in m/s)",
            key="--settle-kinetic" if args.settle_kinetic is not False else "--until-settled",
        ) from None
    return criterion


def _settle_check(sim: RunFront, criterion: SettleCriterion, ck: Checkpoint | None, path: Path | None) -> SettleCheck:
    """The SettleCheck of a run until settled: from t = 0, or continued from the checkpoint ``ck``."""
    from polydem.settle import SettleCheck

    rec = (ck.run or {}).get("settle") if ck is not None else None
    limit = criterion.speed_limit_of(sim.scene, sim.model.settings)
    if rec is None:
        # A run from t = 0, or one resumed from a run of fixed length: the energy released counts from t = 0
        # where the checkpoint's record knows it.
        energy = (ck.run or {}).get("energy_initial") if ck is not None else None
        start = energy["gravity"] if energy is not None and energy.get("gravity") is not None else None
        return SettleCheck(criterion, sim.settle_measures()[1] if start is None else start, speed_limit=limit)
    if rec.get("settled_at") is not None:
        raise CliError(
            f"the run of this checkpoint settled at step {rec['settled_at']} (t = {rec['settled_at'] * sim.dt:.6g} s): "
            "leave out --until-settled (and the scene's until_settled) to run on from it",
            path,
            "--resume",
        )
    start, held = rec.get("gravity_at_start"), rec.get("held_since")
    if not isinstance(start, int | float) or not (
        held is None or isinstance(held, int) and 0 <= held <= sim.steps_done
    ):
        raise CliError(
            "the settle record of its run is damaged (gravity_at_start, held_since): use another checkpoint of the "
            "run or rerun",
            path,
            "--resume",
        )
    same = rec.get("criterion") == criterion.to_dict()
    return SettleCheck(criterion, float(start), held if same else None, speed_limit=limit)


def check_resume(sim, scene: Scene, path: Path, ck: Checkpoint, args: argparse.Namespace, command: str) -> None:
    """CliError (naming ``--resume``) unless the checkpoint ``ck`` of ``--resume`` fits ``scene`` and ``sim``: its
    poses against the scene's walls, then its physics (``polydem COMMAND SCENE --resume CHECKPOINT``)."""
    from polydem.checkpoint import CheckpointError, check_scene

    fix = f"resume with the scene the checkpoint was written from: polydem {command} SCENE --resume CHECKPOINT"
    check_poses(path, ck.arrays["body_q"][:, :3], scene, args.scene, "checkpoint", fix, "--resume")
    try:
        check_scene(ck, sim, fix=f"{fix} (or leave --resume out to {command} this scene from t = 0)")
    except CheckpointError as err:
        raise CliError(err.message, path, "--resume") from None


def _resume(sim: RunFront, scene: Scene, path: Path, ck: Checkpoint, args: argparse.Namespace) -> None:
    """Put the checkpoint ``ck`` (read from ``path``) into ``sim`` after checking it against ``scene``."""
    from polydem.checkpoint import restore_checkpoint

    check_resume(sim, scene, path, ck, args, "run")
    fps = args.fps if args.fps is not None else scene.output.fps
    problem = run_record_problem(ck.run, fps, ck.time, sim.dt) if ck.run is not None else None
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
