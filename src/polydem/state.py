"""State: the arrays a step reads and writes for every body and every wall contact.

A :class:`State` holds no contact pairs (those, with their history, are in
:class:`~polydem.contacts.Contacts`) and nothing static (that is the :class:`~polydem.model.Model`).
``Model.state()`` gives the initial state of a scene; ``Stepper.step(state_in, state_out, contacts,
dt)`` writes the next one.
"""

import numpy as np
import warp as wp

__all__ = ["State"]


class State:
    """Device arrays (float32) of the bodies and of their contacts with the walls.

    N bodies, P wall planes (P >= 1: a scene without walls keeps a placeholder column).

    Attributes:
        body_q: (N,) ``wp.transform``: centroid position [m] and unit quaternion xyzw from the body
            frame (the principal axes) to the world.
        body_v: (N,) ``wp.vec3`` linear velocity [m/s].
        body_w: (N,) ``wp.vec3`` angular velocity in world axes [rad/s].
        body_f: (N,) ``wp.vec3`` force of the contacts and walls in the last step, without
            gravity [N].
        body_t: (N,) ``wp.vec3`` torque of those forces about the centroid, world axes [N m].
        body_dissipated: (N,) float32 energy dissipated so far by damping and friction at the
            body's contacts [J].
        plane_xi: (N, P) ``wp.vec3`` friction springs of the wall contacts [m]; (1, 1) when the
            scene has no friction.
        plane_turn: (N, P) float32 turning volumes of the wall contacts (the normal hysteresis,
            kernels/forces.py) [m^3].
        step_count: (1,) int32 steps done; counted on the device so that a captured step counts.
    """

    FIELDS = ("body_q", "body_v", "body_w", "body_f", "body_t", "body_dissipated", "plane_xi", "plane_turn")
    FIELDS += ("step_count",)
    """Every array of a state, in the order :meth:`assign` copies them."""

    SAVED = ("body_q", "body_v", "body_w", "body_dissipated", "plane_xi", "plane_turn", "step_count")
    """What a checkpoint keeps: ``body_f`` and ``body_t`` are written by every step before they are read."""

    _DTYPES = {
        "body_q": wp.transform,
        "body_v": wp.vec3,
        "body_w": wp.vec3,
        "body_f": wp.vec3,
        "body_t": wp.vec3,
        "body_dissipated": float,
        "plane_xi": wp.vec3,
        "plane_turn": float,
        "step_count": int,
    }

    def __init__(self, num_bodies, num_planes, friction, device=None):
        """A state of ``num_bodies`` bodies at rest at the origin, with no contact history."""
        dev = wp.get_device(device)
        n = int(num_bodies)
        planes = max(int(num_planes), 1)
        self.device = dev
        self.body_q = wp.zeros(n, dtype=wp.transform, device=dev)
        self.body_v = wp.zeros(n, dtype=wp.vec3, device=dev)
        self.body_w = wp.zeros(n, dtype=wp.vec3, device=dev)
        self.body_f = wp.zeros(n, dtype=wp.vec3, device=dev)
        self.body_t = wp.zeros(n, dtype=wp.vec3, device=dev)
        self.body_dissipated = wp.zeros(n, dtype=float, device=dev)
        self.plane_xi = wp.zeros((n, planes) if friction else (1, 1), dtype=wp.vec3, device=dev)
        self.plane_turn = wp.zeros((n, planes), dtype=float, device=dev)
        self.step_count = wp.zeros(1, dtype=int, device=dev)

    @property
    def num_bodies(self):
        return len(self.body_q)

    @classmethod
    def from_numpy(cls, arrays, device=None):
        """A state from host arrays named as :attr:`FIELDS` (``body_f`` and ``body_t`` may be left out: zeros)."""
        dev = wp.get_device(device)
        state = cls.__new__(cls)
        state.device = dev
        n = len(arrays["body_q"])
        for name in cls.FIELDS:
            if name in arrays:
                a = wp.array(np.asarray(arrays[name]), dtype=cls._DTYPES[name], device=dev)
            else:
                a = wp.zeros(n, dtype=cls._DTYPES[name], device=dev)
            setattr(state, name, a)
        return state

    def numpy(self, fields=SAVED):
        """Host copies of ``fields`` (default: what a checkpoint keeps), by name."""
        return {name: getattr(self, name).numpy() for name in fields}

    def assign(self, other):
        """Copy every array of ``other`` (a state of the same shapes) into this one."""
        for name in self.FIELDS:
            wp.copy(getattr(self, name), getattr(other, name))

    def copy(self):
        """A new state with copies of every array."""
        state = State.__new__(State)
        state.device = self.device
        for name in self.FIELDS:
            setattr(state, name, wp.clone(getattr(self, name)))
        return state

    def same_shapes(self, other):
        """Whether :meth:`assign` can copy ``other`` into this state."""
        return all(getattr(self, k).shape == getattr(other, k).shape for k in self.FIELDS)
