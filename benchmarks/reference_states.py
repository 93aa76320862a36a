"""Final states of a few CPU runs, as SHA-256 digests, to prove that a refactoring changes no result.

    python benchmarks/reference_states.py --save   # before a change: benchmarks/results/reference_states.json
    python benchmarks/reference_states.py          # after it: the same cases, compared bit for bit

The cases cover the paths a redesign touches: the built-in default scene (mixed shapes, friction,
box container), the drum (kinematic walls turning about a pivot), the cube drop on a plane wall,
and a run that is checkpointed, reloaded into a fresh simulation and continued (it must equal the
unbroken run). Each digest is over the raw bytes of a state array, so any difference in any bit
shows; the table prints the largest absolute difference of the positions where digests differ.
"""

from __future__ import annotations

import argparse
import hashlib
import json
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve().parent
ROOT = HERE.parent
RESULTS = HERE / "results" / "reference_states.json"


def _cases():
    import polydem
    from polydem.default_scene import default_scene

    def drum():
        return polydem.Scene.from_toml(ROOT / "scenes" / "drum.toml")

    def cube_drop():
        return polydem.Scene.from_toml(ROOT / "scenes" / "cube_drop.toml")

    def heap():
        return polydem.Scene.from_toml(ROOT / "scenes" / "heap.toml")

    def hopper():
        return polydem.Scene.from_toml(ROOT / "scenes" / "hopper.toml")

    # (name, scene factory, steps, steps at which the resumed copy is checkpointed or None). "heap" has
    # compound grains and a mesh funnel, "hopper" a mesh wall; "default_decomposed" runs the default scene
    # through the decomposed front (one rank) and must equal "default".
    return [
        ("default", default_scene, 6000, None),
        ("drum", drum, 2000, None),
        ("cube_drop", cube_drop, 20000, None),
        ("default_resumed", default_scene, 6000, 3500),
        ("heap", heap, 1500, None),
        ("hopper", hopper, 1500, None),
        ("default_decomposed", default_scene, 6000, "decomposed"),
    ]


def _digest(a: np.ndarray) -> str:
    return hashlib.sha256(np.ascontiguousarray(a).tobytes()).hexdigest()


def _run(factory, steps: int, resume_at: int | None) -> dict[str, np.ndarray]:
    from polydem import Simulation
    from polydem.checkpoint import load_checkpoint, save_checkpoint

    if resume_at == "decomposed":
        from polydem.distributed import DistributedSimulation
        from polydem.distributed.comm import SerialComm

        sim = DistributedSimulation(factory(), device="cpu", comm=SerialComm())
        sim.step(steps)
        return {k: np.asarray(v) for k, v in sim.state().items()}
    sim = Simulation(factory(), device="cpu")
    if resume_at is None:
        sim.step(steps)
    else:
        sim.step(resume_at)
        with tempfile.TemporaryDirectory() as tmp:
            path = Path(tmp) / "at.npz"
            save_checkpoint(sim, path)
            sim = Simulation(factory(), device="cpu")
            load_checkpoint(sim, path)
        sim.step(steps - resume_at)
    state = {k: np.asarray(v) for k, v in sim.state().items()}
    contacts = sim.contacts()
    state["contact_volume"] = np.asarray(contacts["volume"])
    return state


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--save", action="store_true", help="record the digests (before a change)")
    parser.add_argument("--only", nargs="*", help="run only these cases")
    args = parser.parse_args()

    import warp as wp

    wp.config.quiet = True
    stored = json.loads(RESULTS.read_text()) if RESULTS.is_file() else {}
    if not args.save and not stored:
        print(f"no reference digests in {RESULTS}: run with --save first", file=sys.stderr)
        return 2
    results = {}
    same = True
    print(f"{'case':<18} {'steps':>6} {'wall s':>7}  result")
    for name, factory, steps, resume_at in _cases():
        if args.only and name not in args.only:
            continue
        t0 = time.perf_counter()
        state = _run(factory, steps, resume_at)
        wall = time.perf_counter() - t0
        digests = {k: _digest(v) for k, v in sorted(state.items())}
        entry = {"steps": steps, "resume_at": resume_at, "digests": digests}
        entry["positions"] = np.asarray(state["body_position"], dtype=np.float64).tolist()
        results[name] = entry
        if args.save:
            verdict = "saved"
        else:
            ref = stored.get(name)
            if ref is None:
                verdict = "no reference"
                same = False
            else:
                differ = [k for k in ref["digests"] if ref["digests"][k] != digests.get(k)]
                if differ:
                    same = False
                    dx = np.abs(np.asarray(ref["positions"]) - np.asarray(entry["positions"])).max()
                    verdict = f"DIFFERENT ({', '.join(differ)}; largest position difference {dx:.3g} m)"
                else:
                    verdict = "bit for bit the same"
        print(f"{name:<18} {steps:>6} {wall:>7.1f}  {verdict}", flush=True)
    for twin in ("default_resumed", "default_decomposed"):
        if "default" in results and twin in results:
            a, b = results["default"]["digests"], results[twin]["digests"]
            if any(a[k] != b[k] for k in b):
                print(f"{twin} differs from the unbroken run")
                same = False
    if args.save:
        RESULTS.parent.mkdir(parents=True, exist_ok=True)
        RESULTS.write_text(json.dumps({**stored, **results}) + "\n")
        print(f"wrote {RESULTS}")
    return 0 if same else 1


if __name__ == "__main__":
    sys.exit(main())
