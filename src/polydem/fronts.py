"""The fronts of a run: what ``polydem run`` and its recorders ask of a simulation.

Three classes step a scene: :class:`~polydem.Simulation` (one process),
:class:`~polydem.distributed.DistributedSimulation` (one rank of a decomposed run: its reading methods
are collective, with the whole scene's arrays on the root and None elsewhere) and
:class:`~polydem.distributed.root.RootSimulation` (rank 0's view of a decomposed run, which
``polydem run`` drives as it drives a Simulation). :class:`Front` is what the three share;
:class:`RunFront` adds what the command and its recorders (checkpoints, USD, VTK, pictures, the
summary) read besides, which Simulation and RootSimulation provide. ``tests/test_fronts.py`` checks that
each class has every member, with the parameters declared here.
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Any, Protocol, runtime_checkable

if TYPE_CHECKING:
    import numpy as np
    import warp as wp

    from polydem.contacts import Contacts
    from polydem.distributed.root import GatheredContacts, GatheredState
    from polydem.model import Model
    from polydem.scene import Scene
    from polydem.state import State

__all__ = ["Front", "RunFront"]


@runtime_checkable
class Front(Protocol):
    """What :class:`~polydem.Simulation`, :class:`~polydem.distributed.DistributedSimulation` and
    :class:`~polydem.distributed.root.RootSimulation` share.

    Its data members are read-only properties here (the command reads them; a class may keep them as plain
    attributes or properties).
    """

    @property
    def scene(self) -> Scene:
        """The whole scene."""
        ...

    @property
    def device(self) -> wp.Device:
        """The Warp device (of this rank, in a decomposed run)."""
        ...

    @property
    def num_bodies(self) -> int:
        """Bodies of the run (the whole scene's, in a decomposed run)."""
        ...

    @property
    def dt(self) -> float:
        """Time step [s]."""
        ...

    @property
    def steps_done(self) -> int:
        """Steps taken."""
        ...

    @property
    def time(self) -> float:
        """Simulated time [s]."""
        ...

    def step(self, n: int = 1) -> None:
        """Advance ``n`` steps."""
        ...

    def state(self) -> dict[str, np.ndarray] | None:
        """The bodies' positions, orientations and velocities (None on a rank other than the root)."""
        ...

    def contacts(self) -> dict[str, np.ndarray] | None:
        """The contacts of the last step and their forces (None on a rank other than the root)."""
        ...

    def energy(self) -> dict[str, float]:
        """Kinetic, contact, gravitational, dissipated and total energy [J]."""
        ...

    def settle_measures(self) -> tuple[float, float, float]:
        """Kinetic energy [J], gravitational energy [J] and largest speed [m/s] of the free bodies."""
        ...


@runtime_checkable
class RunFront(Front, Protocol):
    """What ``polydem run`` and its recorders use: :class:`Front` with the model, the arrays a checkpoint
    keeps, the going back after a failed step and the contact-force average of the VTK frames."""

    @property
    def model(self) -> Model:
        """The whole scene's :class:`~polydem.model.Model` (shapes, walls, flags)."""
        ...

    @property
    def current_state(self) -> State | GatheredState:
        """The state's device arrays (or their host copies, gathered on the root)."""
        ...

    @property
    def current_contacts(self) -> Contacts | GatheredContacts:
        """The pair list and its history (``history_numpy()``)."""
        ...

    def state(self) -> dict[str, np.ndarray]:
        """The bodies' positions, orientations and velocities, float64 (``Simulation.state``)."""
        ...

    def contacts(self) -> dict[str, np.ndarray]:
        """The contacts of the last step and their forces (``Simulation.contacts``)."""
        ...

    def restore_from_arrays(self, arrays: dict[str, np.ndarray], steps_done: int, time: float) -> None:
        """Go back to a checkpoint's arrays, at ``steps_done`` and ``time``."""
        ...

    def restore_last_good(self) -> bool:
        """After an exception inside :meth:`step`: whether the state is now that of ``steps_done``."""
        ...

    @property
    def contact_average_steps(self) -> int | None:
        """Steps in the running contact-force average (None: none is running)."""
        ...

    def start_contact_average(self) -> None:
        """Start (again) averaging the contact forces over the steps from now on."""
        ...

    def contact_average(self) -> dict[str, Any]:
        """The contact forces averaged since :meth:`start_contact_average` (``Simulation.contact_average``)."""
        ...
