"""``mpiexec -n R polydem run``: rank 0 drives the command's usual loop, the other ranks follow.

Rank 0 runs ``polydem run`` as in a run of one process, on a :class:`RootSimulation`: an object with
the methods of :class:`~polydem.Simulation` that the command uses, each of which first tells the
other ranks what to do (a broadcast of the method's name and arguments) and then does it with them
(the collective methods of :class:`~polydem.distributed.DistributedSimulation`). The other ranks
wait in :func:`serve` for those messages until rank 0 says stop. Only rank 0 writes files (USD, VTK,
pictures, checkpoints, the summary); what it writes is the whole scene's, in global body order, in
the formats of a run of one process, so a checkpoint of a decomposed run resumes on any number of
ranks, one included.
"""

from __future__ import annotations

from collections.abc import Callable, Iterable
from typing import TYPE_CHECKING, Any

from polydem.distributed.simulation import DistributedError, DistributedSimulation
from polydem.model import Model

if TYPE_CHECKING:
    import numpy as np
    import warp as wp

    from polydem.distributed.comm import Comm
    from polydem.scene import Scene

_STOP = "stop"


class _Gathered:
    """A host array standing in for a device array of vectors or scalars: ``numpy()``, and ``shape``
    without the vector's length, as Warp gives it."""

    def __init__(self, a: np.ndarray, vector: bool) -> None:
        self._a = a
        self.shape = a.shape[:-1] if vector else a.shape

    def numpy(self) -> np.ndarray:
        return self._a


class GatheredState:
    """The whole scene's state gathered on rank 0, read as a :class:`~polydem.state.State` is by the
    command's outputs (``numpy(fields)``, ``mesh_q``, and the shapes of ``wall_xi`` and ``wall_turn``)."""

    def __init__(self, arrays: dict[str, np.ndarray]) -> None:
        self._arrays = arrays
        for k, v in arrays.items():
            setattr(self, k, _Gathered(v, k in ("body_q", "body_v", "body_w", "wall_xi", "mesh_q")))

    def numpy(self, fields: Iterable[str]) -> dict[str, np.ndarray]:
        return {k: self._arrays[k] for k in fields}


class GatheredContacts:
    """The whole scene's pair history gathered on rank 0 (global keys), for checkpoints."""

    def __init__(self, arrays: dict[str, np.ndarray]) -> None:
        self._arrays = arrays

    def history_numpy(self) -> dict[str, np.ndarray]:
        return {k: self._arrays[k] for k in ("pair_key", "pair_xi", "pair_turn")}


class RootSimulation:
    """Rank 0's view of a decomposed run, with the interface of :class:`~polydem.Simulation` that
    ``polydem run`` uses (:class:`~polydem.fronts.RunFront`). Every method that touches the state runs on
    all ranks (see the module)."""

    scene: Scene
    device: wp.Device
    num_bodies: int
    dt: float
    model: Model

    def __init__(self, ds: DistributedSimulation, on_error: Callable[[Exception], object] | None = None) -> None:
        if ds.rank != ds.root:
            raise ValueError("RootSimulation runs on the root rank; the others call serve()")
        self.ds = ds
        self.dt = ds.dt
        self.device = ds.device
        self.num_bodies = ds.num_bodies
        self.scene = ds.scene
        # The whole scene's static arrays, for what the outputs read of a model (shapes, walls, flags).
        self.model = Model(ds.scene, ds.device, validate=False, settings=ds.settings)
        self._consistent = True
        self._cache: tuple[int, dict[str, np.ndarray]] | None = None
        # What to do when a collective method fails on the root alone (the others would wait inside it).
        self._on_error = on_error

    @property
    def steps_done(self) -> int:
        return self.ds.steps_done

    @property
    def time(self) -> float:
        return self.ds.time

    def _call(self, name: str, *args: Any) -> Any:
        self.ds.comm.bcast((name, args), root=self.ds.root)
        try:
            return getattr(self.ds, name)(*args)
        except DistributedError:
            raise  # raised on every rank: the ranks are still in step
        except Exception as exc:
            if self._on_error is None:
                raise
            self._on_error(exc)

    def _saved(self) -> dict[str, np.ndarray]:
        if self._cache is None or self._cache[0] != self.ds.steps_done:
            self._cache = (self.ds.steps_done, self._call("saved_arrays"))
        return self._cache[1]

    def step(self, n: int = 1) -> None:
        self._cache = None
        try:
            self._call("step", int(n))
        except DistributedError:
            self._consistent = False
            raise

    def state(self) -> dict[str, np.ndarray]:
        return self._call("state")

    def contacts(self) -> dict[str, np.ndarray]:
        return self._call("contacts")

    def energy(self) -> dict[str, float]:
        return self._call("energy")

    def settle_measures(self) -> tuple[float, float, float]:
        return self._call("settle_measures")

    # DistributedSimulation keeps no contact-force average (a partition builds new local simulations,
    # which would drop one): none ever runs, and the VTK frames of a decomposed run have no averaged fields.
    @property
    def contact_average_steps(self) -> int | None:
        """None: no contact-force average is running."""
        return None

    def start_contact_average(self) -> None:
        """Nothing: a decomposed run keeps no contact-force average (:attr:`contact_average_steps` stays None)."""

    def contact_average(self) -> dict[str, Any]:
        raise RuntimeError("a decomposed run keeps no contact-force average")

    @property
    def current_state(self) -> GatheredState:
        return GatheredState(self._saved())

    @property
    def current_contacts(self) -> GatheredContacts:
        return GatheredContacts(self._saved())

    def restore_from_arrays(self, arrays: dict[str, np.ndarray], steps_done: int, time: float) -> None:
        self._cache = None
        self._consistent = True
        self._call("restore_global", arrays, steps_done, time)

    def restore_last_good(self) -> bool:
        """Whether the state is that of a completed step (a decomposed run keeps no copy to go back to:
        after a failed step the state is not consistent)."""
        return self._consistent

    def balance(self) -> tuple[np.ndarray, np.ndarray]:
        return self._call("balance")

    def stop(self, code: int = 0) -> None:
        """Release the other ranks from :func:`serve`, which returns ``code`` (the command's exit code)."""
        self.ds.comm.bcast((_STOP, (int(code),)), root=self.ds.root)


def serve(ds: DistributedSimulation) -> int:
    """The loop of the ranks other than the root: do what the root asks until it says stop; returns the exit
    code the root gave with it, so that every rank ends the command alike."""
    while True:
        name, args = ds.comm.bcast(None, root=ds.root)
        if name == _STOP:
            return int(args[0]) if args else 0
        try:
            getattr(ds, name)(*args)
        except DistributedError:
            continue  # the root raised it too and decides what follows


def device_for_rank(device: str | wp.Device | None, comm: Comm) -> str | wp.Device | None:
    """This rank's device: a CUDA device name is taken modulo the GPUs of the node by the rank's place on
    it (one GPU per rank where there are as many), anything else as given."""
    import warp as wp

    count = wp.get_cuda_device_count()
    if device is None and count:
        device = "cuda:0"
    if device is None or not str(device).startswith("cuda") or comm.Get_size() == 1:
        return device
    if count == 0:
        return device
    try:
        from mpi4py import MPI

        local = comm.Split_type(MPI.COMM_TYPE_SHARED).Get_rank()
    except Exception:
        local = comm.Get_rank()
    return f"cuda:{local % count}"


__all__ = ["GatheredState", "RootSimulation", "device_for_rank", "serve"]
