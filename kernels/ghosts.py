"""The ghost bodies of a decomposed run (:mod:`polydem.distributed`): the rows a rank sends of its bodies
that are ghosts elsewhere and writes into its own ghosts after each step, and how far its bodies
have moved since the slabs were cut.

A row is a body's pose (7), velocity (3), angular velocity (3) and damping load (1: float32, whose value the
state's scalar holds exactly) in the state's scalar, read from and written to scalar views of the state's arrays
(``body_q.view(scalar)``: (N, 7), (N, 3), (N, 3)), so that one kernel serves float32 and float64 states. Copies
only, and a maximum: no rounding.
"""

import functools
from typing import Any

import warp as wp
from polydem.kernels.integrate import make_integrator


@wp.func
def copy_value(state: wp.array2d(dtype=Any), i: int, c: int, rows: wp.array2d(dtype=Any), k: int, r: int, unpack: int):
    # One value between the state's row i, column c, and the message row k, column r.
    if unpack != 0:
        state[i, c] = rows[k, r]
    else:
        rows[k, r] = state[i, c]


@wp.kernel(enable_backward=False)
def rows_kernel(
    # The state (scalar views: (n, 7), (n, 3), (n, 3)): in when packing, out when unpacking
    q: wp.array2d(dtype=Any),
    v: wp.array2d(dtype=Any),
    w: wp.array2d(dtype=Any),
    damping: wp.array(dtype=wp.float32),
    index: wp.array(dtype=int),
    # (len(index), 14) rows: out when packing, in when unpacking
    rows: wp.array2d(dtype=Any),
    unpack: int,
):
    k = wp.tid()
    i = index[k]
    for c in range(7):
        copy_value(q, i, c, rows, k, c, unpack)
    for c in range(3):
        copy_value(v, i, c, rows, k, 7 + c, unpack)
        copy_value(w, i, c, rows, k, 10 + c, unpack)
    if unpack != 0:
        damping[i] = wp.float32(rows[k, 13])
    else:
        rows[k, 13] = rows.dtype(damping[i])


@wp.kernel(enable_backward=False)
def moved_kernel(
    q: wp.array2d(dtype=Any),
    axis: int,
    x0: wp.array(dtype=wp.float64),
    mine: wp.array(dtype=int),
    # Out: (1,) the largest move along the axis since the partition [m]
    moved: wp.array(dtype=wp.float64),
):
    i = wp.tid()
    if mine[i] != 0:
        wp.atomic_max(moved, 0, wp.abs(wp.float64(q[i, axis]) - x0[i]))


@functools.cache
def make_step_rows_kernel(scalar):
    """The kernel that writes the rows of bodies as the integrator will leave them at the end of the step (from
    their force, torque and damping load as the force stage left them), without changing the state: the rows a
    decomposed run sends while the rest of its step still runs (``scalar``: the state's)."""
    ig = make_integrator(scalar)

    @wp.kernel(enable_backward=False, module="unique")
    def step_rows_kernel(
        # Model
        model: ig.BodyModel,
        gravity: ig.vec3,
        dt: scalar,
        # State in: the bodies after the force stage (free bodies only), their damping loads for the next step
        bodies: ig.Bodies,
        damping: wp.array(dtype=wp.float32),
        index: wp.array(dtype=int),
        # Out: (len(index), 14) rows
        rows: wp.array2d(dtype=scalar),
    ):
        k = wp.tid()
        i = index[k]
        tf, v, w = ig.free_body_step(model, gravity, dt, i, bodies.q[i], bodies.v[i], bodies.w[i], bodies.f[i],
                                     bodies.t[i])  # fmt: skip
        p = wp.transform_get_translation(tf)
        q = wp.transform_get_rotation(tf)
        for c in range(3):
            rows[k, c] = p[c]
            rows[k, 7 + c] = v[c]
            rows[k, 10 + c] = w[c]
        for c in range(4):
            rows[k, 3 + c] = q[c]
        rows[k, 13] = scalar(damping[i])

    return step_rows_kernel


# ---------------------------------------------------------------------------------------------
# Launch functions
# ---------------------------------------------------------------------------------------------


def launch_pack_rows(
    *, q: wp.array, v: wp.array, w: wp.array, damping: wp.array, index: wp.array, rows: wp.array
) -> None:
    """The rows (len(index), 14) of the bodies ``index`` of the state's scalar views ``q``, ``v``, ``w`` and its
    damping loads ``damping``."""
    wp.launch(rows_kernel, dim=index.shape[0], inputs=[q, v, w, damping, index, rows, 0], device=rows.device)


def launch_unpack_rows(
    *, rows: wp.array, index: wp.array, q: wp.array, v: wp.array, w: wp.array, damping: wp.array
) -> None:
    """Write the received ``rows`` (len(index), 14) into the bodies ``index`` of the scalar views ``q``, ``v``,
    ``w`` and the damping loads ``damping``."""
    wp.launch(rows_kernel, dim=index.shape[0], inputs=[q, v, w, damping, index, rows, 1], device=rows.device)


def launch_largest_move(*, q: wp.array, axis: int, x0: wp.array, mine: wp.array, moved: wp.array) -> None:
    """Raise ``moved`` (1,) float64 to the largest move along ``axis`` [m] of a body flagged in ``mine``
    (N,) since its coordinate ``x0`` (N,) float64 at the partition (``q``: the (N, 7) view of the poses)."""
    wp.launch(moved_kernel, dim=mine.shape[0], inputs=[q, axis, x0, mine], outputs=[moved], device=moved.device)


def launch_step_rows(
    *, model: Any, gravity: Any, dt: float, bodies: Any, damping: wp.array, index: wp.array, rows: wp.array
) -> None:
    """The rows (len(index), 14) of the free bodies ``index`` as the integrator will leave them at the end of this
    step: called after the force stage has written their force, torque and damping load (``model``: the
    bodies' model struct; ``gravity``: three numbers [m/s^2]; ``bodies``: the state's bodies struct). The
    same bits as :func:`launch_pack_rows` after the step (the integrator's own function)."""
    scalar = rows.dtype
    ig = make_integrator(scalar)
    g = ig.vec3(*[scalar(float(x)) for x in gravity])
    wp.launch(
        make_step_rows_kernel(scalar),
        dim=index.shape[0],
        inputs=[model, g, scalar(float(dt)), bodies, damping, index],
        outputs=[rows],
        device=rows.device,
    )
