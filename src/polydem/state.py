"""State: the arrays a step reads and writes for every body and every wall contact.

A :class:`State` holds no contact pairs (those, with their history, are in
:class:`~polydem.contacts.Contacts`) and nothing static (that is the :class:`~polydem.model.Model`).
``Model.state()`` gives the initial state of a scene; ``Stepper.step(state_in, state_out, contacts,
dt)`` writes the next one.
"""

import numpy as np
import warp as wp

from polydem.kernels.precision import numpy_dtype, scalars

__all__ = ["State"]


class State:
    """Device arrays of the bodies and of their contacts with the walls.

    N bodies, W walls (the P planes, then the M mesh walls; W >= 1: a scene without walls keeps a
    placeholder column).

    Dtypes by ``precision`` (:mod:`polydem.kernels.precision`): the body arrays (``body_*``) are
    float32 in "float32" and float64 in "mixed" and "float64" (``wp.transformd``, ``wp.vec3d``);
    the wall-contact history (``plane_*``) is float32 in "float32" and "mixed", float64 in
    "float64".

    Attributes:
        body_q: (N,) ``wp.transform``: centroid position [m] and unit quaternion xyzw from the body
            frame (the principal axes) to the world.
        body_v: (N,) ``wp.vec3`` linear velocity [m/s].
        body_w: (N,) ``wp.vec3`` angular velocity in world axes [rad/s].
        body_f: (N,) ``wp.vec3`` force of the contacts and walls in the last step, without
            gravity [N].
        body_t: (N,) ``wp.vec3`` torque of those forces about the centroid, world axes [N m].
        body_dissipated: (N,) energy dissipated so far by damping and friction at the
            body's contacts [J].
        plane_xi: (N, P) ``wp.vec3`` friction springs of the wall contacts [m]; (1, 1) when the
            scene has no friction.
        plane_turn: (N, P) turning volumes of the wall contacts (the normal hysteresis,
            kernels/forces.py) [m^3].
        mesh_q: (max(M, 1),) ``wp.transform`` pose of each mesh wall's frame (origin at its pivot) [m].
        step_count: (1,) int32 steps done; counted on the device so that a captured step counts.
        precision: "float32", "mixed" or "float64".
    """

    FIELDS = ("body_q", "body_v", "body_w", "body_f", "body_t", "body_dissipated", "plane_xi", "plane_turn")
    FIELDS += ("mesh_q", "step_count")
    """Every array of a state, in the order :meth:`assign` copies them."""

    SAVED = ("body_q", "body_v", "body_w", "body_dissipated", "plane_xi", "plane_turn", "mesh_q", "step_count")
    """What a checkpoint keeps: ``body_f`` and ``body_t`` are written by every step before they are read."""

    @staticmethod
    def dtypes(precision="float32"):
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
            "plane_xi": vec3c,
            "plane_turn": c,
            "mesh_q": wp.types.transformation(s),
            "step_count": int,
        }

    def __init__(self, num_bodies, num_planes, friction, device=None, precision="float32", num_meshes=0):
        """A state of ``num_bodies`` bodies at rest at the origin, with no contact history."""
        dev = wp.get_device(device)
        n = int(num_bodies)
        planes = max(int(num_planes), 1)
        self.device = dev
        self.precision = precision
        shapes = {name: n for name in self.FIELDS}
        shapes.update(plane_xi=(n, planes) if friction else (1, 1), plane_turn=(n, planes), step_count=1)
        shapes.update(mesh_q=max(int(num_meshes), 1))
        for name, dtype in self.dtypes(precision).items():
            setattr(self, name, wp.zeros(shapes[name], dtype=dtype, device=dev))

    @property
    def num_bodies(self):
        return len(self.body_q)

    @classmethod
    def from_numpy(cls, arrays, device=None, precision="float32"):
        """A state in ``precision`` from host arrays named as :attr:`FIELDS` (``body_f`` and
        ``body_t`` may be left out: zeros); the arrays are converted to the precision's dtypes."""
        dev = wp.get_device(device)
        state = cls.__new__(cls)
        state.device = dev
        state.precision = precision
        n = len(arrays["body_q"])
        body, history = (numpy_dtype(x) for x in scalars(precision))
        for name, dtype in cls.dtypes(precision).items():
            if name in arrays:
                a = np.asarray(arrays[name])
                if name == "mesh_q":
                    a = a.astype(body)
                elif name != "step_count":
                    a = a.astype(body if name.startswith("body_") else history)
                a = wp.array(a, dtype=dtype, device=dev)
            else:
                a = wp.zeros(1 if name == "mesh_q" else n, dtype=dtype, device=dev)
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
        state.precision = self.precision
        for name in self.FIELDS:
            setattr(state, name, wp.clone(getattr(self, name)))
        return state

    def same_shapes(self, other):
        """Whether :meth:`assign` can copy ``other`` into this state."""
        return all(getattr(self, k).shape == getattr(other, k).shape for k in self.FIELDS)
