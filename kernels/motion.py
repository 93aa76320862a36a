"""Prescribed motions of containers and pistons: vibration, taps, ramps and servos (issue 26).

A motion moves a set of kinematic bodies (a container's slabs, a piston) together along a unit ``axis``
by a displacement ``d(t)`` on the device, so that a captured CUDA graph replays it without the host.
Each cycle of a cycle motion is one period of

    d(s) = A (1 - cos(w s)),   v(s) = A w sin(w s),   a(s) = A w^2 cos(w s),   0 <= s < 2 pi / w,

which starts and ends at rest in place (the velocity is continuous, the container returns to where
it was), lifts by 2 A at mid-cycle and reaches the peak acceleration ``A w^2 = Gamma g`` at its ends
(upwards) and its middle (downwards: the grains leave the floor there where Gamma > 1). Cycles start
every ``period`` seconds from ``start``: a period of one cycle is a continuous vibration, a longer one
a train of taps with the container at rest between them; ``count`` cycles in all (0: no end).

A ramp moves at a set speed: ``d = speed (t - start)`` for ``start <= t < start + duration``, then
``speed duration``. Cycles and ramps take d(t) from the step counter each step (never summed from
velocities, so nothing drifts over 1e6 steps) and the velocity from v(t), which the contact forces use
for the wall's relative velocity.

A servo integrates its displacement, ``d += v dt`` with ``v = clamp(gain (F_target - F), +-max_speed)``
(from ``start`` on), F the force the grains push its bodies back with along -axis in the step's force
stage: its (d, v, F) live in the state (``motion_travel``), so that a snapshot, a redo and a CUDA graph
carry them. Ramps record (d, v, F) there too, for a stress-strain record (polydem.protocols.compress).
F is summed without atomics, in a fixed order (``LANES`` strided partial sums per body, then the bodies
and lanes in order), so that a run repeats bit for bit.
"""

import functools
import math

import warp as wp
from polydem.kernels.precision import scalars
from polydem.kernels.structs import arrays, make_struct, pairs_struct, planes_struct

__all__ = [
    "LANES",
    "MOTION_CYCLE",
    "MOTION_RAMP",
    "MOTION_SERVO",
    "Motions",
    "cycle_displacement",
    "launch_drive_bodies",
    "launch_drive_walls",
    "launch_measure_motions",
    "make_motion_kernels",
    "make_wall_motion_kernel",
    "ramp_displacement",
]

MOTION_CYCLE = wp.constant(0)
MOTION_RAMP = wp.constant(1)
MOTION_SERVO = wp.constant(2)
LANES = 32
"""Partial sums per driven body of the force on it: its pairs are walked by this many threads."""

_CYCLES = arrays(axis=wp.vec3d, amplitude=wp.float64, omega=wp.float64, start=wp.float64, period=wp.float64, count=int)
_MEASURED = arrays(kind=int, speed=wp.float64, duration=wp.float64, target=wp.float64, gain=wp.float64)
_WALLS = arrays(plane_motion=int, plane_rest=wp.float64, mesh_motion=int, mesh_rest=wp.vec3d)
Motions = make_struct(
    "Motions",
    **_CYCLES,
    **_MEASURED,
    **arrays(body_motion=int, body_rest=wp.vec3d, rows=int, row_start=int),
    **_WALLS,
)


StepTime = make_struct("StepTime", step_count=wp.array(dtype=int), step_offset=int, dt=wp.float64)
"""The time the motions are taken at: the end of step ``step_count[0] + step_offset``, of length ``dt`` [s]."""


@wp.func
def time_of(when: StepTime):
    return wp.float64(when.step_count[0] + when.step_offset) * when.dt


def step_time(step_count, step_offset, dt):
    """A :data:`StepTime` of these values."""
    when = StepTime()
    when.step_count, when.step_offset, when.dt = step_count, int(step_offset), float(dt)
    return when


"""The motions of a Model (``polydem.model.Model.motions``), per motion (K,): the unit ``axis``; a cycle's
``amplitude`` [m], angular frequency ``omega`` [rad/s], ``start`` [s], ``period`` [s] and ``count``; each
one's ``kind`` (``MOTION_*``), a ramp's and servo's ``speed`` (a servo's largest) [m/s] and a ramp's
``duration`` [s], and a servo's ``target`` force [N] and ``gain`` [m/(N s)] (these two only where ramps or
servos drive bodies: the kernels' ``travel`` variant reads them); per body (N,) the motion it follows
(``body_motion``, -1: none) and its position at rest (``body_rest``) [m]; the driven bodies of the ramps and
servos by motion (``rows``, (R,)), in ``row_start`` (K+1,) ranges; per plane wall (P,) the motion it follows
(``plane_motion``, -1: none) and its offset at rest (``plane_rest``, n . x [m]); per mesh wall (M,) the motion
it follows (``mesh_motion``) and the translation of its pose at rest (``mesh_rest``) [m]. Plane and mesh
walls follow cycles and ramps only (a servo needs the force on what it drives)."""


@wp.func
def cycle_displacement(
    t: wp.float64, amplitude: wp.float64, omega: wp.float64, start: wp.float64, period: wp.float64, count: int
):
    # (d, v) of the motion at time t: the cycle under way, or rest before, between and after the cycles.
    zero = wp.float64(0.0)
    tau = t - start
    if tau < zero:
        return wp.vec2d(zero, zero)
    k = wp.floor(tau / period)
    if count > 0 and k >= wp.float64(count):
        return wp.vec2d(zero, zero)
    s = tau - k * period
    if s * omega >= wp.float64(2.0 * math.pi):
        return wp.vec2d(zero, zero)
    phase = omega * s
    return wp.vec2d(amplitude * (wp.float64(1.0) - wp.cos(phase)), amplitude * omega * wp.sin(phase))


@wp.func
def ramp_displacement(t: wp.float64, speed: wp.float64, start: wp.float64, duration: wp.float64):
    # (d, v) of a ramp at time t: at rest before start, moving for duration, then holding still.
    zero = wp.float64(0.0)
    tau = t - start
    if tau < zero:
        return wp.vec2d(zero, zero)
    if tau >= duration:
        return wp.vec2d(speed * duration, zero)
    return wp.vec2d(speed * tau, speed)


def make_motion_kernels(scalar, travel=False):
    """The drive kernel for poses in ``scalar`` (wp.float32 or wp.float64): each driven
    row with the index of its motion (-1: not driven) and its position at rest. ``travel``: the
    variant for models with ramps or servos, which takes their (d, v) from ``motion_travel``;
    without, the kind and travel arrays are not read (cycles only)."""
    vec3 = wp.types.vector(3, scalar)
    transform = wp.types.transformation(scalar)

    @wp.func
    def cycle_of(motions: Motions, m: int, t: wp.float64):
        # (d, v) of motion m, a cycle motion, at time t.
        return cycle_displacement(
            t, motions.amplitude[m], motions.omega[m], motions.start[m], motions.period[m], motions.count[m]
        )

    @wp.kernel(enable_backward=False)
    def drive_kernel(
        when: StepTime,
        motions: Motions,
        # The (d, v, F) of the ramps and servos this step (the travel variant only)
        motion_travel: wp.array(dtype=wp.vec3d),
        # Out: the driven bodies' poses and velocities
        body_q: wp.array(dtype=transform),
        body_v: wp.array(dtype=vec3),
    ):
        i = wp.tid()
        m = motions.body_motion[i]
        if m < 0:
            return
        t = time_of(when)
        dv = wp.vec2d()
        if wp.static(travel):
            if motions.kind[m] != MOTION_CYCLE:
                # Set this step by launch_measure_motions, at the same time t.
                tr = motion_travel[m]
                dv = wp.vec2d(tr[0], tr[1])
            else:
                dv = cycle_of(motions, m, t)
        else:
            dv = cycle_of(motions, m, t)
        u = motions.axis[m]
        x = motions.body_rest[i] + u * dv[0]
        body_q[i] = transform(vec3(scalar(x[0]), scalar(x[1]), scalar(x[2])), wp.transform_get_rotation(body_q[i]))
        v = u * dv[1]
        body_v[i] = vec3(scalar(v[0]), scalar(v[1]), scalar(v[2]))

    return drive_kernel


@functools.cache
def make_wall_motion_kernel(scalar):
    """The kernel of :func:`launch_drive_walls` for walls in ``scalar`` (the poses' precision)."""
    vec3 = wp.types.vector(3, scalar)
    transform = wp.types.transformation(scalar)
    Planes = planes_struct(scalar)

    @wp.kernel(enable_backward=False)
    def drive_walls_kernel(
        when: StepTime,
        motions: Motions,
        # Out: the driven planes' offsets and velocities (their normals in), the driven mesh walls' poses and
        # velocities
        planes: Planes,
        mesh_q: wp.array(dtype=transform),
        mesh_v: wp.array(dtype=vec3),
    ):
        j = wp.tid()
        num_planes = motions.plane_motion.shape[0]
        m = int(-1)
        if j < num_planes:
            m = motions.plane_motion[j]
        else:
            m = motions.mesh_motion[j - num_planes]
        if m < 0:
            return
        t = time_of(when)
        dv = wp.vec2d()
        if motions.kind[m] == MOTION_RAMP:
            dv = ramp_displacement(t, motions.speed[m], motions.start[m], motions.duration[m])
        else:
            dv = cycle_displacement(
                t, motions.amplitude[m], motions.omega[m], motions.start[m], motions.period[m], motions.count[m]
            )
        u = motions.axis[m]
        v = u * dv[1]
        if j < num_planes:
            n = planes.normal[j]
            shift = wp.float64(n[0]) * u[0] + wp.float64(n[1]) * u[1] + wp.float64(n[2]) * u[2]
            planes.offset[j] = scalar(motions.plane_rest[j] + shift * dv[0])
            planes.v[j] = vec3(scalar(v[0]), scalar(v[1]), scalar(v[2]))
        else:
            k = j - num_planes
            x = motions.mesh_rest[k] + u * dv[0]
            mesh_q[k] = transform(vec3(scalar(x[0]), scalar(x[1]), scalar(x[2])), wp.transform_get_rotation(mesh_q[k]))
            mesh_v[k] = vec3(scalar(v[0]), scalar(v[1]), scalar(v[2]))

    return drive_walls_kernel


def launch_drive_walls(motions, step_count, step_offset, dt, planes, mesh_q, mesh_v, device=None):
    """Set the offset and velocity of each driven plane wall (``motions.plane_motion`` >= 0, into ``planes``, a
    Planes struct of the Stepper's own offsets and velocities) and the pose and velocity of each driven mesh
    wall (``motions.mesh_motion`` >= 0, into ``mesh_q`` and ``mesh_v``, placeholders of one entry where there
    are none) from its motion at time ``(step_count[0] + step_offset) * dt``: d(t) from the step counter, as
    for the bodies."""
    num = motions.plane_motion.shape[0] + motions.mesh_motion.shape[0]
    kernel = make_wall_motion_kernel(_scalar_of(mesh_q))
    inputs = [step_time(step_count, step_offset, dt), motions]
    wp.launch(kernel, dim=num, inputs=inputs, outputs=[planes, mesh_q, mesh_v], device=device)


_KERNELS = {}


def _kernels(scalar, travel=False):
    key = (wp.types.type_repr(scalar), bool(travel))
    if key not in _KERNELS:
        _KERNELS[key] = make_motion_kernels(scalar, bool(travel))
    return _KERNELS[key]


def _scalar_of(q):
    return wp.float64 if wp.types.types_equal(q.dtype, wp.transformd) else wp.float32


def launch_drive_bodies(motions, step_count, step_offset, dt, body_q, body_v, device=None, *, travel=None):
    """Set the pose and velocity of each driven body (``motions.body_motion`` >= 0) from its motion at time
    ``(step_count[0] + step_offset) * dt``. ``motions``: a :data:`Motions`; ``travel``: (K,) vec3d the (d, v,
    F) of the ramps and servos this step (:func:`launch_measure_motions`), or None for cycles only (the
    kinds are then not read)."""
    kernel = _kernels(_scalar_of(body_q), travel is not None)
    inputs = [step_time(step_count, step_offset, dt), motions, travel]
    wp.launch(kernel, dim=len(body_q), inputs=inputs, outputs=[body_q, body_v], device=device)


@functools.cache
def make_measure_kernels(contact_scalar):
    """The kernels of :func:`launch_measure_motions` for pair forces in ``contact_scalar``."""
    Pairs = pairs_struct(contact_scalar)

    @wp.kernel(enable_backward=False)
    def force_parts_kernel(motions: Motions, pairs: Pairs, parts: wp.array2d(dtype=wp.vec3d)):
        # Lane `lane` of driven row r: every LANES-th of its pairs, the force on the body (on A; B gets -).
        r, lane = wp.tid()
        i = motions.rows[r]
        f = wp.vec3d()
        ra = pairs.ranges_a[i]
        p = ra[0] + lane
        while p < ra[1]:
            f += wp.vec3d(pairs.force[p])
            p += LANES
        rb = pairs.ranges_b[i]
        k = rb[0] + lane
        while k < rb[1]:
            f -= wp.vec3d(pairs.force[pairs.by_b[k]])
            k += LANES
        parts[r, lane] = f

    @wp.kernel(enable_backward=False)
    def update_kernel(
        motions: Motions,
        parts: wp.array2d(dtype=wp.vec3d),
        when: StepTime,
        motion_travel: wp.array(dtype=wp.vec3d),
    ):
        m = wp.tid()
        kind = motions.kind[m]
        if kind == MOTION_CYCLE:
            return
        f = wp.vec3d()
        for r in range(motions.row_start[m], motions.row_start[m + 1]):
            for lane in range(LANES):
                f += parts[r, lane]
        push = -wp.dot(f, motions.axis[m])
        t = time_of(when)
        if kind == MOTION_RAMP:
            dv = ramp_displacement(t, motions.speed[m], motions.start[m], motions.duration[m])
            motion_travel[m] = wp.vec3d(dv[0], dv[1], push)
            return
        v = wp.float64(0.0)
        # The servo moves from start on: in the step that ends at t, if it ends after start.
        if t > motions.start[m]:
            vmax = motions.speed[m]
            v = wp.clamp(motions.gain[m] * (motions.target[m] - push), -vmax, vmax)
        motion_travel[m] = wp.vec3d(motion_travel[m][0] + v * when.dt, v, push)

    return force_parts_kernel, update_kernel


def launch_measure_motions(model, contacts, parts, step_count, step_offset, dt, motion_travel, device=None):
    """Each ramp's and servo's (d, v, F) at time ``(step_count[0] + step_offset) * dt`` into
    ``motion_travel``: F from the pair forces of the force stage just run (``contacts.pairs``), the
    servos' d advanced by one step. ``model``: its ``motions`` (:data:`Motions`: the kinds, axes, starts,
    speeds, durations, targets and gains; ``rows`` (R,) the driven bodies of ramps and servos by motion,
    in ``row_start`` (K+1,) ranges); ``parts``: (R, LANES) vec3d scratch."""
    parts_kernel, update_kernel = make_measure_kernels(scalars(model.precision)[1])
    motions = model.motions
    if len(motions.rows):
        wp.launch(parts_kernel, dim=(len(motions.rows), LANES), inputs=[motions, contacts.pairs, parts], device=device)
    inputs = [motions, parts, step_time(step_count, step_offset, dt)]
    wp.launch(update_kernel, dim=len(motions.kind), inputs=inputs, outputs=[motion_travel], device=device)
