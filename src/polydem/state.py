"""State: the arrays a step reads and writes for every body and every wall contact.

A :class:`State` holds no contact pairs (those, with their history, are in
:class:`~polydem.contacts.Contacts`) and nothing static (that is the :class:`~polydem.model.Model`).
``Model.state()`` gives the initial state of a scene; ``Stepper.step(state_in, state_out, contacts,
dt)`` writes the next one.
"""

from __future__ import annotations

from collections.abc import Iterable

import numpy as np
import warp as wp

from polydem.kernels.precision import Precision, numpy_dtype, scalars
from polydem.kernels.structs import bodies_struct, filled, wall_history_struct

__all__ = ["State"]


class State:
    """Device arrays of the bodies and of their contacts with the walls.

    N bodies, W walls (the P planes, then the M mesh walls; W >= 1: a scene without walls keeps a
    placeholder column).

    Dtypes by ``precision`` (:mod:`polydem.kernels.precision`): the body arrays (``body_*``) are
    float32 in "float32" and float64 in "mixed" and "float64" (``wp.transformd``, ``wp.vec3d``);
    the wall-contact history (``wall_*``) is float32 in "float32" and "mixed", float64 in
    "float64".

    Attributes:
        body_q: (N,) ``wp.transform``: centroid position [m] and unit quaternion xyzw from the body
            frame (the principal axes) to the world.
        body_v: (N,) ``wp.vec3`` linear velocity [m/s].
        body_w: (N,) ``wp.vec3`` angular velocity in world axes [rad/s].
        body_f: (N,) ``wp.vec3`` force of the contacts and walls in the last step, without
            gravity [N]; zero before the first step and after a restore (``Simulation.restore``:
            no step has run since the state was set; see :attr:`TRANSIENT`).
        body_t: (N,) ``wp.vec3`` torque of those forces about the centroid, world axes [N m]; as ``body_f``.
        body_dissipated: (N,) energy dissipated so far by damping and friction at the
            body's contacts [J].
        body_damping: (N,) float32 damping load of each free body for the next step [1]: dt times the
            inverse mass at its farthest point times its contacts' tangential dashpots (kernels/forces.py
            ``damping_load_kernel``), written at the end of each step's force stage; derived from the contact
            history (neither a checkpoint nor a snapshot keeps it: it is computed again when one is restored).
        wall_xi: (N, P) ``wp.vec3`` friction springs of the wall contacts [m]; (1, 1) when the
            scene has no friction.
        wall_turn: (N, P) turning volumes of the wall contacts (the normal hysteresis,
            kernels/forces.py) [m^3].
        mesh_q: (max(M, 1),) ``wp.transform`` pose of each mesh wall's frame (origin at its pivot) [m].
        step_count: (1,) int32 steps done; counted on the device so that a captured step counts.
        motion_travel: (max(K, 1),) ``wp.vec3d`` of the K motions: each ramp's and servo's displacement [m],
            velocity [m/s] and the force the grains push back with [N] at the last step (kernels/motion.py;
            a servo's displacement is summed here, so a snapshot must carry it).
        precision: the :class:`~polydem.kernels.precision.Precision`.
        bodies, walls: the ``body_*`` arrays and ``wall_xi``, ``wall_turn`` in the ``wp.struct`` the kernels
            take (:mod:`polydem.kernels.structs`); built on first use and again after one of their arrays is
            replaced by another.
    """

    body_q: wp.array
    body_v: wp.array
    body_w: wp.array
    body_f: wp.array
    body_t: wp.array
    body_dissipated: wp.array
    body_damping: wp.array
    wall_xi: wp.array
    wall_turn: wp.array
    mesh_q: wp.array
    step_count: wp.array
    motion_travel: wp.array
    device: wp.Device
    precision: Precision

    FIELDS: tuple[str, ...] = ("body_q", "body_v", "body_w", "body_f", "body_t", "body_dissipated", "wall_xi")
    FIELDS += ("wall_turn", "mesh_q", "step_count")
    FIELDS += ("motion_travel", "body_damping")
    """Every array of a state, in the order :meth:`assign` copies them."""

    SAVED = ("body_q", "body_v", "body_w", "body_dissipated", "wall_xi", "wall_turn", "mesh_q", "step_count")
    """What a checkpoint keeps: ``body_f`` and ``body_t`` are written by every step before they are read."""

    TRANSIENT = ("body_f", "body_t", "body_damping")
    """The outputs of a step's force stage, which every step writes before it reads them, and the damping
    loads, which the pair history gives: a snapshot (``copy(transient=False)``, ``Simulation.snapshot``) leaves
    them out, :meth:`assign` from such a copy zeroes them, and ``Simulation.restore`` computes the loads
    again."""

    # The arrays of each struct (bodies_struct, wall_history_struct), by the struct's member names.
    _BODIES = {"q": "body_q", "v": "body_v", "w": "body_w", "f": "body_f", "t": "body_t"}
    _BODIES |= {"dissipated": "body_dissipated"}
    _WALLS = {"xi": "wall_xi", "turn": "wall_turn"}
    _STRUCT_OF = dict.fromkeys(_BODIES.values(), "_bodies") | dict.fromkeys(_WALLS.values(), "_walls")

    def __setattr__(self, name: str, value: object) -> None:
        super().__setattr__(name, value)
        if name in self._STRUCT_OF:
            # A struct holds its arrays' pointers: one built with the array replaced is built again.
            self.__dict__.pop(self._STRUCT_OF[name], None)

    @property
    def bodies(self):
        if "_bodies" not in self.__dict__:
            arrays = {member: getattr(self, name) for member, name in self._BODIES.items()}
            self._bodies = filled(bodies_struct(scalars(self.precision)[0]), **arrays)
        return self._bodies

    @property
    def walls(self):
        if "_walls" not in self.__dict__:
            arrays = {member: getattr(self, name) for member, name in self._WALLS.items()}
            self._walls = filled(wall_history_struct(scalars(self.precision)[1]), **arrays)
        return self._walls

    @staticmethod
    def dtypes(precision: str = Precision.FLOAT32) -> dict[str, type]:
        """The Warp dtype of every field in ``precision``, by name."""
        s, c = scalars(precision)
        vec3s, vec3c = wp.types.vector(3, s), wp.types.vector(3, c)
        return {
            "body_q": wp.types.transformation(s),
            "body_v": vec3s,
            "body_w": vec3s,
            "body_f": vec3s,
            "body_t": vec3s,
            "body_dissipated": s,
            "wall_xi": vec3c,
            "wall_turn": c,
            "mesh_q": wp.types.transformation(s),
            "step_count": int,
            "motion_travel": wp.vec3d,
            "body_damping": wp.float32,
        }

    def __init__(
        self,
        num_bodies: int,
        num_planes: int,
        friction: bool,
        device: wp.DeviceLike = None,
        precision: str = Precision.FLOAT32,
        num_meshes: int = 0,
        num_motions: int = 0,
    ) -> None:
        """A state of ``num_bodies`` bodies at rest at the origin, with no contact history."""
        dev = wp.get_device(device)
        n = int(num_bodies)
        planes = max(int(num_planes), 1)
        self.device = dev
        self.precision = Precision(precision)
        shapes: dict[str, int | tuple[int, int]] = {name: n for name in self.FIELDS}
        shapes.update(wall_xi=(n, planes) if friction else (1, 1), wall_turn=(n, planes), step_count=1)
        shapes.update(mesh_q=max(int(num_meshes), 1), motion_travel=max(int(num_motions), 1))
        for name, dtype in self.dtypes(precision).items():
            setattr(self, name, wp.zeros(shapes[name], dtype=dtype, device=dev))

    @property
    def num_bodies(self) -> int:
        return len(self.body_q)

    @classmethod
    def from_numpy(
        cls, arrays: dict[str, np.ndarray], device: wp.DeviceLike = None, precision: str = Precision.FLOAT32
    ) -> State:
        """A state in ``precision`` from host arrays named as :attr:`FIELDS` (``body_f``, ``body_t`` and
        ``body_damping`` may be left out: zeros); the arrays are converted to the precision's dtypes."""
        dev = wp.get_device(device)
        state = cls.__new__(cls)
        state.device = dev
        state.precision = Precision(precision)
        n = len(arrays["body_q"])
        body, history = (numpy_dtype(x) for x in scalars(precision))
        for name, dtype in cls.dtypes(precision).items():
            if name in arrays:
                a = np.asarray(arrays[name])
                if name == "mesh_q":
                    a = a.astype(body)
                elif name == "motion_travel":
                    a = a.astype(np.float64)
                elif name == "body_damping":
                    a = a.astype(np.float32)
                elif name != "step_count":
                    a = a.astype(body if name.startswith("body_") else history)
                a = wp.array(a, dtype=dtype, device=dev)
            else:
                a = wp.zeros(1 if name in ("mesh_q", "motion_travel") else n, dtype=dtype, device=dev)
            setattr(state, name, a)
        return state

    def numpy(self, fields: Iterable[str] = SAVED) -> dict[str, np.ndarray]:
        """Host copies of ``fields`` (default: what a checkpoint keeps), by name."""
        return {name: getattr(self, name).numpy() for name in fields}

    def assign(self, other: State) -> None:
        """Copy every array of ``other`` (a state of the same shapes) into this one.

        Where ``other`` holds no :attr:`TRANSIENT` arrays (a copy made with ``transient=False``), this
        state's are zeroed: no step has written them since the state was set (the damping loads, zero
        here, are computed again by ``Simulation.restore``; a state stepped without that would run with
        unscaled dashpots for one step). Where this state holds none, only the others are copied.
        """
        mine, theirs = self.__dict__, other.__dict__
        for name in self.FIELDS:
            if name not in mine:
                continue
            if name in theirs:
                wp.copy(mine[name], theirs[name])
            else:
                mine[name].zero_()

    def copy(self, transient: bool = True) -> State:
        """A new state with copies of every array; with ``transient=False`` without :attr:`TRANSIENT`
        (``body_f``, ``body_t``, ``body_damping``: a snapshot's, 2 x 12 + 4 or 2 x 24 + 4 bytes a body
        less; such a state is only read, by :meth:`assign`, :meth:`numpy` of other fields and
        :meth:`same_shapes`)."""
        state = State.__new__(State)
        state.device = self.device
        state.precision = self.precision
        for name in self.FIELDS:
            if transient or name not in self.TRANSIENT:
                setattr(state, name, wp.clone(getattr(self, name)))
        return state

    def same_shapes(self, other: State) -> bool:
        """Whether :meth:`assign` can copy ``other`` into this state: the arrays both hold have the same shapes."""
        mine, theirs = self.__dict__, other.__dict__
        return all(mine[k].shape == theirs[k].shape for k in self.FIELDS if k in mine and k in theirs)
