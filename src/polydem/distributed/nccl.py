"""Ghost rows from GPU to GPU with NCCL, enqueued on the GPU's streams (``DistributedSimulation(exchange="nccl")``).

With the host's exchange ("host") each step's rows go to pinned memory, over MPI and back, and the
host waits for them before it may launch the next step: one round trip of the host per step, which a small
rank's step cannot hide. NCCL's sends and receives are stream operations: the rows go from one GPU's memory to
the other's (NVLink or PCIe within a machine) in stream order, so that the host launches step after step without
waiting, and they are captured in the steps' CUDA graphs like any kernel.

nccl4py (NVIDIA's bindings; ``pip install 'polydem[nccl]'`` installs it with the NCCL of CUDA 13, or
``pip install 'nccl4py[cu12]'``) is imported only here: when the ranks of a run on GPUs ask for NCCL or leave the
choice to "auto" (the default: :func:`auto_exchange`). MPI still starts the ranks, broadcasts NCCL's id and carries
the chunks' agreements and the repartitions.
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Any

import warp as wp

if TYPE_CHECKING:
    from polydem.distributed.comm import Comm


def load_nccl() -> Any:
    """nccl4py's ``nccl.core``, or a RuntimeError that says how to install it."""
    try:
        import nccl.core as nccl
    except ImportError as exc:
        raise RuntimeError(
            "exchange='nccl' needs nccl4py (NVIDIA's NCCL bindings): pip install 'polydem[nccl]' (NCCL for CUDA 13) "
            "or pip install 'nccl4py[cu12]' (CUDA 12); or use exchange='host', the exchange through host memory"
        ) from exc
    return nccl


def nccl_place(device: wp.Device) -> tuple[bool, str | None]:
    """(whether NCCL can run on this rank: a GPU and nccl4py installed, the GPU's UUID): what each rank tells the
    others when the exchange is left to choose (:func:`auto_exchange`)."""
    if not device.is_cuda:
        return False, None
    try:
        load_nccl()
    except RuntimeError:
        return False, device.uuid
    return True, device.uuid


def auto_exchange(places: list[tuple[bool, str | None]]) -> str:
    """The exchange a decomposed run takes when left to choose, from every rank's :func:`nccl_place`: "nccl" where
    there are several ranks, NCCL can run on each and each has a GPU of its own (NCCL takes one per rank), else
    "host"."""
    gpus = [uuid for ok, uuid in places if ok]
    if len(places) > 1 and len(gpus) == len(places) and len(set(gpus)) == len(gpus):
        return "nccl"
    return "host"


class NcclExchange:
    """One NCCL communicator over the ranks of ``comm``, each on its own GPU ``device`` (collective to make).

    It lives as long as the process: ``ncclCommDestroy`` is collective and waits for the graphs that captured its
    operations (on one H200 it did not return), and the process's exit frees it.

    Raises:
        ValueError: ``device`` is not a CUDA device.
        RuntimeError: nccl4py is missing, or NCCL could not make the communicator (two ranks on one GPU, say:
            NCCL needs a GPU per rank).
    """

    def __init__(self, comm: Comm, device: wp.Device) -> None:
        if not device.is_cuda:
            raise ValueError(f"exchange='nccl' moves the ghost rows between GPUs: the rank's device is {device}")
        rank, size = int(comm.Get_rank()), int(comm.Get_size())
        # Each collective step only once every rank is known to get there: a rank that raised alone would leave
        # the others waiting in the broadcast or in NCCL's own set-up.
        nccl = uid = None
        try:
            nccl = load_nccl()
            uid = nccl.get_unique_id() if rank == 0 else None
            failure = ""
        except Exception as exc:
            failure = f"rank {rank}: {exc}"
        failures = [m for m in comm.allgather(failure) if m]
        if failures:
            raise RuntimeError("; ".join(failures))
        self._nccl = nccl
        uid = comm.bcast(uid, root=0)
        try:
            from cuda.core import Device

            # NCCL takes the current device of the CUDA runtime: this rank's GPU, as Warp's context is.
            with wp.ScopedDevice(device):
                Device(device.ordinal).set_current()
                self.comm = nccl.Communicator.init(size, rank, uid)
        except Exception as exc:
            raise RuntimeError(
                f"rank {rank}: NCCL could not make its communicator on {device} ({type(exc).__name__}: {exc}); "
                "NCCL needs one GPU per rank (mpiexec -n N with N GPUs): else use exchange='host'"
            ) from exc

    def post(self, send: dict[int, wp.array], recv: dict[int, wp.array], stream: wp.Stream) -> None:
        """Enqueue on ``stream`` the sends of the rows ``send[peer]`` and the receipt of ``recv[peer]``, as one
        group (each rank posts all of its step's messages; NCCL pairs them with the peers', in any order)."""
        handle = stream.cuda_stream
        with self._nccl.group():
            for peer, rows in send.items():
                self.comm.send(rows, peer, stream=handle)
            for peer, rows in recv.items():
                self.comm.recv(rows, peer, stream=handle)
