"""The files of one part of a run (from t = 0, or from the checkpoint it resumed from): the USD
animation, the VTK series, pictures, checkpoints, plots and the summary.

With VTK output the contact forces are averaged over each interval between frames
(``Simulation.start_contact_average``, started again at every frame): the VTK contact network of a
frame carries the average over the interval before it, and the summary the average over the last
interval. Without it nothing is averaged: the steps of an average run the report variant of the
contact kernels, measured 7% slower (27k cubes on an H200).

A file that cannot be written once the run has started is an :class:`OutputError` (the run
stops, the other outputs are still written) or, at the end, a line in ``errors``.
"""

from __future__ import annotations

import json
import os
from pathlib import Path

import numpy as np

from polydem.cli.common import relative, remove, resolve, shorten
from polydem.cli.errors import CliError, OutputError, why
from polydem.cli.record import finite
from polydem.cli.settings import output_paths

__all__ = ["Outputs", "scene_metadata"]


def scene_metadata(scene_arg) -> dict:
    """What the USD file and the summary record of the scene, so that ``polydem render`` finds it."""
    if scene_arg is None:
        return {"default_scene": True}
    return {"scene_file": str(Path(scene_arg).resolve())}


class Outputs:
    """The output files of the part of a run that starts at step ``start`` in ``out_dir``."""

    def __init__(
        self, scene, out_dir: Path, start: int, resumed_from, *, vtk: bool, picture_size, vtk_contact_types=False
    ):
        self.scene = scene
        self.out_dir = out_dir
        self.start = start
        self.resumed_from = resumed_from
        self.picture_size = picture_size
        paths = output_paths(scene, out_dir)
        self.cp_dir = paths["output.checkpoint.path"]
        self.summary_path = paths.get("output.summary")
        self.usd_path = paths.get("output.usd")
        if self.usd_path is not None and resumed_from is not None:
            p = self.usd_path
            self.usd_path = p.with_name(f"{p.stem}.from_step_{start}{p.suffix}")
        self.vtk_dir = out_dir / "vtk" if vtk else None
        self.vtk_contact_types = vtk_contact_types  # the VtkWriter's contact_types: False, or a method
        self.usd = None  # the UsdRecorder, made by open()
        self.vtk = None  # the VtkWriter, made by open() when VTK output is on (--vtk or output.vtk)
        self.usd_failed = False
        self.usd_codes: list[float] = []  # time codes of the first and last frame of this part's USD file
        self.errors: list[str] = []  # outputs that could not be written (one line each)
        self.picture_files: list[str] = []
        self.checkpoints: list[str] = []
        self.plot_files: list[str] = []
        self.summary_written = False
        self.last_average: dict | None = None  # the contact-force average over the last interval between frames

    def rel(self, path) -> str:
        """``path`` as the closing lines and the summary name it: relative to the output folder."""
        return shorten(relative(path, self.out_dir))

    def open(self, fps: float, frame_dt: float, metadata: dict) -> None:
        """Open the USD file and the VTK series (a USD file that cannot be made is a CliError)."""
        if self.usd_path is not None:
            from polydem.usd import UsdRecorder

            try:
                rec = UsdRecorder(self.usd_path, self.scene, fps=fps, frame_dt=frame_dt)
            except Exception as exc:  # nothing has run yet: the user can fix it and start again
                raise CliError(f"cannot write the USD file: {why(exc)}", self.usd_path, "output.usd") from None
            rec.set_metadata(**metadata)
            self.usd = rec
        if self.vtk_dir is not None:
            from polydem.vtk import VtkWriter

            self.vtk = VtkWriter(
                self.vtk_dir, self.scene, resume=self.resumed_from is not None, contact_types=self.vtk_contact_types
            )

    def frame_average(self, sim) -> dict | None:
        """The contact-force average over the interval since the last frame ({} at the first one),
        and a new interval from this step; None without VTK output or where ``sim`` keeps no average."""
        if self.vtk_dir is None:
            return None
        steps = sim.contact_average_steps
        average = sim.contact_average() if steps else {}
        if average:
            self.last_average = average
        sim.start_contact_average()
        if sim.contact_average_steps is None:
            return None  # a front that keeps no average (a decomposed run): no averaged fields, not zeros
        return average

    def average_summary(self, sim) -> dict | None:
        """The summary's ``contact_average``: the contact forces averaged over the last interval between
        frames (or from the last frame to the end where the run stopped between frames); None where
        nothing was averaged (no VTK output)."""
        if self.vtk_dir is None:
            return None
        steps = sim.contact_average_steps
        a = sim.contact_average() if steps else self.last_average
        if not a:
            return None
        b = a["body_b"]
        fn = a["normal_force"]
        walls = []
        for j in range(sim.model.num_walls):
            on = b == -1 - j
            walls.append({"wall": j, "force": (-a["force"][on].sum(axis=0)).tolist()})
        largest = None
        if len(fn):
            i = int(np.argmax(fn))
            largest = {
                "normal_force": float(fn[i]),
                "body_a": int(a["body_a"][i]),
                "body_b": int(b[i]) if b[i] >= 0 else None,
                "wall": int(-1 - b[i]) if b[i] < 0 else None,
            }
        return {
            "from_time": a["start_time"],
            "to_time": a["end_time"],
            "steps": a["steps"],
            "contacts": len(fn),
            "mean_normal_force": float(np.mean(fn)) if len(fn) else None,
            "largest": largest,
            "walls": walls,
        }

    def record_frame(self, sim, contacts, frame: int) -> None:
        """Add the state of ``sim`` as frame ``frame`` to the USD file and the VTK series (with the
        contact forces averaged since the last frame)."""
        average = self.frame_average(sim)
        rec = self.usd
        if rec is not None and (rec.last_time_code is None or rec.time_code(sim.time) > rec.last_time_code):
            try:
                rec.record_simulation(sim)  # saves the file now and then
            except Exception as exc:
                self.usd_failed = True
                raise OutputError(f"cannot write the USD file {self.rel(self.usd_path)}: {why(exc)}") from exc
            self.usd_codes = [*self.usd_codes[:1], rec.last_time_code]
        if self.vtk is not None and (self.vtk.last_index is None or frame > self.vtk.last_index):
            try:
                mesh = sim.current_state.mesh_q.numpy() if sim.model.num_mesh_walls else None
                self.vtk.record(sim.time, sim.state(), contacts, index=frame, mesh_poses=mesh, average=average)
            except OSError as exc:
                raise OutputError(f"cannot write the VTK files in {self.rel(self.vtk_dir)}: {why(exc)}") from exc

    def close(self) -> None:
        """Close the USD file: the frames so far are kept, whatever happened."""
        if self.usd is None:
            return
        try:
            self.usd.close()
        except Exception as exc:
            if not self.usd_failed:
                self.errors.append(f"cannot save the USD file {self.rel(self.usd_path)}: {why(exc)}")
            self.usd_failed = True

    def picture(self, sim, name: str) -> None:
        from polydem.picture_memory import PictureSizeError
        from polydem.render import render_simulation

        path = self.out_dir / "pictures" / name
        width, height = self.picture_size
        try:
            path.parent.mkdir(parents=True, exist_ok=True)
            render_simulation(sim, path, width=width, height=height)
        except OSError as exc:
            raise OutputError(f"cannot write the picture {self.rel(path)}: {why(exc)}") from exc
        except PictureSizeError as exc:  # the GPU's memory, or memory the run took since it was checked
            fix = "give a smaller --picture-size"
            raise OutputError(f"cannot draw the picture {self.rel(path)}: {exc}; {fix}") from exc
        except (MemoryError, RuntimeError) as exc:
            # Warp's failed allocations are RuntimeErrors: the picture is lost, not the plots and the
            # summary written after it.
            raise OutputError(f"cannot draw the picture {self.rel(path)}: {why(exc)}") from exc
        self.picture_files.append(relative(path, self.out_dir))

    def checkpoint(self, sim, name: str, run_record) -> Path:
        """Write the checkpoint ``name`` with ``run_record(path)``, the record of the run so far."""
        from polydem.checkpoint import save_checkpoint

        path = self.cp_dir / name
        try:
            self.cp_dir.mkdir(parents=True, exist_ok=True)
            save_checkpoint(sim, path, run=run_record(path))
        except OSError as exc:
            remove(Path(f"{path}.tmp.npz"))  # save_checkpoint's temporary file
            raise OutputError(f"cannot write the checkpoint {self.rel(path)}: {why(exc)}") from exc
        self.checkpoints.append(relative(path, self.out_dir))
        return path

    def attempt(self, write, *args):
        """``write(*args)``; an output that cannot be written is noted in ``errors`` (returns None)."""
        try:
            return write(*args)
        except OutputError as exc:
            self.errors.append(str(exc))
            return None

    def absolute(self, names) -> list[str]:
        return [str(resolve(self.out_dir, p).resolve()) for p in names]

    def part(self, to_step: int, wall: float) -> dict:
        """This part of the run (from the start or the checkpoint resumed from, to ``to_step``)."""
        rec = self.usd
        return {
            "from_step": self.start,
            "to_step": to_step,
            "folder": str(self.out_dir.resolve()),
            "resumed_from": str(Path(self.resumed_from).resolve()) if self.resumed_from is not None else None,
            "usd": str(self.usd_path.resolve()) if self.usd_path is not None else None,
            "usd_frames": rec.frames if rec is not None else 0,
            "usd_time_codes": [self.usd_codes[0], self.usd_codes[-1]] if self.usd_codes else None,
            "wall_time": wall,
        }

    def write_plots(self, history) -> str | None:
        """The plots of the frame history; returns a note when there are none (no matplotlib)."""
        from polydem.plots import write_plots

        try:
            plots = write_plots(history, self.out_dir)
        except OSError as exc:
            self.errors.append(f"cannot write the plots: {why(exc)}")
            plots = []
        except Exception as exc:  # matplotlib itself: the plots are an extra, the run is fine
            plots = f"no plots: matplotlib failed ({why(exc)})"
        if isinstance(plots, str):
            return plots
        self.plot_files = [relative(p, self.out_dir) for p in plots]
        return None

    def write_measure_plots(self, scene, sim, measured: dict | None) -> str | None:
        """``measures.png`` of the settled region that the summary's ``measured`` (``measures``) describes; returns
        a note when there is none (no matplotlib, no region, no contact in it)."""
        from polydem import measures
        from polydem.plots import write_measure_plots

        if not measured or "box" not in measured:
            return None  # the summary says why there are no measures
        g = np.asarray(scene.gravity, dtype=np.float64)
        up = -g if np.linalg.norm(g) > 0.0 else np.array([0.0, 0.0, 1.0])
        try:
            grains = measures.Grains.from_scene(scene, sim.state())
            box = measures.Box(measured["box"]["lower"], measured["box"]["upper"])
            plots = write_measure_plots(grains, sim.contacts(), box, measured, self.out_dir, up=up)
        except OSError as exc:
            self.errors.append(f"cannot write the measure plots: {why(exc)}")
            return None
        except Exception as exc:  # matplotlib or a measure: the plots are an extra, the run is fine
            return f"no measure plots: {type(exc).__name__}: {exc}"
        if isinstance(plots, str):
            return plots
        self.plot_files += [relative(p, self.out_dir) for p in plots]
        return None

    def write_summary(self, summary: dict) -> None:
        self.summary_written = False
        if self.summary_path is None:
            return
        tmp = self.summary_path.with_name(self.summary_path.name + ".tmp")
        try:
            self.summary_path.parent.mkdir(parents=True, exist_ok=True)
            tmp.write_text(json.dumps(finite(summary), indent=1) + "\n")
            os.replace(tmp, self.summary_path)
            self.summary_written = True
        except OSError as exc:
            self.errors.append(f"cannot write the summary {self.rel(self.summary_path)}: {why(exc)}")
            remove(tmp)
