"""Checkpoints: save a running Simulation to a file and continue from it later.

A checkpoint holds everything the dynamics depend on: poses, velocities, the turning volumes of
the normal hysteresis and the friction springs of the persisting contacts (with the keys that
identify their pairs), those of the wall contacts, the energy
dissipated so far, the step count and the time. Resuming gives the same result, bit for bit on
the same device, as a run that was never interrupted: the candidate pairs are found again, and
pairs out of contact contribute exact zeros.
"""

import os

import numpy as np
import warp as wp

FORMAT = "polydem-checkpoint-2"


def save_checkpoint(sim, path):
    """Write the state of ``sim`` to ``path`` (a ``.npz`` file), atomically."""
    path = os.fspath(path)
    if not path.endswith(".npz"):
        raise ValueError(f"checkpoint path must end with .npz, got {path!r}")
    bp = sim.broadphase
    count = int(bp.pair_count.numpy()[0])
    data = {
        "format": np.array(FORMAT),
        "num_bodies": np.array(sim.num_bodies),
        "steps_done": np.array(sim.steps_done),
        "time": np.array(sim.time),
        "dt": np.array(sim.dt),
        "body_q": sim.body_q.numpy(),
        "body_v": sim.body_v.numpy(),
        "body_w": sim.body_w.numpy(),
        "body_dissipated": sim.body_dissipated.numpy(),
        "plane_xi": sim.plane_xi.numpy(),
        "plane_turn": sim.plane_turn.numpy(),
        "step_count": sim.step_count.numpy(),
        "pair_key": bp.pair_key.numpy()[:count],
        "pair_xi": sim.pair_xi.numpy()[:count] if sim.model.friction else np.zeros((0, 3), np.float32),
        "pair_turn": sim.pair_turn.numpy()[:count],
    }
    tmp = path + ".tmp.npz"
    np.savez(tmp, **data)
    os.replace(tmp, path)


def load_checkpoint(sim, path):
    """Put the state saved in ``path`` into ``sim``, which must be built from the same scene."""
    path = os.fspath(path)
    if not os.path.exists(path):
        raise FileNotFoundError(f"checkpoint {path!r} does not exist")
    try:
        data = np.load(path)
        fmt = str(data["format"])
    except Exception as err:  # a truncated or foreign file
        raise ValueError(f"{path}: not a polydem checkpoint ({err})") from err
    if fmt != FORMAT:
        raise ValueError(f"{path}: checkpoint format {fmt!r}, this polydem reads {FORMAT!r}")
    n = int(data["num_bodies"])
    if n != sim.num_bodies:
        raise ValueError(f"{path}: checkpoint has {n} bodies but the scene has {sim.num_bodies}; use the same scene")
    if not np.isclose(float(data["dt"]), sim.dt, rtol=1e-12):
        raise ValueError(
            f"{path}: checkpoint time step {float(data['dt']):.6g} s differs from the scene's {sim.dt:.6g} s"
        )
    dev = sim.device
    count = len(data["pair_key"])
    cap = max(count, 1)
    key = np.zeros(cap, dtype=np.int64)
    key[:count] = data["pair_key"]
    xi = np.zeros((cap, 3), dtype=np.float32)
    if sim.model.friction and len(data["pair_xi"]):
        xi[:count] = data["pair_xi"]
    turn = np.zeros(cap, dtype=np.float32)
    turn[:count] = data["pair_turn"]
    plane_xi = data["plane_xi"]
    plane_turn = data["plane_turn"]
    if plane_xi.shape[:2] != tuple(sim.plane_xi.shape) or plane_turn.shape != tuple(sim.plane_turn.shape):
        raise ValueError(f"{path}: wall contacts of shape {plane_turn.shape} do not fit this scene's walls")
    sim._saved = {
        "q": wp.array(data["body_q"], dtype=wp.transform, device=dev),
        "v": wp.array(data["body_v"], dtype=wp.vec3, device=dev),
        "w": wp.array(data["body_w"], dtype=wp.vec3, device=dev),
        "diss": wp.array(data["body_dissipated"], dtype=float, device=dev),
        "plane_xi": wp.array(plane_xi, dtype=wp.vec3, device=dev),
        "plane_turn": wp.array(plane_turn, dtype=float, device=dev),
        "xi": wp.array(xi, dtype=wp.vec3, device=dev),
        "turn": wp.array(turn, dtype=float, device=dev),
        "key": wp.array(key, dtype=wp.int64, device=dev),
        "count": wp.array(np.array([count], dtype=np.int32), dtype=int, device=dev),
        "step": wp.array(data["step_count"], dtype=int, device=dev),
    }
    sim._restore()
    sim.steps_done = int(data["steps_done"])
    sim.time = float(data["time"])
    return sim
