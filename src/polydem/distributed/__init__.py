"""Runs over several processes and GPUs: spatial domain decomposition with MPI (mpi4py).

:class:`DistributedSimulation` steps one scene over the ranks of an MPI communicator, each rank
owning the bodies of a slab of space and holding ghost copies of its neighbours' bodies within the
interaction range (:mod:`polydem.distributed.simulation` says how, and why the result is the
undivided run's). ``mpiexec -n 4 polydem run scene.toml`` runs a scene so; in Python, construct a
DistributedSimulation on every rank with the same scene.
"""

from polydem.distributed.comm import launched_rank, launched_size, world
from polydem.distributed.simulation import DistributedError, DistributedSimulation

__all__ = ["DistributedError", "DistributedSimulation", "launched_rank", "launched_size", "world"]
