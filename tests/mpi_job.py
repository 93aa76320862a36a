"""A decomposed run for tests/test_distributed.py, launched by mpiexec: steps a test scene on every rank
and writes the whole state and contacts (gathered on rank 0) to an npz file.

    mpiexec -n 2 python tests/mpi_job.py SCENE STEPS MARGIN DEVICE OUT [CHUNK [OVERLAP [EXCHANGE]]]

OVERLAP 0 exchanges the ghosts after each whole step (DistributedSimulation(overlap=False)). DEVICE "cuda": a GPU
per rank (``device_for_rank``). EXCHANGE "host" (default) or "nccl".
"""

import sys

import numpy as np
import warp as wp

wp.config.quiet = True

from distributed_scenes import build  # noqa: E402

from polydem.distributed import DistributedSimulation, world  # noqa: E402
from polydem.distributed.root import device_for_rank  # noqa: E402


def main():
    name, steps, margin, device, out = sys.argv[1], int(sys.argv[2]), float(sys.argv[3]), sys.argv[4], sys.argv[5]
    chunk = int(sys.argv[6]) if len(sys.argv) > 6 else 50
    overlap = bool(int(sys.argv[7])) if len(sys.argv) > 7 else True
    exchange = sys.argv[8] if len(sys.argv) > 8 else "host"
    comm = world()
    if device == "cuda":
        device = device_for_rank(device, comm)
    ds = DistributedSimulation(build(name), device=device, comm=comm, margin=margin, chunk=chunk, overlap=overlap,
                               exchange=exchange)  # fmt: skip
    splits = []
    for _ in range(0, steps, 500):  # whether the ranks' steps were split, after every partition
        ds.step(min(500, steps - ds.steps_done))
        splits.append(ds.split)
    splits = comm.gather(splits, root=0)
    state, contacts, energy = ds.state(), ds.contacts(), ds.energy()
    owned, local = ds.balance()
    # Every rank's damping loads, ghosts included (a ghost's comes from its owner): by global index.
    mine = (np.zeros(0, np.int64), np.zeros(0, np.float32))
    if ds.sim is not None:
        mine = (ds.local_index, ds.sim.current_state.body_damping.numpy())
    loads = comm.gather(mine, root=0)
    if comm.Get_rank() == 0:
        arrays = {f"state_{k}": v for k, v in state.items()}
        arrays.update({f"contacts_{k}": v for k, v in contacts.items()})
        arrays.update({f"energy_{k}": np.float64(v) for k, v in energy.items()})
        arrays["split"] = np.array(splits, dtype=bool)
        arrays.update(partitions=ds.partitions, owned=owned, local=local, steps_done=ds.steps_done, redone=ds.redone)
        arrays["damping_index"] = np.concatenate([i for i, _ in loads])
        arrays["damping"] = np.concatenate([d for _, d in loads])
        np.savez(out, **arrays)


if __name__ == "__main__":
    main()
