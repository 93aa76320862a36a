"""The memory a picture of :mod:`polydem.render` takes, and whether this machine has it.

Plain Python (no numpy, no Warp): ``polydem run`` checks ``--picture-size`` while it parses its
options, before anything is imported or run, and :func:`polydem.render.render` checks again, with
the device it renders on, before it allocates anything.

What a picture of W x H pixels cast with S x S rays per pixel (R = W H S^2 rays) allocates:

* the ray caster's outputs (``kernels/raycast.py``, ``launch_raycast``), on the rendering device:
  colour (vec3 float32, 12 bytes), depth (float32, 4) and hit (int32, 4) per ray;
  :data:`RAYCAST_BYTES_PER_RAY`. On the CPU they are host memory.
* :func:`~polydem.render.render`, on the host: on a GPU the colour comes back (12 bytes per ray);
  then, per pixel of the picture, the supersampled mean (float32 RGB), its 8-bit copy and the
  temporaries of the conversion, and Pillow's copy for the PNG: :data:`PICTURE_BYTES_PER_PIXEL`.
* :func:`~polydem.render.render_layers`, on the host, per ray: every layer copied back from a GPU
  (20), the depth in float64 (8), the mask of missed rays (1), the 8-bit image and its
  temporaries (15) and the hits mapped to compound bodies (21): :data:`LAYERS_BYTES_PER_RAY`.

The bounding-volume trees, the bodies and the walls take memory in proportion to the scene, not
to the picture, and are left out: a scene that could be simulated has room for them.

These are upper bounds, compared with the whole memory available: arrays freed along the way
overlap less than the sum says, and on the CPU the peaks measured were 45% (4000 x 3000),
89% (1000 x 750, supersample 4) and 51% (``render_layers``, 3000 x 2000) of them. The rest is the
headroom the process and the other programs need.
"""

from __future__ import annotations

import os

__all__ = [
    "LAYERS_BYTES_PER_RAY",
    "PICTURE_BYTES_PER_PIXEL",
    "RAYCAST_BYTES_PER_RAY",
    "PictureSizeError",
    "check_picture_size",
    "host_memory_available",
    "picture_bytes",
]

RAYCAST_BYTES_PER_RAY = 12 + 4 + 4
"""Bytes per ray of the ray caster's colour, depth and hit arrays."""

COLOR_BYTES_PER_RAY = 12
"""Bytes per ray of the colour copied back from a GPU by :func:`~polydem.render.render`."""

PICTURE_BYTES_PER_PIXEL = 12 + 12 + 3 + 4 + 9
"""Bytes per pixel of the picture itself: the mean colour, its temporary, the 8-bit image,
Pillow's copy, and room for the PNG encoder's rows."""

LAYERS_BYTES_PER_RAY = 20 + 8 + 1 + 15 + 21
"""Bytes per ray that :func:`~polydem.render.render_layers` adds on the host to the ray caster's."""

MAX_SIDE = (2**31 - 1) // 12
"""Longest side [rays]: Warp keeps an array's strides in bytes as int32, 12 bytes per colour."""


class PictureSizeError(ValueError):
    """A picture too large for the memory of this machine (or of its GPU).

    Attributes: ``width``, ``height``, ``supersample``, ``needed`` (bytes), ``available``
    (bytes), ``where`` ("memory" or "GPU memory of cuda:N"), ``largest`` ((width, height) of
    the largest picture of this aspect ratio that fits at this supersampling, or None when
    not even 1 x 1 does) and ``largest_supersample`` (the most rays per pixel side that fit at
    this size; 0 when none does).
    """

    def __init__(self, width, height, supersample, needed, available, where, largest, largest_supersample):
        self.width, self.height, self.supersample = width, height, supersample
        self.needed, self.available, self.where = needed, available, where
        self.largest, self.largest_supersample = largest, largest_supersample
        rays = f" with {supersample} x {supersample} rays per pixel" if supersample > 1 else ""
        if needed > available:
            fits = f"at most about {largest[0]} x {largest[1]} fits" if largest else "not even 1 x 1 fits"
            why = f"needs about {_size(needed)} of {where}, more than the {_size(available)} available ({fits})"
        else:
            why = f"has a side over {MAX_SIDE} rays, the most a Warp array can hold"
        super().__init__(f"a {width} x {height} picture{rays} {why}")


def _size(n: float) -> str:
    for unit, scale in (("TB", 1e12), ("GB", 1e9), ("MB", 1e6)):
        if n >= scale:
            return f"{n / scale:.3g} {unit}"
    return f"{n / 1e3:.3g} kB"


def picture_bytes(width: int, height: int, supersample: int = 1, *, gpu: bool = False, layers: bool = False):
    """(host bytes, GPU bytes) of a ``width`` x ``height`` picture cast with ``supersample``^2 rays
    per pixel on a GPU (``gpu``) or the CPU; ``layers``: :func:`~polydem.render.render_layers`
    (every layer), else :func:`~polydem.render.render` (the image)."""
    pixels = int(width) * int(height)
    rays = pixels * int(supersample) ** 2
    device = RAYCAST_BYTES_PER_RAY * rays if gpu else 0
    host = 0 if gpu else RAYCAST_BYTES_PER_RAY * rays
    if layers:
        host += LAYERS_BYTES_PER_RAY * rays
    else:
        host += (COLOR_BYTES_PER_RAY * rays if gpu else 0) + PICTURE_BYTES_PER_PIXEL * pixels
    return host, device


def _meminfo_available() -> int | None:
    """MemAvailable of /proc/meminfo [bytes] (Linux): free memory plus what the page cache gives back."""
    try:
        with open("/proc/meminfo") as fh:
            for line in fh:
                if line.startswith("MemAvailable:"):
                    return int(line.split()[1]) * 1024
    except (OSError, ValueError, IndexError):
        pass
    return None


def _cgroup_room() -> int | None:
    """What a cgroup v2 memory limit leaves this process (a container's limit), or None without one."""
    try:
        with open("/sys/fs/cgroup/memory.max") as fh:
            limit = fh.read().strip()
        if limit == "max":
            return None
        with open("/sys/fs/cgroup/memory.current") as fh:
            used = int(fh.read().strip())
        return max(int(limit) - used, 0)
    except (OSError, ValueError):
        return None


def host_memory_available() -> int | None:
    """Bytes of host memory a picture can take now: the memory available (Linux's MemAvailable,
    else the physical memory), within a container's limit; None where neither can be read."""
    room = _meminfo_available()
    if room is None:
        try:
            room = os.sysconf("SC_PHYS_PAGES") * os.sysconf("SC_PAGE_SIZE")
        except (AttributeError, OSError, ValueError):
            room = None
    limit = _cgroup_room()
    if limit is not None:
        room = limit if room is None else min(room, limit)
    return room


def check_picture_size(
    width: int,
    height: int,
    supersample: int = 1,
    *,
    gpu: bool = False,
    layers: bool = False,
    host_available: int | None = None,
    gpu_available: int | None = None,
    gpu_name: str = "the GPU",
) -> None:
    """PictureSizeError unless a picture fits (see :func:`picture_bytes`): its host bytes within
    ``host_available`` (default :func:`host_memory_available`), its GPU bytes within
    ``gpu_available`` (None: not checked), and no side of the supersampled picture over
    :data:`MAX_SIDE`."""
    w, h, s = int(width), int(height), int(supersample)
    if host_available is None:
        host_available = host_memory_available()
    limits = []
    if host_available is not None:
        limits.append((0, host_available, "memory"))
    if gpu and gpu_available is not None:
        limits.append((1, gpu_available, f"GPU memory of {gpu_name}"))
    need = picture_bytes(w, h, s, gpu=gpu, layers=layers)
    for k, available, where in limits:
        if need[k] > available:
            raise PictureSizeError(w, h, s, need[k], available, where, *_largest(w, h, s, k, available, gpu, layers))
    if max(w, h) * s > MAX_SIDE:
        raise PictureSizeError(w, h, s, need[0], max(need[0], 1), "memory", *_largest(w, h, s, 0, 0, gpu, layers))


def _largest(w, h, s, k, available, gpu, layers):
    """(the largest (width, height) of this aspect ratio that fits at supersample ``s``, or None;
    the largest supersample that fits at w x h, 0 for none)."""

    def fits(ww, hh, ss):
        return picture_bytes(ww, hh, ss, gpu=gpu, layers=layers)[k] <= available and max(ww, hh) * ss <= MAX_SIDE

    def most(ok, high):
        """The largest x in [0, high] with ok(x) (ok(0) holds, ok falls with x)."""
        low = 0
        while low < high:
            mid = (low + high + 1) // 2
            low, high = (mid, high) if ok(mid) else (low, mid - 1)
        return low

    # Scale both sides by f / 2^20 of the picture's: the largest f that fits keeps the aspect ratio.
    f = most(lambda f: fits(max(w * f >> 20, 1), max(h * f >> 20, 1), s), 1 << 20)
    largest = (max(w * f >> 20, 1), max(h * f >> 20, 1)) if fits(max(w * f >> 20, 1), max(h * f >> 20, 1), s) else None
    return largest, most(lambda ss: ss == 0 or fits(w, h, ss), s)
