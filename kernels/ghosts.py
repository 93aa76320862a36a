"""The ghost bodies of a decomposed run (:mod:`polydem.distributed`): the rows a rank sends of its bodies
that are ghosts elsewhere and writes into its own ghosts after each step, and how far its bodies
have moved since the slabs were cut.

A row is a body's pose (7), velocity (3) and angular velocity (3) in the state's scalar, read from and
written to scalar views of the state's arrays (``body_q.view(scalar)``: (N, 7), (N, 3), (N, 3)), so
that one kernel serves float32 and float64 states. Copies only, and a maximum: no rounding.
"""

from typing import Any

import warp as wp


@wp.kernel(enable_backward=False)
def pack_kernel(
    # State in (scalar views: (n, 7), (n, 3), (n, 3))
    q: wp.array2d(dtype=Any),
    v: wp.array2d(dtype=Any),
    w: wp.array2d(dtype=Any),
    index: wp.array(dtype=int),
    # Out: (len(index), 13) rows to send
    rows: wp.array2d(dtype=Any),
):
    k = wp.tid()
    i = index[k]
    for c in range(7):
        rows[k, c] = q[i, c]
    for c in range(3):
        rows[k, 7 + c] = v[i, c]
        rows[k, 10 + c] = w[i, c]


@wp.kernel(enable_backward=False)
def unpack_kernel(
    rows: wp.array2d(dtype=Any),
    index: wp.array(dtype=int),
    # Out: the ghosts' rows of the state (scalar views)
    q: wp.array2d(dtype=Any),
    v: wp.array2d(dtype=Any),
    w: wp.array2d(dtype=Any),
):
    k = wp.tid()
    i = index[k]
    for c in range(7):
        q[i, c] = rows[k, c]
    for c in range(3):
        v[i, c] = rows[k, 7 + c]
        w[i, c] = rows[k, 10 + c]


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


# ---------------------------------------------------------------------------------------------
# Launch functions
# ---------------------------------------------------------------------------------------------


def launch_pack_rows(*, q: wp.array, v: wp.array, w: wp.array, index: wp.array, rows: wp.array) -> None:
    """The rows (len(index), 13) of the bodies ``index`` of the state's scalar views ``q``, ``v``, ``w``."""
    wp.launch(pack_kernel, dim=index.shape[0], inputs=[q, v, w, index], outputs=[rows], device=rows.device)


def launch_unpack_rows(*, rows: wp.array, index: wp.array, q: wp.array, v: wp.array, w: wp.array) -> None:
    """Write the received ``rows`` (len(index), 13) into the bodies ``index`` of the scalar views ``q``, ``v``,
    ``w``."""
    wp.launch(unpack_kernel, dim=index.shape[0], inputs=[rows, index], outputs=[q, v, w], device=rows.device)


def launch_largest_move(*, q: wp.array, axis: int, x0: wp.array, mine: wp.array, moved: wp.array) -> None:
    """Raise ``moved`` (1,) float64 to the largest move along ``axis`` [m] of a body flagged in ``mine``
    (N,) since its coordinate ``x0`` (N,) float64 at the partition (``q``: the (N, 7) view of the poses)."""
    wp.launch(moved_kernel, dim=mine.shape[0], inputs=[q, axis, x0, mine], outputs=[moved], device=moved.device)
