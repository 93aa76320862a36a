"""The ``wp.struct`` types that group the arrays the kernels take together, one type per precision.

A kernel takes one struct where it would take six to ten arrays: the bodies' static arrays of a Model
(:func:`body_model_struct`), the material table (:func:`materials_struct`), the plane walls
(:func:`planes_struct`), the mesh walls (:func:`mesh_walls_struct`), the bodies' state
(:func:`bodies_struct`), the wall contacts' history (:func:`wall_history_struct`), the pair list with its
per-pair arrays (:func:`pairs_struct`) and the contact outputs (:func:`outputs_struct`). The owners of the
arrays build each instance once, where they build the arrays (:class:`polydem.model.Model`,
:class:`polydem.state.State`, :class:`polydem.contacts.Contacts`), and again where they replace them: a
launch copies the struct's value, array pointers included, so a captured CUDA graph holds the arrays it
was captured with, as it does with arrays passed one by one (the struct is in the kernel's parameter
space, as the arrays were: on sm_90 the contact kernels came out with smaller stack frames, and a few
kernels of at most 32 registers took one to three more).

S is the state scalar and C the contact scalar of a precision (:func:`polydem.kernels.precision.scalars`).
Each factory is cached, so that every caller gets the same type for the same scalars (Warp checks a
struct argument's type by identity); :func:`struct_types` names them all for one precision.
"""

import functools
from dataclasses import dataclass
from typing import Any

import warp as wp
from polydem.kernels.precision import scalars


def make_struct(name: str, **members: Any) -> Any:
    """A ``wp.struct`` type ``name`` with ``members`` (name: Warp type, in order), made in this module
    (registered in ``sys.modules``, as Warp needs)."""
    cls = type(name, (), {"__annotations__": members, "__module__": __name__, "__qualname__": name})
    return wp.struct(cls)


def arrays(**dtypes: Any) -> dict[str, Any]:
    """Members that are 1-D arrays of the dtypes given, by name."""
    return {name: wp.array(dtype=dtype) for name, dtype in dtypes.items()}


def filled(struct: Any, **values: Any) -> Any:
    """An instance of the ``wp.struct`` type ``struct`` with its members set to ``values``."""
    instance = struct()
    for name, value in values.items():
        setattr(instance, name, value)
    return instance


@functools.cache
def body_model_struct(S: Any) -> Any:
    """The bodies' static arrays of a Model (N,): ``shape``, ``material`` and ``flags`` (0 free, 1 fixed, 2
    kinematic) int32, ``inv_mass`` S [1/kg], ``inertia`` S vec3 principal moments [kg m^2], ``radius``
    float32 bounding radius [m], ``pivot`` S vec3 [m] (read only where ``has_pivot`` is 1)."""
    vec3 = wp.types.vector(3, S)
    members = arrays(shape=int, material=int, flags=int, inv_mass=S, inertia=vec3, radius=float, pivot=vec3)
    return make_struct("BodyModel", **members, has_pivot=int)


@functools.cache
def bodies_struct(S: Any) -> Any:
    """The bodies' state (N,), in S: pose ``q`` (transform), velocity ``v``, angular velocity ``w``, the force
    ``f`` and torque ``t`` of the last force stage and the energy ``dissipated`` so far (as
    :class:`polydem.state.State`'s ``body_*``)."""
    vec3 = wp.types.vector(3, S)
    return make_struct("Bodies", **arrays(q=wp.types.transformation(S), v=vec3, w=vec3, f=vec3, t=vec3, dissipated=S))


@functools.cache
def materials_struct(C: Any) -> Any:
    """The material table: ``count`` materials M, the law's exponent ``law_m``, the step ``toe_dt`` [s] whose
    resolved toe the laws with one take (the larger of the run's and the recommended step: response.toe_volume), the
    (M*M,) mixed pair properties in C, row-major by (A's material, B's): stiffness ``k``, restitution ``e``,
    friction ``mu``, tangential stiffness ``kt`` and the tangential dashpot's factor of e, ``damping``
    (kernels/response.py ``make_damping``)."""
    return make_struct("Materials", count=int, law_m=C, toe_dt=C, **arrays(k=C, e=C, mu=C, kt=C, damping=C))


@functools.cache
def planes_struct(S: Any) -> Any:
    """The plane walls (P,): outward unit ``normal``, ``offset`` [m] (n . x of its points) and velocity ``v``
    [m/s] in S, ``material`` int32. The Model's planes are where they are at t = 0, at rest; a Stepper whose
    planes follow motions keeps its own offsets and velocities (kernels/motion.py, ``launch_drive_walls``)."""
    vec3 = wp.types.vector(3, S)
    return make_struct("Planes", **arrays(normal=vec3, offset=S, material=int, v=vec3))


@functools.cache
def wall_history_struct(C: Any) -> Any:
    """The wall contacts' history (N, W) in C: friction springs ``xi`` and turning volumes ``turn``."""
    return make_struct("WallHistory", xi=wp.array2d(dtype=wp.types.vector(3, C)), turn=wp.array2d(dtype=C))


@functools.cache
def pairs_struct(C: Any) -> Any:
    """The candidate pairs (capacity,): bodies ``a`` and ``b``, their ``count`` (1,); history (``xi``, (1,)
    without friction; ``turn``) and last step's ``force``, ``torque_a`` and ``dissipated`` in C; the pairs
    ordered by B (``by_b``), the pair each thread of the pair kernel takes (``thread``; (1,) where threads take
    their own slot) and each body's (N,) vec2i ranges in the pairs by A and by B (``ranges_a``, ``ranges_b``)."""
    vec3 = wp.types.vector(3, C)
    members = arrays(
        a=int, b=int, count=int, xi=vec3, turn=C, force=vec3, torque_a=vec3, dissipated=C, by_b=int, thread=int
    )
    return make_struct("Pairs", **members, **arrays(ranges_a=wp.vec2i, ranges_b=wp.vec2i))


@functools.cache
def mesh_walls_struct(S: Any) -> Any:
    """The mesh walls (M,) of a Model: each one's cell BVH (``bvh``, a ``wp.Bvh`` id), first cell
    (``cell_start``, (M+1,)), ``material``, velocity ``v`` and angular velocity ``w`` in S; per cell (C,) its
    shape in the shape set (``cell_shape``), frame origin in its wall's frame (``cell_center``) and front
    plane (``cell_front``, S vec4); ``first_column``: the wall columns of the mesh walls start after the
    planes'."""
    vec3 = wp.types.vector(3, S)
    members = arrays(bvh=wp.uint64, cell_start=int, material=int, v=vec3, w=vec3, cell_shape=int, cell_center=vec3)
    return make_struct("MeshWalls", **members, cell_front=wp.array(dtype=wp.types.vector(4, S)), first_column=int)


def output_dtypes(S: Any, C: Any) -> dict[str, Any]:
    """The dtype of each quantity of the contact outputs (:class:`polydem.kernels.forces.ContactOutputs`;
    ``volume`` for ``pair_volume`` and ``wall_volume``) for a state scalar S and a contact scalar C: the
    points in S, the rest in C."""
    vec3s, vec3c = wp.types.vector(3, S), wp.types.vector(3, C)
    return {"volume": C, "energy": C, "normal": vec3c, "point": vec3s, "fn": C, "ft": vec3c, "depth": C}


@functools.cache
def outputs_struct(S: Any, C: Any, walls: bool) -> Any:
    """The pair columns of the contact outputs (a (pairs,) array per quantity of :func:`output_dtypes`,
    named as it: ``volume``, ...) or, with ``walls``, their wall columns ((bodies, walls) arrays), which the
    diagnostics and report variants of the contact kernels write."""
    array = wp.array2d if walls else wp.array
    members = {quantity: array(dtype=dtype) for quantity, dtype in output_dtypes(S, C).items()}
    return make_struct("WallOutputs" if walls else "PairOutputs", **members)


@dataclass(frozen=True)
class StructTypes:
    """The struct types of one precision, by the names the kernels give them."""

    BodyModel: Any
    Bodies: Any
    Materials: Any
    Planes: Any
    MeshWalls: Any
    WallHistory: Any
    Pairs: Any
    PairOutputs: Any
    WallOutputs: Any


@functools.cache
def struct_types(precision: str) -> StructTypes:
    """The struct types of the kernels of ``precision`` (:mod:`polydem.kernels.precision`)."""
    S, C = scalars(precision)
    return StructTypes(
        BodyModel=body_model_struct(S),
        Bodies=bodies_struct(S),
        Materials=materials_struct(C),
        Planes=planes_struct(S),
        MeshWalls=mesh_walls_struct(S),
        WallHistory=wall_history_struct(C),
        Pairs=pairs_struct(C),
        PairOutputs=outputs_struct(S, C, False),
        WallOutputs=outputs_struct(S, C, True),
    )
