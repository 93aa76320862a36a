"""Host-side description of a simulation: materials, shapes, bodies and walls.

Data flows one way: a scene file (TOML) or Python calls -> :class:`Scene` -> ``Model``/``State``
(device arrays). A Scene holds only numpy arrays and plain Python objects; it never touches Warp.
Every user error raises :class:`SceneError`, which names the file (if any), the offending key
(e.g. ``bodies[3].material``) and says how to fix it.

Units are SI throughout: m, s, kg, rad (the scene file also takes ``degrees`` where it says so).
Quaternions are ``[x, y, z, w]`` (Warp's order) and must be unit quaternions.

Poses. A :class:`~polydem.ConvexShape` lives in its *body frame* (origin at the centroid, axes along
the principal axes of inertia), which in general is not the frame its points were given in (the
*input frame*; ``shape.input_transform`` maps body -> input coordinates: ``x_in = R_in x_b + t_in``).
Users place a shape by its input frame: ``position`` is where the input-frame origin goes and
``orientation`` rotates the input axes. So a box of size (0.3, 0.1, 0.2) with the identity
orientation has its 0.3 m edge along world x, and a mesh placed at the origin sits exactly where it
is in its file. For every generated shape except ``rock`` the input origin is the centroid. The
scene stores the pose of the body frame, which is what the simulator integrates::

    body_position    = position + R(orientation) @ t_in        (the centre of mass) [m]
    body_orientation = orientation * q(R_in)                     (body frame -> world)

``velocity`` is the velocity of the centre of mass [m/s] and ``angular_velocity`` is in world axes
[rad/s], whichever frame the pose was given in.

Body kinds: ``free`` bodies move under gravity and contacts; ``fixed`` bodies never move (their
velocities must be zero); ``kinematic`` bodies move with their prescribed (constant) velocity and
angular velocity and are not pushed by contacts. A kinematic body may name a ``pivot``: a fixed
point its pose turns about at its angular velocity (the parts of a rotating drum); its velocity is
then ``angular_velocity x (centroid - pivot)`` at the start and is derived, not given.

Scene files (TOML; examples in ``scenes/``). Every table and key is checked; an unknown key gets a
did-you-mean and the list of valid keys, and every error names the file and the key::

    [simulation]     name, description, steps | duration, dt (seconds or "auto"), gravity,
                     device ("cpu", "cuda", "cuda:N"; optional), precision ("mixed", the
                     default: float64 positions, velocities and force sums, float32 contact
                     geometry local to each contact; "float32": float32 throughout, leaner;
                     "float64": float64 throughout), until_settled (true: run until the pile has
                     settled, steps | duration being the maximum; polydem.SettleCriterion)
    [simulation.settle]  the settle criterion (implies until_settled): kinetic_fraction (of the
                     gravitational energy released, default 1e-4; false for none),
                     speed_fraction (limit on any free body's fastest point, as a fraction of
                     sqrt(g r_min), default 3e-4; false for none), max_speed [m/s] (replaces
                     speed_fraction's limit), hold [s] (default 0.02)
    [materials.NAME] density, law, k, restitution, friction (+ m, tangential_stiffness)
    [shapes.NAME]    type = box | tetrahedron | ... | mesh | points, and its parameters
    [[bodies]]       shape, material, position, orientation | rotation, velocity, angular_velocity,
                     kind (free | fixed | kinematic), pivot (kinematic bodies turning about a point)
    [[walls]]        type = "plane" (point, normal, material), "box" (an open or closed container
                     of fixed slabs) or "drum" (a rotating polygonal drum of kinematic slabs)
    [[emitters]]     many bodies placed without overlaps in a box region (see Scene.emit)
    [output]         usd, fps, summary, pictures, checkpoint, vtk (see Output)

Bodies are added in the file's order of sections: ``[[bodies]]``, then ``[[walls]]``, then
``[[emitters]]`` (so emitters avoid every body and wall given before them), each in its order.

The package keeps each concern in one file: :mod:`.description` (the Scene class and its shape
registry), :mod:`.settings` (the ``[simulation]`` table), :mod:`.bodies`, :mod:`.materials`,
:mod:`.walls` (planes, meshes, box containers, drums), :mod:`.emitters`, :mod:`.output`,
:mod:`.checks` (float32 ranges, the time step, loads), :mod:`.overlaps` (initial overlaps),
:mod:`.shape_specs` and :mod:`.loader` (scene files), with :mod:`.errors`, :mod:`.values` (the typed
readers every value goes through) and :mod:`.schema` (``Key`` and ``Table``: each table of a scene
file is declared once, beside the module that uses it, and the loader, the checks of single values,
the messages and ``Scene.to_dict`` come from the declaration); quaternion maths is
:mod:`polydem.quaternions`. No module of the package imports another that imports it back
(tests/test_scene_imports.py).
"""

from polydem.quaternions import quat_to_matrix
from polydem.scene.bodies import KIND_FIXED, KIND_FREE, KIND_KINEMATIC, KINDS, MAX_BODIES, Body, BodyKind
from polydem.scene.checks import (
    F32_HIGH,
    F32_LOW,
    MAX_DT_FRACTION,
    MAX_STEPS,
    OVERLAP_ERROR,
    OVERLAP_WARNING,
    REFERENCE_DEPTH,
    STEPS_PER_CONTACT_PERIOD,
    TimeStep,
    reference_stiffness,
)
from polydem.scene.description import Scene
from polydem.scene.emitters import FILLS, ORIENTATIONS
from polydem.scene.errors import SceneError, SceneWarning
from polydem.scene.materials import LAWS, Material, PairMaterial, pair_material
from polydem.scene.output import Output
from polydem.scene.overlaps import INITIAL_OVERLAP_ERROR, INITIAL_OVERLAP_WARNING
from polydem.scene.settings import PRECISIONS
from polydem.scene.shape_specs import SHAPE_TYPES
from polydem.scene.values import QUAT_TOL, quat_from_axis_angle
from polydem.scene.walls import Drum, PlaneWall

__all__ = [
    "Body",
    "BodyKind",
    "Drum",
    "F32_HIGH",
    "F32_LOW",
    "FILLS",
    "INITIAL_OVERLAP_ERROR",
    "INITIAL_OVERLAP_WARNING",
    "KINDS",
    "KIND_FIXED",
    "KIND_FREE",
    "KIND_KINEMATIC",
    "LAWS",
    "MAX_BODIES",
    "MAX_DT_FRACTION",
    "MAX_STEPS",
    "Material",
    "ORIENTATIONS",
    "OVERLAP_ERROR",
    "OVERLAP_WARNING",
    "Output",
    "PRECISIONS",
    "PairMaterial",
    "PlaneWall",
    "QUAT_TOL",
    "REFERENCE_DEPTH",
    "SHAPE_TYPES",
    "STEPS_PER_CONTACT_PERIOD",
    "Scene",
    "SceneError",
    "SceneWarning",
    "TimeStep",
    "pair_material",
    "quat_from_axis_angle",
    "quat_to_matrix",
    "reference_stiffness",
]
