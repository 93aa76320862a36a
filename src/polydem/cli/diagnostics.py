"""Numbers about a state that the run records and its summary reports: the settled region of a
pile (packing fraction, coordination number), the overlaps relative to the bodies' volumes and the
penetration depths relative to their sizes."""

from __future__ import annotations

import math

import numpy as np

from polydem.scene.bodies import BodyKind

__all__ = [
    "SETTLED_MARGIN",
    "SETTLED_PERCENTILE",
    "body_volumes",
    "relative_depths",
    "relative_overlaps",
    "settled_region",
]

SETTLED_PERCENTILE = 80.0
"""The settled region reaches up to this percentile of the free bodies' centre heights."""

SETTLED_MARGIN = 2.0
"""The settled region keeps this many mean body diameters from the sides of the free bodies' box."""


def body_volumes(scene) -> np.ndarray:
    vol = np.array([scene.shapes[name].volume for name in scene.shape_names], dtype=np.float64)
    return vol[np.asarray(scene.body_shape)]


def _smaller_volume(contacts, volumes) -> np.ndarray:
    """The volume of the smaller body of each contact (the body's own for walls)."""
    b = contacts["body_b"]
    return np.minimum(volumes[contacts["body_a"]], np.where(b >= 0, volumes[np.maximum(b, 0)], np.inf))


def relative_overlaps(contacts, volumes) -> np.ndarray:
    """Overlap volume of each contact over the smaller body's volume (the body's own for walls)."""
    return contacts["volume"] / _smaller_volume(contacts, volumes)


def relative_depths(contacts, volumes) -> np.ndarray:
    """Penetration depth of each contact over the smaller body's size, the cube root of its volume
    (the edge of a cube; the body's own for walls)."""
    return contacts["depth"] / np.cbrt(_smaller_volume(contacts, volumes))


def _perpendicular(up: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Two horizontal unit axes (x and y for up = z)."""
    axis = np.eye(3)[int(np.argmin(np.abs(up)))]
    e1 = axis - up * float(axis @ up)
    e1 /= np.linalg.norm(e1)
    return e1, np.cross(up, e1)


def settled_region(scene, state, contacts) -> dict:
    """Packing fraction and coordination number of the settled part of a pile.

    Definition (heights along minus gravity, +z when there is none; "horizontal" perpendicular to it):

    * D is the mean volume-equivalent diameter (6 V / pi)^(1/3) of the free bodies;
    * the region is a box: horizontally, the bounding box of the free bodies' centres shrunk by
      ``SETTLED_MARGIN`` (2) D on every side (away from the side walls); vertically, from the lowest
      point of any free body (the floor) up to the ``SETTLED_PERCENTILE`` (80th) percentile of the
      free bodies' centre heights (below the loose top layer);
    * the bodies in the region are the free bodies whose centres lie in it;
    * packing fraction = the sum of their volumes / the volume of the box (bodies cut by the top
      and side faces count whole or not at all, which cancels on average);
    * coordination number = the mean number of contacts of a body in the region, counting every
      contact (with a free, fixed or kinematic body, or a wall plane); ``coordination_number_free``
      counts only the contacts with other free bodies.

    Returns a dict with ``bodies`` (in the region), ``packing_fraction``, ``coordination_number``,
    ``coordination_number_free``, ``diameter`` (D [m]), ``lower`` and ``upper`` (the box: horizontal
    axis 1, horizontal axis 2, height [m]); the three values are None, with a ``note``, when the
    region is empty (a bed narrower than about 4 D, or too few bodies).
    """
    from polydem.quaternions import quat_to_matrix

    kind = np.asarray(scene.body_kind)
    free = kind == BodyKind.FREE
    out = {
        "bodies": 0,
        "packing_fraction": None,
        "coordination_number": None,
        "coordination_number_free": None,
    }
    if not free.any():
        out["note"] = "no free bodies"
        return out
    g = np.asarray(scene.gravity, dtype=np.float64)
    up = -g / np.linalg.norm(g) if np.linalg.norm(g) > 0.0 else np.array([0.0, 0.0, 1.0])
    e1, e2 = _perpendicular(up)
    pos = np.asarray(state["body_position"], dtype=np.float64)
    quat = np.asarray(state["body_orientation"], dtype=np.float64)
    volumes = body_volumes(scene)
    body_shape = np.asarray(scene.body_shape)
    idx = np.flatnonzero(free)
    diameter = float(np.mean((6.0 * volumes[idx] / math.pi) ** (1.0 / 3.0)))
    h, u, w = pos[idx] @ up, pos[idx] @ e1, pos[idx] @ e2
    floor = np.inf
    for s, name in enumerate(scene.shape_names):
        verts = np.asarray(scene.shapes[name].vertices, dtype=np.float64)
        members = idx[body_shape[idx] == s]
        for k in range(0, len(members), 65536):
            rows = members[k : k + 65536]
            up_body = np.einsum("nji,j->ni", quat_to_matrix(quat[rows]), up)  # R^T up
            lowest = pos[rows] @ up + (up_body @ verts.T).min(axis=1)
            floor = min(floor, float(lowest.min()))
    top = float(np.percentile(h, SETTLED_PERCENTILE))
    margin = SETTLED_MARGIN * diameter
    lower = np.array([u.min() + margin, w.min() + margin, floor])
    upper = np.array([u.max() - margin, w.max() - margin, top])
    out.update(diameter=diameter, lower=lower.tolist(), upper=upper.tolist())
    if not np.all(upper > lower):
        out["note"] = (
            f"no settled region: the free bodies span less than {2 * SETTLED_MARGIN:g} mean diameters "
            "horizontally (or do not form a bed)"
        )
        return out
    inside = (u >= lower[0]) & (u <= upper[0]) & (w >= lower[1]) & (w <= upper[1]) & (h <= upper[2])
    members = idx[inside]
    out["bodies"] = int(len(members))
    if not len(members):
        out["note"] = "no free body has its centre in the settled region"
        return out
    n = len(kind)
    a, b = contacts["body_a"], contacts["body_b"]
    count = np.bincount(a, minlength=n) + np.bincount(b[b >= 0], minlength=n)
    both = (b >= 0) & free[a] & free[np.maximum(b, 0)]
    count_free = np.bincount(a[both], minlength=n) + np.bincount(b[both], minlength=n)
    out["packing_fraction"] = float(volumes[members].sum() / np.prod(upper - lower))
    out["coordination_number"] = float(count[members].mean())
    out["coordination_number_free"] = float(count_free[members].mean())
    return out
