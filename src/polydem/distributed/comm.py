"""The communicator: MPI through mpi4py when the run was launched by ``mpiexec``, else one rank alone.

mpi4py is an optional dependency (``pip install 'polydem[mpi]'`` installs it with the MPICH wheel);
it is imported only here, and only when the environment says an MPI launcher started the process.
"""

from __future__ import annotations

import os
from collections.abc import Sequence
from typing import TYPE_CHECKING, Any, NoReturn, TypeAlias, TypeVar

if TYPE_CHECKING:
    from mpi4py import MPI

T = TypeVar("T")

# What MPICH (PMI), Open MPI, Intel MPI, Slurm's srun and Cray set for each rank they start.
_SIZE_VARIABLES = ("PMI_SIZE", "OMPI_COMM_WORLD_SIZE", "MPI_LOCALNRANKS", "PMIX_SIZE", "SLURM_NTASKS", "ALPS_APP_PE")


def launched_size() -> int:
    """The number of ranks an MPI launcher started, from its environment variables (1 when none)."""
    for name in _SIZE_VARIABLES:
        value = os.environ.get(name)
        if value and value.isdigit() and name != "ALPS_APP_PE":
            return int(value)
    return 1


# ... and this rank's number among them.
_RANK_VARIABLES = ("PMI_RANK", "OMPI_COMM_WORLD_RANK", "PMIX_RANK", "SLURM_PROCID", "ALPS_APP_PE")


def launched_rank() -> int:
    """This process's rank as an MPI launcher numbered it, from its environment variables (0 when none).

    Known before MPI starts: an error that every rank finds alike before then (a bad option, no mpi4py)
    is printed by rank 0 alone, the others exiting with the same code."""
    if launched_size() <= 1:
        return 0
    for name in _RANK_VARIABLES:
        value = os.environ.get(name)
        if value and value.isdigit():
            return int(value)
    return 0


class SerialComm:
    """A communicator of one rank with mpi4py's lower-case methods: a run that was not launched by MPI."""

    rank = 0
    size = 1

    def Get_rank(self) -> int:
        return 0

    def Get_size(self) -> int:
        return 1

    def bcast(self, obj: T, root: int = 0) -> T:
        return obj

    def gather(self, obj: T, root: int = 0) -> list[T]:
        return [obj]

    def allgather(self, obj: T) -> list[T]:
        return [obj]

    def alltoall(self, objs: Sequence[T]) -> list[T]:
        return list(objs)

    def allreduce(self, obj: T, op: Any = None) -> T:
        return obj

    def Barrier(self) -> None:
        pass

    def Abort(self, code: int = 1) -> NoReturn:
        raise SystemExit(code)


if TYPE_CHECKING:
    Comm: TypeAlias = SerialComm | MPI.Intracomm
    """What the distributed classes take as a communicator: mpi4py's, or one rank alone."""


def world() -> Comm:
    """``MPI.COMM_WORLD`` when launched by an MPI launcher with more than one rank, else a :class:`SerialComm`.

    Raises:
        RuntimeError: launched by ``mpiexec`` with several ranks but mpi4py is not installed (each rank
            would otherwise run the whole scene on its own).
    """
    if launched_size() <= 1:
        return SerialComm()
    try:
        from mpi4py import MPI
    except ImportError as exc:
        raise RuntimeError(
            f"this process was started by an MPI launcher with {launched_size()} ranks, but mpi4py is not "
            "installed: pip install 'polydem[mpi]' (mpi4py and the MPICH library), or run without mpiexec"
        ) from exc
    return MPI.COMM_WORLD


def op(name: str) -> MPI.Op | None:
    """mpi4py's reduction ``name`` ("max", "min", "sum"), or None for a :class:`SerialComm`."""
    try:
        from mpi4py import MPI
    except ImportError:
        return None
    return {"max": MPI.MAX, "min": MPI.MIN, "sum": MPI.SUM}[name]
