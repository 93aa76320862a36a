"""Unit quaternions ``[x, y, z, w]`` (Warp's order) in float64 numpy, vectorised over leading axes.

The one home of polydem's host-side rotation maths. scipy's ``Rotation`` computes the same
rotations but rounds differently in the last bits (it normalises its inputs and orders the
products otherwise), and scene poses must stay bit for bit what they were.
"""

from __future__ import annotations

import math

import numpy as np

__all__ = ["quat_conjugate", "quat_from_matrices", "quat_from_matrix", "quat_multiply", "quat_rotate", "quat_to_matrix"]


def quat_multiply(a, b):
    """Hamilton product of (..., 4) xyzw quaternions."""
    ax, ay, az, aw = np.moveaxis(np.asarray(a, dtype=np.float64), -1, 0)
    bx, by, bz, bw = np.moveaxis(np.asarray(b, dtype=np.float64), -1, 0)
    return np.stack(
        [
            aw * bx + ax * bw + ay * bz - az * by,
            aw * by - ax * bz + ay * bw + az * bx,
            aw * bz + ax * by - ay * bx + az * bw,
            aw * bw - ax * bx - ay * by - az * bz,
        ],
        axis=-1,
    )


def quat_conjugate(q):
    q = np.array(q, dtype=np.float64)
    q[..., :3] *= -1.0
    return q


def quat_rotate(q, v):
    """Rotate (..., 3) vectors by (..., 4) unit quaternions."""
    q = np.asarray(q, dtype=np.float64)
    v = np.asarray(v, dtype=np.float64)
    u, w = q[..., :3], q[..., 3:4]
    t = 2.0 * np.cross(u, v)
    return v + w * t + np.cross(u, t)


def quat_from_matrix(r) -> np.ndarray:
    """Unit xyzw quaternion of a 3x3 rotation matrix (Shepperd's method)."""
    r = np.asarray(r, dtype=np.float64)
    tr = r[0, 0] + r[1, 1] + r[2, 2]
    if tr > 0.0:
        s = 2.0 * math.sqrt(tr + 1.0)
        q = [(r[2, 1] - r[1, 2]) / s, (r[0, 2] - r[2, 0]) / s, (r[1, 0] - r[0, 1]) / s, 0.25 * s]
    elif r[0, 0] > r[1, 1] and r[0, 0] > r[2, 2]:
        s = 2.0 * math.sqrt(1.0 + r[0, 0] - r[1, 1] - r[2, 2])
        q = [0.25 * s, (r[0, 1] + r[1, 0]) / s, (r[0, 2] + r[2, 0]) / s, (r[2, 1] - r[1, 2]) / s]
    elif r[1, 1] > r[2, 2]:
        s = 2.0 * math.sqrt(1.0 + r[1, 1] - r[0, 0] - r[2, 2])
        q = [(r[0, 1] + r[1, 0]) / s, 0.25 * s, (r[1, 2] + r[2, 1]) / s, (r[0, 2] - r[2, 0]) / s]
    else:
        s = 2.0 * math.sqrt(1.0 + r[2, 2] - r[0, 0] - r[1, 1])
        q = [(r[0, 2] + r[2, 0]) / s, (r[1, 2] + r[2, 1]) / s, 0.25 * s, (r[1, 0] - r[0, 1]) / s]
    q = np.array(q)
    return q / np.linalg.norm(q)


def quat_from_matrices(r) -> np.ndarray:
    """(..., 4) unit xyzw quaternions of (..., 3, 3) rotation matrices: :func:`quat_from_matrix` of each, the
    same bits (its branches as masks, the same operations in the same order, and its norm from the same dot
    product: ``np.vecdot`` runs numpy's dot of each row, which ``np.linalg.norm`` of one quaternion runs)."""
    r = np.asarray(r, dtype=np.float64)
    shape = r.shape[:-2]
    r = r.reshape(-1, 3, 3)
    r00, r01, r02 = r[:, 0, 0], r[:, 0, 1], r[:, 0, 2]
    r10, r11, r12 = r[:, 1, 0], r[:, 1, 1], r[:, 1, 2]
    r20, r21, r22 = r[:, 2, 0], r[:, 2, 1], r[:, 2, 2]
    tr = r00 + r11 + r22
    case = np.full(len(r), 3)
    case[r11 > r22] = 2
    case[(r00 > r11) & (r00 > r22)] = 1
    case[tr > 0.0] = 0
    q = np.empty((len(r), 4))

    def root(x):  # 2 sqrt(x), refused as math.sqrt and the float division refuse it (not a rotation)
        if np.any(x < 0.0):
            raise ValueError("math domain error")
        s = 2.0 * np.sqrt(x)
        if np.any(s == 0.0):
            raise ZeroDivisionError("float division by zero")
        return s

    k = np.flatnonzero(case == 0)
    s = root(tr[k] + 1.0)
    q[k] = np.column_stack([(r21[k] - r12[k]) / s, (r02[k] - r20[k]) / s, (r10[k] - r01[k]) / s, 0.25 * s])
    k = np.flatnonzero(case == 1)
    s = root(1.0 + r00[k] - r11[k] - r22[k])
    q[k] = np.column_stack([0.25 * s, (r01[k] + r10[k]) / s, (r02[k] + r20[k]) / s, (r21[k] - r12[k]) / s])
    k = np.flatnonzero(case == 2)
    s = root(1.0 + r11[k] - r00[k] - r22[k])
    q[k] = np.column_stack([(r01[k] + r10[k]) / s, 0.25 * s, (r12[k] + r21[k]) / s, (r02[k] - r20[k]) / s])
    k = np.flatnonzero(case == 3)
    s = root(1.0 + r22[k] - r00[k] - r11[k])
    q[k] = np.column_stack([(r02[k] + r20[k]) / s, (r12[k] + r21[k]) / s, 0.25 * s, (r10[k] - r01[k]) / s])
    q /= np.sqrt(np.vecdot(q, q))[:, None]
    return q.reshape(*shape, 4)


def quat_to_matrix(q) -> np.ndarray:
    """(..., 3, 3) rotation matrices of (..., 4) unit xyzw quaternions."""
    q = np.asarray(q, dtype=np.float64)
    x, y, z, w = np.moveaxis(q, -1, 0)
    return np.stack(
        [
            np.stack([1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)], axis=-1),
            np.stack([2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)], axis=-1),
            np.stack([2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)], axis=-1),
        ],
        axis=-2,
    )
