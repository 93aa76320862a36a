"""The end of a run: the summary (``summary.json``) and the closing lines on stdout."""

from __future__ import annotations

import os
import shlex

import numpy as np

from polydem.cli.common import listing, plural, relative, shorten
from polydem.cli.diagnostics import relative_depths, relative_overlaps, settled_region
from polydem.cli.errors import EXIT_INTERRUPTED, EXIT_TERMINATED
from polydem.cli.outputs import scene_metadata
from polydem.scene.bodies import BodyKind

__all__ = ["Report"]


class Report:
    """The summary and the closing lines of a run of ``sim`` (``args``: the command line), from
    its ``log``, ``outputs`` and ``schedule``; ``pictures``: the scene's pictures setting."""

    def __init__(self, args, scene, sim, *, log, outputs, schedule, pictures, energy_at_start):
        self.args = args
        self.scene = scene
        self.sim = sim
        self.log = log
        self.outputs = outputs
        self.schedule = schedule
        self.pictures = pictures
        self.energy_at_start = energy_at_start

    def _largest(self, contacts, relative, key) -> dict | None:
        # The contact with the largest ``relative`` measure (overlap or depth), with its ``key`` value.
        rel = relative(contacts, self.log.volumes) if contacts is not None else np.zeros(0)
        if not len(rel):
            return None
        i = int(np.argmax(rel))
        b = int(contacts["body_b"][i])
        return {
            "relative": float(rel[i]),
            key: float(contacts[key][i]),
            "body_a": int(contacts["body_a"][i]),
            "body_b": b if b >= 0 else None,
            "wall": -1 - b if b < 0 else None,
        }

    def _files(self) -> dict:
        """The ``outputs`` entry of the summary: the files of the whole run, relative to the folder."""
        o = self.outputs
        e = self.log.earlier or {}
        folder = o.out_dir
        return {
            "folder": str(folder),
            "usd": relative(o.usd_path, folder) if o.usd_path is not None and not o.usd_failed else None,
            "usd_frames": o.usd.frames if o.usd is not None and not o.usd_failed else 0,
            "vtk": {
                "files": [relative(p, folder) for p in o.vtk.files],
                "frames": o.vtk.frames,
            }
            if o.vtk is not None
            else None,
            "pictures": [*(relative(p, folder) for p in e.get("pictures", [])), *o.picture_files],
            "checkpoints": list(
                dict.fromkeys([*(relative(p, folder) for p in e.get("checkpoints", [])), *o.checkpoints])
            ),
            "summary": relative(o.summary_path, folder) if o.summary_path is not None else None,
        }

    def _notes(self, notes: list[str]) -> list[str]:
        if isinstance(self.pictures, tuple):
            missing = [k for k in self.pictures if k >= self.schedule.frame]
            if missing:
                notes.append(f"picture frames {missing} were not reached by this run")
        if self.outputs.resumed_from is not None and self.log.earlier is None:
            notes.append(
                f"the checkpoint holds no record of the run before step {self.outputs.start}: the history, contact "
                "counts, initial energy, wall time and files cover the resumed part only"
            )
        return notes

    def summary(self, wall, reason, notes, consistent) -> dict:
        from polydem import __version__

        sim, scene, log, o = self.sim, self.scene, self.log, self.outputs
        kind = np.asarray(scene.body_kind)
        start, resumed_from = o.start, o.resumed_from
        run_steps = sim.steps_done - start
        energy = sim.energy() if consistent else None
        contacts = sim.contacts() if consistent else None
        frames = log.frame_contacts
        e = log.earlier or {}
        parts = [dict(p) for p in [*e.get("parts", []), o.part(sim.steps_done, wall)]]
        for p in parts:
            for k in ("usd", "resumed_from"):
                if p.get(k) is not None:
                    p[k] = relative(p[k], o.out_dir)
        region = self._region(scene, sim, contacts) if consistent else None
        summary = {
            "polydem": __version__,
            "scene": scene.name,
            "scene_file": scene_metadata(self.args.scene).get("scene_file"),
            "default_scene": self.args.scene is None,
            "device": str(sim.device),
            "precision": scene.precision,
            "interrupted": reason is not None,
            "reason": reason,
            "resumed_from": str(resumed_from) if resumed_from is not None else None,
            "resumed_at_step": start if resumed_from is not None else None,
            "history_from_step": parts[0]["from_step"],
            "parts": parts,
            "steps": sim.steps_done,
            "steps_this_run": run_steps,
            "target_steps": self.schedule.target,
            "dt": sim.dt,
            "simulated_time": sim.time,
            "wall_time": e.get("wall_time", 0.0) + wall,
            "wall_time_this_run": wall,
            "steps_per_second": run_steps / wall if wall > 0 else None,
            "body_steps_per_second": run_steps * sim.num_bodies / wall if wall > 0 else None,
            "bodies": {"total": int(sim.num_bodies), **{k.label: int(np.sum(kind == k)) for k in BodyKind}},
            "fps": self.schedule.fps,
            "frames": len(frames),
            "contacts": {
                "final": len(contacts["volume"]) if contacts is not None else None,
                "mean": float(np.mean(frames)) if frames else None,
                "max": int(np.max(frames)) if frames else None,
            },
            "largest_overlap": {
                "final": self._largest(contacts, relative_overlaps, "volume"),
                "max_over_frames": log.frame_overlap if frames else None,
            },
            "largest_depth": {
                "final": self._largest(contacts, relative_depths, "depth"),
                "max_over_frames": log.frame_depth if frames else None,
            },
            "energy": {
                "initial": log.energy_initial,
                "at_resume": self.energy_at_start if resumed_from is not None else None,
                "final": energy,
            },
            "settled_region": region,
            "measures": self._measures(scene, sim, region, contacts) if consistent else None,
            "contact_average": o.average_summary(sim) if consistent else None,
            "outputs": self._files(),
        }
        notes = self._notes(notes)
        if notes:
            summary["notes"] = notes
        motions = self._motions(sim) if consistent else None
        if motions:
            summary["motions"] = motions
        return summary

    @staticmethod
    def _motions(sim) -> dict | None:
        """The ramps' and servos' last step by name (kernels/motion.py): displacement [m], velocity [m/s],
        the force the grains push back with [N] and that force over the area [Pa]; None without any."""
        model = sim.model
        travel = getattr(sim.current_state, "motion_travel", None)
        if not getattr(model, "has_measured_motions", False) or travel is None:
            return None
        rows = travel.numpy().astype(np.float64)
        out = {}
        for k, name in enumerate(model.motion_names):
            motion = sim.scene.motions[name]
            if motion.kind == "cycle":
                continue
            area = motion.area or float(model.motion_area[k])
            d, v, f = rows[k]
            out[name] = {"kind": motion.kind, "displacement": d, "velocity": v, "force": f,
                         "stress": f / area if area > 0.0 else None}  # fmt: skip
        return out

    def _region(self, scene, sim, contacts) -> dict:
        """:func:`settled_region` of the final state, with ``at_rest``: whether the free bodies are at rest by
        the default settle criterion (no hold; None where it cannot judge: no gravity, no energy released).
        A pile whose grains still fall has a region below its top, but nothing settled in it."""
        from polydem.settle import SettleCheck, SettleCriterion

        region = settled_region(scene, sim.state(), contacts)
        at_rest = None
        start = (self.log.energy_initial or {}).get("gravity")
        try:
            criterion = SettleCriterion()
            criterion.check_gravity(scene.gravity)
            kinetic, gravity, speed = sim.settle_measures()
            if start is not None and start - gravity > 0.0:
                check = SettleCheck(criterion, start, speed_limit=criterion.speed_limit_of(scene, sim.model.settings))
                at_rest = bool(check.holds(kinetic, gravity, speed))
        except ValueError:  # no gravity or no free bodies: nothing to judge
            pass
        region["at_rest"] = at_rest
        return region

    @staticmethod
    def _measures(scene, sim, region, contacts) -> dict:
        """:func:`polydem.measures.summary` in the settled region (exact packing fraction, contact types,
        coordination without rattlers, fabric, Love-Weber stress), or a ``note`` saying why there is none.
        A measure that fails leaves its reason here and the rest of the summary intact."""
        from polydem import measures

        box = measures.settled_box(scene, region)
        if box is None:
            why = (region or {}).get("note") or "gravity does not lie along a coordinate axis"
            return {"note": f"no settled region to measure: {why}"}
        try:
            grains = measures.Grains.from_scene(scene, sim.state())
            out = measures.summary(grains, box, contacts=contacts, device=sim.device)
        except (ValueError, RuntimeError, MemoryError) as exc:
            return {"note": f"the measures failed: {type(exc).__name__}: {exc}"}
        out["at_rest"] = region.get("at_rest")
        return out

    def closing_lines(self, s) -> list[str]:
        """The closing lines of the summary ``s``: what the run did and every file written."""
        frames = s["frames"]
        c = s["contacts"]
        lines = []
        if c["final"] is not None:
            over = ""
            if frames:
                over = f" (mean {c['mean']:.1f}, max {c['max']} over {plural(frames, 'frame')})"
            lines.append(f"  contacts: {c['final']}{over}")
        lo = s["largest_overlap"]
        parts = []
        if lo["final"] is not None:
            parts.append(f"{lo['final']['relative']:.3%} now")
        if lo["max_over_frames"] is not None:
            parts.append(f"{lo['max_over_frames']:.3%} at most in the frames")
        if parts:
            lines.append(f"  largest overlap (of the smaller body's volume): {', '.join(parts)}")
        ld = s["largest_depth"]
        parts = []
        if ld["final"] is not None:
            parts.append(f"{ld['final']['relative']:.3%} now ({ld['final']['depth']:.3g} m)")
        if ld["max_over_frames"] is not None:
            parts.append(f"{ld['max_over_frames']:.3%} at most in the frames")
        if parts:
            lines.append(f"  largest depth (of the smaller body's size, cube root of its volume): {', '.join(parts)}")
        region = s["settled_region"]
        if region is not None and region["packing_fraction"] is not None:
            head = "settled region" if region.get("at_rest") is not False else "region below the top, not at rest"
            lines.append(
                f"  {head} ({plural(region['bodies'], 'body', 'bodies')}): packing fraction "
                f"{region['packing_fraction']:.3f}, "
                f"coordination number {region['coordination_number']:.2f}"
            )
            m = s.get("measures") or {}
            coord = m.get("coordination") or {}
            if m.get("packing_fraction") is not None and coord.get("z") is not None:
                kinds = ", ".join(f"{k} {n}" for k, n in (m.get("contact_features") or {}).items() if n)
                lines.append(
                    f"  measured there: packing fraction {m['packing_fraction']:.3f} (grains clipped by the region), "
                    f"coordination {coord['z']:.2f} without the {coord['rattler_fraction']:.1%} rattlers (fewer than "
                    f"{coord['min_contacts']} contacts)" + (f"; contacts {kinds}" if kinds else "")
                )
        e = s["energy"]["final"]
        if e is not None:
            lines.append(
                f"  energy [J]: kinetic {e['kinetic']:.4g}, contact {e['contact']:.4g}, dissipated "
                f"{e['dissipated']:.4g}, total {e['total']:.6g} (at the start {s['energy']['initial']['total']:.6g})"
            )
        lines.append(f"  written to {self.outputs.out_dir}{os.sep}:")
        files = self.written(s)
        width = min(max((len(name) for name, _ in files), default=0), 40)
        lines += [f"    {name:<{width}}  {what}" for name, what in files] or ["    nothing"]
        earlier = self.earlier_files(s)
        if earlier is not None:
            lines.append(earlier)
        for note in s.get("notes", []):
            lines.append(f"  note: {note}")
        for error in self.outputs.errors:
            lines.append(f"  not written: {error}")
        return lines

    def report(self, out, err, s, cp_path, reason, status) -> None:
        """Print the closing lines of the summary ``s`` and, after a signal, how to resume."""
        head = "interrupted" if status in (EXIT_INTERRUPTED, EXIT_TERMINATED) else "stopped" if reason else "done"
        rate = f" ({s['steps_per_second']:.0f} steps/s)" if s["steps_per_second"] else ""
        first = (
            f"{head}: {s['steps_this_run']} steps to step {s['steps']} (t = {s['simulated_time']:.6g} s) in "
            f"{s['wall_time_this_run']:.2f} s{rate}, {plural(s['bodies']['total'], 'body', 'bodies')}"
        )
        settle = self.settle_line(s, reason)
        out.write("\n".join([first, *settle, *self.closing_lines(s)]) + "\n")
        out.flush()
        if reason is not None and cp_path is not None and status in (EXIT_INTERRUPTED, EXIT_TERMINATED):
            err.write(
                f"polydem: run interrupted at step {s['steps']}; continue with:\n  {self.resume_command(cp_path)}\n"
            )
            err.flush()

    @staticmethod
    def settle_line(s, reason) -> list[str]:
        """The line of a run until settled: when it settled, or that it did not."""
        st = s.get("settle")
        if st is None:
            return []
        frac = st["kinetic_fraction"]
        now = f"kinetic energy {frac:.3g} of the gravitational energy released" if frac is not None else ""
        if st["largest_speed"] is not None and st.get("speed_limit") is not None:
            speed = f"largest speed {st['largest_speed']:.3g} m/s (limit {st['speed_limit']:.3g})"
            now += (", " if now else "") + speed
        if st["settled"]:
            wall = f", {st['wall_s']:.2f} s wall" if st["wall_s"] is not None else ""
            return [f"  settled at t = {st['time_s']:.6g} s ({st['steps']} steps{wall}): {now}"]
        if reason is not None:
            return [f"  not settled when the run stopped (t = {s['simulated_time']:.6g} s): {now}"]
        return [
            f"  not settled within the maximum duration (t = {st['max_time_s']:.6g} s, {st['max_steps']} steps): "
            f"{now}; give a longer --duration"
        ]

    def written(self, s) -> list[tuple[str, str]]:
        """The files written (relative to the output folder) as (names, what) pairs, by kind."""
        o = s["outputs"]
        files = []
        if o["usd"]:
            files.append((shorten(o["usd"]), f"USD animation, {plural(o['usd_frames'], 'frame')}"))
        if o.get("vtk"):
            vtk = o["vtk"]
            names = ", ".join(shorten(f) for f in vtk["files"] if f.endswith(".pvd"))
            walls = " (and vtk/walls.vtu)" if any(f.endswith("walls.vtu") for f in vtk["files"]) else ""
            files.append((names, f"VTK series for ParaView, {plural(vtk['frames'], 'frame')}{walls}"))
        if o["summary"] and self.outputs.summary_written:
            files.append((shorten(o["summary"]), "summary"))
        # This run's files only: a resumed run's summary lists the earlier parts' too (earlier_files).
        pictures = list(self.outputs.picture_files)
        if pictures:
            last = pictures[-1] == "pictures/last.png"
            what = ("picture of the final state" if last else "picture") if len(pictures) == 1 else "pictures"
            files.append((listing(pictures, "pictures", 6), what))
        if self.outputs.plot_files:
            files.append((", ".join(self.outputs.plot_files), "plots"))
        checkpoints = list(dict.fromkeys(self.outputs.checkpoints))
        if checkpoints:
            what = "checkpoint" if len(checkpoints) == 1 else "checkpoints"
            files.append((listing(checkpoints, "checkpoints", 4), what))
        return files

    def earlier_files(self, s) -> str | None:
        """The line naming the files of the earlier parts of a resumed run (listed in its summary, not
        written by this run), or None."""
        o = s["outputs"]
        mine = set(self.outputs.picture_files) | set(self.outputs.checkpoints)
        pictures = [p for p in o["pictures"] if p not in mine]
        checkpoints = [p for p in o["checkpoints"] if p not in mine]
        if not (pictures or checkpoints):
            return None
        folders = sorted({os.path.dirname(os.path.dirname(p)) or "." for p in [*pictures, *checkpoints]})
        where = ", ".join("this folder" if f == "." else shorten(f) for f in folders)
        what = [plural(len(x), name) for x, name in ((checkpoints, "checkpoint"), (pictures, "picture")) if x]
        return f"  earlier parts of the run wrote {' and '.join(what)} (in {where}; listed in the summary)"

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
        if getattr(a, "until_settled", False):
            cmd.append("--until-settled")
        if getattr(a, "settle_kinetic", False) is not False:
            cmd += ["--settle-kinetic", "off" if a.settle_kinetic is None else repr(a.settle_kinetic)]
        if getattr(a, "settle_speed_fraction", False) is not False:
            f = a.settle_speed_fraction
            cmd += ["--settle-speed-fraction", "off" if f is None else repr(f)]
        for option, value in (
            ("--settle-speed", getattr(a, "settle_speed", None)),
            ("--settle-hold", getattr(a, "settle_hold", None)),
        ):
            if value is not None:
                cmd += [option, repr(value)]
        if a.vtk:
            cmd.append("--vtk")
        if a.out is not None:
            cmd += ["--out", str(a.out)]
        return shlex.join(cmd)
