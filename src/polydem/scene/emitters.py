"""Emitters: many bodies placed without overlaps on a grid of cells in a box region."""

from __future__ import annotations

import math

import numpy as np

from polydem.compound import expand_bodies
from polydem.quaternions import quat_rotate, quat_to_matrix
from polydem.scene import bodies as scene_bodies  # MAX_BODIES read at call time: one setting for both checks
from polydem.scene.bodies import BODY, KIND_FIXED, KINDS, append_bodies
from polydem.scene.errors import SceneError
from polydem.scene.schema import REQUIRED, SPEED, SPEED_WHY, Key, Table
from polydem.scene.shape_specs import scaled_spec
from polydem.scene.values import F32_HIGH, RADIUS_HIGH, RADIUS_LOW, as_integer, read_number, read_table, typename

ORIENTATIONS = ("random", "aligned")
"""Emitter orientations: uniformly random, or every body with its input axes along the world axes."""

FILLS = ("bottom", "random")
"""Emitter fill orders: the lowest cells first (against gravity), or cells anywhere in the region."""

_REGION_HINT = "region = {min = [x0, y0, z0], max = [x1, y1, z1]} in m"
_LOGNORMAL_HINT = "scale_lognormal = {mean = 1.0, sigma = 0.2}: the mean size factor and the spread of its logarithm"

REGION = Table(
    "region",
    (
        Key("min", "vector", unit="m", default=REQUIRED, hint=_REGION_HINT),
        Key("max", "vector", unit="m", default=REQUIRED, hint=_REGION_HINT),
    ),
)
"""An emitter's ``region = {min = [..], max = [..]}``."""

LOGNORMAL = Table(
    "scale_lognormal",
    (
        Key("mean", range="> 0", default=REQUIRED, hint=_LOGNORMAL_HINT, about="mean size factor"),
        Key(
            "sigma",
            range=">= 0 and <= 2",
            why=" (factors from e^-6 to e^6 times the median)",
            default=REQUIRED,
            hint=_LOGNORMAL_HINT,
            about="standard deviation of ln(factor)",
        ),
    ),
)
"""An emitter's ``scale_lognormal = {mean = m, sigma = s}``."""

EMITTER = Table(
    "[[emitters]]",
    (
        Key(
            "shape",
            "any",
            default=REQUIRED,
            hint="a shape name, a list of names, or a table of weights such as {cube = 2, rock = 1}",
        ),
        Key("weights", "any"),
        Key("material", "any", default=REQUIRED, hint="a material name"),
        Key(
            "count",
            "integer",
            range=">= 1",
            default=REQUIRED,
            hint="number of bodies, an integer >= 1",
            about="number of bodies to place",
        ),
        Key("region", "any", unit="m", default=REQUIRED, hint="the box to fill: " + _REGION_HINT),
        Key("orientation", "choice", choices=ORIENTATIONS, what="orientation", default="random"),
        Key("seed", "integer", range=">= 0", default=0),
        Key("velocity", "vector", unit="m/s", range=SPEED, why=SPEED_WHY, default=(0.0, 0.0, 0.0)),
        Key(
            "velocity_jitter",
            unit="m/s",
            range=f">= 0 and <= {F32_HIGH:.3g}",
            why=SPEED_WHY,
            default=0.0,
            hint="in m/s",
        ),
        Key("scale", range="> 0", hint="size factor of the shapes"),
        Key("scale_range", "vector", size=2, label="[lo, hi]"),
        Key("scale_lognormal", "any"),
        Key("scale_bins", "integer", range="[1, 64]", default=8),
        Key("kind", "choice", choices=KINDS, what="body kind", default=BODY.defaults["kind"]),
        Key(
            "spacing",
            range=">= 1",
            why=" (narrower cells would let bounding spheres overlap)",
            default=1.1,
            hint="cell side over the largest bounding diameter",
        ),
        Key("jitter", range="[0, 1]", why=" (a fraction of each body's free room)", default=0.9, about=""),
        Key("fill", "choice", choices=FILLS, what="fill order", default="bottom"),
    ),
)
"""An ``[[emitters]]`` table: the arguments of :meth:`Scene.emit`."""

_MAX_EMITTER_CELLS = 20_000_000  # grid cells an emitter may scan (random fill) or hold in one layer
_EMITTER_CHUNK = 1 << 20  # grid cells tested at a time
_MAX_GRID_CELLS = 2.0**62  # cells of a grid filled from the bottom: its indices are int64
_PAIR_BATCH = 1 << 20  # (obstacle, cell) pairs tested at a time


def _region(region, key, file) -> tuple[np.ndarray, np.ndarray]:
    """``(min, max)`` corners of an emitter region given as {min = [..], max = [..]} or a pair."""
    if isinstance(region, dict):
        REGION.check(region, key, file)
    elif isinstance(region, list | tuple) and len(region) == 2:
        region = {"min": region[0], "max": region[1]}
    else:
        raise SceneError(f"expected a box, {_REGION_HINT}, got {typename(region)}", key, file)
    corners = REGION.read(region, key, file)
    lo, hi = corners["min"], corners["max"]
    bad = np.flatnonzero(hi <= lo)
    if bad.size:
        ax = int(bad[0])
        raise SceneError(
            f"max must exceed min along every axis, but along {'xyz'[ax]} min = {lo[ax]:g} and max = {hi[ax]:g} m",
            f"{key}.max",
            file,
        )
    return lo, hi


def _largest_remainder(count: int, frac: np.ndarray) -> np.ndarray:
    """Integer counts summing to ``count`` in the proportions ``frac`` (largest remainders get the rest)."""
    raw = count * frac
    out = np.floor(raw).astype(np.int64)
    rest = count - int(out.sum())
    order = np.lexsort((np.arange(len(frac)), -(raw - out)))
    out[order[:rest]] += 1
    return out


def _scale_sampler(scale, scale_range, scale_lognormal, bins: int, key: str, file):
    """A function ``(rng, n) -> (bin index per body, factor per bin)`` for an emitter's sizes, and the key of the
    distribution (None for none: the factor 1)."""
    given = [
        k
        for k, v in (("scale", scale), ("scale_range", scale_range), ("scale_lognormal", scale_lognormal))
        if v is not None
    ]
    if len(given) > 1:
        raise SceneError(
            f"give one size distribution: scale, scale_range or scale_lognormal, not both {given[0]} and {given[1]}",
            f"{key}.{given[1]}",
            file,
        )

    def single(value):
        return lambda rng, n: (np.zeros(n, dtype=np.int64), np.array([value]))

    if scale_range is not None:
        lo, hi = EMITTER["scale_range"].read(scale_range, f"{key}.scale_range", file)
        if lo <= 0.0 or hi < lo:
            raise SceneError(f"expected 0 < lo <= hi (size factors), got [{lo:g}, {hi:g}]", f"{key}.scale_range", file)
        if hi == lo:
            return single(float(lo)), f"{key}.scale_range"
        values = lo + (np.arange(bins) + 0.5) * (hi - lo) / bins

        def uniform(rng, n):
            u = rng.uniform(lo, hi, size=n)
            return np.clip(np.floor((u - lo) / (hi - lo) * bins).astype(np.int64), 0, bins - 1), values

        return uniform, f"{key}.scale_range"
    if scale_lognormal is not None:
        lk = f"{key}.scale_lognormal"
        if isinstance(scale_lognormal, list | tuple) and len(scale_lognormal) == 2:
            scale_lognormal = {"mean": scale_lognormal[0], "sigma": scale_lognormal[1]}
        table = read_table(scale_lognormal, lk, file, what=f"a table, {_LOGNORMAL_HINT}")
        LOGNORMAL.check(table, lk, file)
        mean, sigma = LOGNORMAL.read(table, lk, file).values()
        if sigma == 0.0:
            return single(mean), lk
        mu = math.log(mean) - 0.5 * sigma * sigma
        a, width = mu - 3.0 * sigma, 6.0 * sigma
        values = np.exp(a + (np.arange(bins) + 0.5) * width / bins)

        def lognormal(rng, n):
            x = rng.normal(mu, sigma, size=n)
            return np.clip(np.floor((x - a) / width * bins).astype(np.int64), 0, bins - 1), values

        return lognormal, lk
    if scale is None:
        return single(1.0), None
    return single(EMITTER["scale"].read(scale, f"{key}.scale", file)), f"{key}.scale"


def _cell_index(layer, m, k, ax_a, ax_b, nb, nk, ascending) -> np.ndarray:
    """(N, 3) grid indices of cells given by layer (counted against gravity) and index in the layer."""
    gi = np.empty((len(layer), 3), dtype=np.int64)
    gi[:, k] = layer if ascending else nk - 1 - layer
    gi[:, ax_a] = m // nb
    gi[:, ax_b] = m % nb
    return gi


class _Obstacles:
    """What an emitter's grid cells must keep clear of: plane walls, the scene's bodies, drums, mesh walls.

    A cell (a cube of side ``cell``) is blocked when it reaches behind a plane, when it is not
    separated from a body by one of the body's face planes (conservative near edges and corners),
    or when it lies beside a drum (within its axial span) but not wholly inside it. A body in a free
    cell therefore touches none of them.
    """

    def __init__(self, scene, grid_lo, grid_hi, cell):
        self.origin = grid_lo
        self.n = np.rint((grid_hi - grid_lo) / cell).astype(np.int64)
        self.cell = cell
        self.h = 0.5 * cell
        self.tol = 1e-9 * cell
        planes = scene.planes
        self.plane_n = np.array([p.normal for p in planes], dtype=np.float64).reshape(-1, 3)
        self.plane_e = np.array([np.dot(p.normal, p.point) for p in planes], dtype=np.float64)
        self.body = np.zeros(0, dtype=np.int64)
        if scene.num_bodies:
            # Compound grains are obstacles part by part (the tests below take convex shapes).
            self.shapes, shape, pos, quat, _ = expand_bodies(
                list(scene.shapes.values()), scene.body_shape, scene.body_position, scene.body_orientation
            )
            radius = np.array([s.radius for s in self.shapes])[shape]
            d = pos - np.clip(pos, grid_lo, grid_hi)
            self.body = np.flatnonzero(np.einsum("ij,ij->i", d, d) < radius * radius)
            self.pos = pos[self.body]
            self.rad = radius[self.body]
            self.shape = shape[self.body]
            self.rot = quat_to_matrix(quat[self.body])
        self.mesh_planes = []
        from polydem.meshwall import MeshWallError, build_cells

        for wall, key in zip(scene.mesh_walls, scene.mesh_wall_keys, strict=True):
            depth = wall.thickness if wall.thickness is not None else cell
            try:
                cells = build_cells(
                    wall.vertices, wall.triangles, depth, label=f"mesh wall {key} ({wall.source})"
                ).cells
            except MeshWallError as exc:
                # The emitter places its bodies before the checks run: the same one-line refusal as theirs.
                raise scene.error(str(exc), key) from None
            for c in cells:
                off = c.face_offsets + c.face_normals @ c.center
                self.mesh_planes.append((c.center, c.radius, c.face_normals, off, c.vertices + c.center))
        self.drums = []
        reach = self.h * math.sqrt(3.0)
        for drum in scene.drums:
            u, e = drum.interior_planes()
            axial = 0.5 * drum.length + (drum.thickness if drum.caps else 0.0) + reach
            self.drums.append((np.asarray(drum.center), np.asarray(drum.axis), axial, u, e))

    def blocked(self, centres, krange, k, local_of) -> np.ndarray:
        """Which of the cells at ``centres`` are blocked; ``krange`` bounds their grid index along
        axis ``k`` and ``local_of`` maps (M, 3) grid indices to positions in ``centres``."""
        h, tol = self.h, self.tol
        out = np.zeros(len(centres), dtype=bool)
        for nrm, e in zip(self.plane_n, self.plane_e, strict=True):
            out |= centres @ nrm - e - h * np.abs(nrm).sum() < -tol
        for c, a, axial, u, e in self.drums:
            z = (centres - c) @ a
            near = np.flatnonzero(np.abs(z) < axial)
            if near.size:
                inside = np.all(centres[near] @ u.T + h * np.abs(u).sum(axis=1) <= e + tol, axis=1)
                out[near[~inside]] = True
        if self.body.size:
            self._block_bodies(out, krange, k, local_of)
        if self.mesh_planes and len(centres):
            self._block_meshes(out, centres)
        return out

    def _block_meshes(self, out, centres):
        """Cells whose bounding sphere is not separated from a mesh wall's cell by one of its planes."""
        from scipy.spatial import cKDTree

        reach = self.h * math.sqrt(3.0)
        tree = cKDTree(centres)
        for c, r, nrm, off, verts in self.mesh_planes:
            near = tree.query_ball_point(c, r + reach)
            if near:
                near = np.asarray(near)
                p = centres[near]
                apart = np.any(p @ nrm.T - off > reach + self.tol, axis=1)
                # Thin cells (the wedges behind a shallow crease) are poorly separated by their
                # face planes: also try the axis from the grid cell to the wall cell's centre.
                axis = c - p
                axis /= np.maximum(np.linalg.norm(axis, axis=1, keepdims=True), 1e-300)
                gap = np.min(np.einsum("vk,nk->nv", verts, axis), axis=1) - np.einsum("nk,nk->n", p, axis)
                apart |= gap > reach + self.tol
                out[near[~apart]] = True

    def _block_bodies(self, out, krange, k, local_of):
        cell, n = self.cell, self.n
        ilo = np.clip(np.floor((self.pos - self.rad[:, None] - self.origin) / cell), 0, n - 1).astype(np.int64)
        ihi = np.clip(np.floor((self.pos + self.rad[:, None] - self.origin) / cell), 0, n - 1).astype(np.int64)
        ilo[:, k] = np.maximum(ilo[:, k], krange[0])
        ihi[:, k] = np.minimum(ihi[:, k], krange[1])
        dims = ihi - ilo + 1
        sel = np.flatnonzero(np.all(dims > 0, axis=1))
        if not sel.size:
            return
        ilo, dims = ilo[sel], dims[sel]
        sizes = np.prod(dims, axis=1)
        big = np.flatnonzero(sizes > _PAIR_BATCH)
        if big.size:  # a wall spanning the whole chunk: cut its block into slices along its longest axis
            small = np.flatnonzero(sizes <= _PAIR_BATCH)
            pieces = [(sel[small], ilo[small], dims[small])]  # each of these whole, in their order
            for i in big:
                ax = int(np.argmax(dims[i]))
                step = max(1, _PAIR_BATCH // (int(sizes[i]) // int(dims[i, ax])))
                for s0 in range(0, int(dims[i, ax]), step):
                    lo_, d_ = ilo[i].copy(), dims[i].copy()
                    lo_[ax] += s0
                    d_[ax] = min(step, int(dims[i, ax]) - s0)
                    pieces.append((sel[i : i + 1], lo_[None], d_[None]))
            sel = np.concatenate([pc[0] for pc in pieces])
            ilo = np.concatenate([pc[1] for pc in pieces])
            dims = np.concatenate([pc[2] for pc in pieces])
            sizes = np.prod(dims, axis=1)
        ends = np.cumsum(sizes)
        start = 0
        while start < sel.size:
            base = ends[start - 1] if start else 0
            stop = max(start + 1, int(np.searchsorted(ends, base + _PAIR_BATCH, side="right")))
            self._block_pairs(out, sel[start:stop], ilo[start:stop], dims[start:stop], sizes[start:stop], local_of)
            start = stop

    def _block_pairs(self, out, obs, ilo, dims, sizes, local_of):
        """Test every (obstacle, cell) pair of the index blocks ``ilo + [0, dims)``, one per entry of
        ``obs`` (an obstacle may have several blocks)."""
        h, tol = self.h, self.tol
        ob = np.repeat(np.arange(len(obs)), sizes)
        local = np.arange(int(sizes.sum()), dtype=np.int64) - np.repeat(np.cumsum(sizes) - sizes, sizes)
        dz, dy = dims[ob, 2], dims[ob, 1]
        gi = np.empty((len(ob), 3), dtype=np.int64)
        gi[:, 2] = local % dz
        local //= dz
        gi[:, 1] = local % dy
        gi[:, 0] = local // dy
        gi += ilo[ob]
        j = obs[ob]
        rel = self.origin + (gi + 0.5) * self.cell - self.pos[j]
        # Bounding sphere against the cube first: most far pairs end here.
        gap = np.maximum(np.abs(rel) - h, 0.0)
        close = np.flatnonzero(np.einsum("ij,ij->i", gap, gap) < self.rad[j] ** 2)
        if not close.size:
            return
        gi, j, rel = gi[close], j[close], rel[close]
        for sid in np.unique(self.shape[j]):
            pick = np.flatnonzero(self.shape[j] == sid)
            shape = self.shapes[int(sid)]
            # The obstacles of these pairs (np.unique's, by a mark per obstacle) and each pair's among them.
            present = np.zeros(len(self.body), dtype=bool)
            present[j[pick]] = True
            bodies = np.flatnonzero(present)
            which = (np.cumsum(present) - 1)[j[pick]]
            normals = np.einsum("bij,fj->bfi", self.rot[bodies], shape.face_normals)  # world normals
            support = h * np.abs(normals).sum(axis=2)  # (bodies, faces): half extent of the cube along each
            r = rel[pick]
            sep = np.full(len(pick), -np.inf)
            for face in range(shape.num_faces):
                # (the same rows as normals[which, face], gathered from a contiguous copy)
                nw = np.ascontiguousarray(normals[:, face]).take(which, axis=0)
                s = np.einsum("ij,ij->i", r, nw) - shape.face_offsets[face] - support[:, face].take(which)
                np.maximum(sep, s, out=sep)
            hit = pick[sep < -tol]
            if hit.size:
                out[local_of(gi[hit])] = True


def _orientations(orientation, count, rng) -> np.ndarray:
    """(count, 4) xyzw orientations: uniformly random, or the identity for ``"aligned"``."""
    if orientation == "random":
        q = rng.normal(size=(count, 4))
        norm = np.sqrt(np.einsum("ij,ij->i", q, q))
        return np.where(norm[:, None] > 1e-12, q / np.maximum(norm, 1e-300)[:, None], [0.0, 0.0, 0.0, 1.0])
    return np.broadcast_to(np.array([0.0, 0.0, 0.0, 1.0]), (count, 4))


def emit(
    scene,
    shape,
    material,
    count,
    region,
    *,
    weights=EMITTER.defaults["weights"],
    orientation=EMITTER.defaults["orientation"],
    seed=EMITTER.defaults["seed"],
    velocity=EMITTER.defaults["velocity"],
    velocity_jitter=EMITTER.defaults["velocity_jitter"],
    scale=EMITTER.defaults["scale"],
    scale_range=EMITTER.defaults["scale_range"],
    scale_lognormal=EMITTER.defaults["scale_lognormal"],
    scale_bins=EMITTER.defaults["scale_bins"],
    kind=EMITTER.defaults["kind"],
    spacing=EMITTER.defaults["spacing"],
    jitter=EMITTER.defaults["jitter"],
    fill=EMITTER.defaults["fill"],
    key: str | None = None,
) -> np.ndarray:
    """:meth:`Scene.emit <polydem.scene.Scene.emit>`: place ``count`` bodies of ``scene`` in a box region without
    overlaps; returns their indices."""
    key = key or f"emitters[{len(scene.emitters)}]"
    f = scene.file
    count = EMITTER["count"].read(count, f"{key}.count", f)
    lo, hi = _region(region, f"{key}.region", f)
    base, frac = _emitter_shapes(scene, shape, weights, key)
    mat = scene.material_index(material, key=f"{key}.material")
    given = {"kind": kind, "orientation": orientation, "fill": fill, "seed": seed, "velocity": velocity}
    given.update(velocity_jitter=velocity_jitter, spacing=spacing, jitter=jitter, scale_bins=scale_bins)
    a = EMITTER.read(given, key, f)
    kind_code = KINDS.index(a["kind"])
    orientation, fill, seed, vel, vj = a["orientation"], a["fill"], a["seed"], a["velocity"], a["velocity_jitter"]
    spacing, jitter = a["spacing"], a["jitter"]
    sample_scales, scale_key = _scale_sampler(scale, scale_range, scale_lognormal, a["scale_bins"], key, f)
    if kind_code == KIND_FIXED and (vj > 0.0 or np.any(vel != 0.0)):
        raise scene.error(
            "fixed bodies cannot move; remove velocity and velocity_jitter or use kind = 'kinematic'",
            f"{key}.velocity",
        )
    _check_capacity(scene, count, lo, hi, base, frac, sample_scales, spacing, key)

    streams = [np.random.default_rng(s) for s in np.random.SeedSequence(seed).spawn(6)]
    rng_shape, rng_scale, rng_cells, rng_jitter, rng_orient, rng_vel = streams
    rows, radius = _emitted_shapes(scene, base, frac, sample_scales, count, rng_shape, rng_scale, scale_key)
    r_max = float(radius.max())
    cell = spacing * 2.0 * r_max
    centres = _emitter_cells(scene, lo, hi, cell, count, fill, rng_cells, key, r_max, spacing)
    room = jitter * np.maximum(0.5 * cell - radius, 0.0)
    centres = centres + rng_jitter.uniform(-1.0, 1.0, size=(count, 3)) * room[:, None]
    q = _orientations(orientation, count, rng_orient)
    v = np.broadcast_to(vel, (count, 3))
    if vj > 0.0:
        v = v + rng_vel.uniform(-vj, vj, size=(count, 3))
    frames = scene.shape_input_frames()
    t_in = np.array([frames[s][1] for s in range(len(frames))])[rows]
    positions = centres - quat_rotate(q, t_in) if np.any(t_in) else centres
    idx = append_bodies(scene, rows, mat, positions, q, v, np.zeros((count, 3)), kind_code, lambda i: key)
    scene.emitters.append({"key": key, "count": count, "first": int(idx[0]), "last": int(idx[-1])})
    return idx


def _emitted_shapes(scene, base, frac, sample_scales, count, rng_shape, rng_scale, scale_key):
    """(count,) shape index and bounding radius of each emitted body: the mix of ``base`` shapes in the
    proportions ``frac``, each scaled by a factor drawn from ``sample_scales`` (given as ``scale_key``)."""
    label = rng_shape.permutation(np.repeat(np.arange(len(base)), _largest_remainder(count, frac)))
    bin_index, values = sample_scales(rng_scale, count)
    # np.unique(..., return_inverse=True) of these small codes, by a count of each (no sort of the bodies)
    code = label * len(values) + bin_index
    present = np.bincount(code, minlength=len(base) * len(values)) > 0
    combo = np.flatnonzero(present)
    inverse = (np.cumsum(present) - 1)[code]
    shapes = list(scene.shapes.values())
    for cb in combo.tolist():
        _check_scaled_radius(scene, shapes[base[cb // len(values)]], float(values[cb % len(values)]), scale_key)
    combo_shape = np.array(
        [_scaled_shape(scene, base[int(cb) // len(values)], float(values[int(cb) % len(values)])) for cb in combo],
        dtype=np.int32,
    )
    shapes = list(scene.shapes.values())
    combo_radius = np.array([shapes[s].radius for s in combo_shape])
    return combo_shape[inverse], combo_radius[inverse]


def _check_scaled_radius(scene, shape, factor: float, scale_key):
    """Refuse a size factor that takes ``shape`` beyond the bounding radii a run resolves, before its
    volume and inertia (factor^3, factor^5) leave float64: the float32 check of :meth:`validate` would only
    name the scaled shape, which the scene file does not."""
    radius = shape.radius * factor
    if factor == 1.0 or RADIUS_LOW <= radius <= RADIUS_HIGH:
        return
    raise scene.error(
        f"the size factor {factor:.3g} gives shape {shape.name!r} (bounding radius {shape.radius:.3g} m) a "
        f"bounding radius of {radius:.3g} m: too {'small' if radius < RADIUS_LOW else 'large'} for the "
        f"simulator's float32 arithmetic, which takes bounding radii from {RADIUS_LOW:.2g} to {RADIUS_HIGH:.2g} m; "
        f"give size factors from {RADIUS_LOW / shape.radius:.3g} to {RADIUS_HIGH / shape.radius:.3g} for it",
        scale_key,
    )


def _check_capacity(scene, count, lo, hi, base, frac, sample_scales, spacing, key):
    """Reject a count the scene or the region cannot hold, by arithmetic before any per-body array.

    Every cell is at least ``spacing`` times the largest bounding diameter among the shapes that
    get bodies, each at its smallest size factor, so the region holds at most that many cells.
    """
    total = scene.num_bodies + count
    if total > scene_bodies.MAX_BODIES:
        many = f"{total:.3g}" if total < 1e300 else as_integer(total)  # :g takes an int only as a float
        raise scene.error(
            f"count = {as_integer(count)} would make {many} bodies, more than a scene can hold "
            f"({scene_bodies.MAX_BODIES:,}); lower count",
            f"{key}.count",
        )
    per_shape = _largest_remainder(count, frac)
    _, factors = sample_scales(np.random.default_rng(0), 0)
    shapes = list(scene.shapes.values())
    r_low = max(shapes[b].radius for b, c in zip(base, per_shape, strict=True) if c > 0) * float(np.min(factors))
    cell = spacing * 2.0 * r_low
    cells = np.floor((hi - lo) / cell * (1.0 + 1e-12))
    capacity = float(np.prod(cells))  # a float: a region of tiny cells holds more than an int64 counts
    # The grid scan gives the exact number (walls and bodies block cells) and the better message;
    # only counts whose per-body arrays would be large are cut here.
    if count > capacity and count > _EMITTER_CHUNK and capacity > 0:
        raise scene.error(
            f"the region holds at most {int(capacity)} bodies, fewer than count = {count}: it fits at most "
            f"{' x '.join(str(int(c)) for c in cells)} cells of {cell:.4g} m (spacing {spacing:g} x the largest "
            f"bounding diameter at the smallest size, {2.0 * r_low:.4g} m); lower count or enlarge the region",
            f"{key}.count",
        )


def _emitter_shapes(scene, shape, weights, key) -> tuple[list[int], np.ndarray]:
    """Shape indices and normalised weights of an emitter's ``shape`` (and ``weights``)."""
    f = scene.file
    if isinstance(shape, dict):
        if weights is not None:
            raise scene.error("give the weights either in the shape table or as weights, not both", f"{key}.weights")
        names = list(shape)
        weights = [shape[n] for n in names]
        wkey = [f"{key}.shape.{n}" for n in names]
    elif isinstance(shape, list | tuple):
        names = list(shape)
        wkey = [f"{key}.weights[{i}]" for i in range(len(names))]
    else:
        if weights is not None:
            raise scene.error(
                "weights go with a list of shapes, e.g. shape = ['cube', 'rock'] and weights = [2, 1]",
                f"{key}.weights",
            )
        names, weights, wkey = [shape], None, [f"{key}.weights"]
    if not names:
        raise scene.error("the list of shapes is empty; give at least one shape name", f"{key}.shape")
    index = []
    for i, name in enumerate(names):
        sub = f"{key}.shape" if len(names) == 1 else f"{key}.shape[{i}]"
        if isinstance(shape, dict):
            sub = f"{key}.shape.{name}"
        s = scene.resolve_shape(name, sub)
        if s in index:
            raise scene.error(f"shape {scene.shape_names[s]!r} is listed twice; list each shape once", sub)
        index.append(s)
    if weights is None:
        frac = np.full(len(index), 1.0 / len(index))
    else:
        if not isinstance(weights, list | tuple | np.ndarray) or len(weights) != len(index):
            raise scene.error(
                f"expected {len(index)} weights, one per shape, got {typename(weights)}", f"{key}.weights"
            )
        frac = np.array([read_number(wt, wkey[i], f, nonneg=True) for i, wt in enumerate(weights)])
        if frac.sum() <= 0.0:
            raise scene.error("the weights are all zero; give at least one positive weight", f"{key}.weights")
        frac = frac / frac.sum()
    return index, frac


def _scaled_shape(scene, base: int, factor: float) -> int:
    """Index of shape ``base`` scaled by ``factor`` (registered once as ``"{name}_x{factor}"``)."""
    if factor == 1.0:
        return base
    cache = (base, factor)
    if cache in scene.scaled_shapes:
        return scene.scaled_shapes[cache]
    src = scene.shape_names[base]
    name = stem = f"{src}_x{factor:.6g}"
    k = 1
    while name in scene.shape_names:
        k += 1
        name = f"{stem}_{k}"
    shape = list(scene.shapes.values())[base].scaled(factor)
    shape.name = name
    scene.add_shape(name, shape, spec=scaled_spec(scene.shape_spec(src), factor))
    scene.scaled_shapes[cache] = scene.shape_index(name)
    return scene.scaled_shapes[cache]


def _lowest_cells(layer: np.ndarray, draw: np.ndarray, count: int) -> np.ndarray:
    """The first ``count`` cells of a stable sort by (``layer``, ``draw``), in the order of the cells (sorted
    indices): the lowest layers whole and, of the last layer needed, the cells of the smallest draws (ties in
    the order of the cells). ``layer`` ascends, so only that layer is sorted."""
    last = layer[count - 1]
    first, end = np.searchsorted(layer, last, side="left"), np.searchsorted(layer, last, side="right")
    chosen = first + np.argsort(draw[first:end], kind="stable")[: count - first]
    return np.concatenate([np.arange(first, dtype=np.int64), np.sort(chosen)])


def _emitter_cells(scene, lo, hi, cell, count, fill, rng, key, r_max, spacing) -> np.ndarray:
    """(count, 3) centres of the free grid cells chosen for an emitter (see :meth:`emit`)."""
    ext = hi - lo
    # Counted in floats until they are known to fit the int64 grid indices.
    n = np.floor(ext / cell * (1.0 + 1e-12))
    sizes = f"cells of {cell:.4g} m (spacing {spacing:g} x the largest bounding diameter {2.0 * r_max:.4g} m)"
    if np.any(n < 1):
        ax = int(np.flatnonzero(n < 1)[0])
        raise scene.error(
            f"the region is {ext[ax]:.4g} m along {'xyz'[ax]}, too small for one body: bodies are placed in "
            f"{sizes}; make the region at least {cell:.4g} m along {'xyz'[ax]}, or use smaller shapes or a "
            "smaller spacing",
            f"{key}.region",
        )
    origin = lo + 0.5 * (ext - n * cell)
    g = np.asarray(scene.gravity, dtype=np.float64)
    up = -g / np.linalg.norm(g) if np.linalg.norm(g) > 0.0 else np.array([0.0, 0.0, 1.0])
    k = int(np.argmax(np.abs(up)))
    ascending = bool(up[k] >= 0.0)
    ax_a, ax_b = (i for i in range(3) if i != k)
    per_layer = float(n[ax_a] * n[ax_b])
    total = per_layer * float(n[k])
    most = _MAX_EMITTER_CELLS if fill == "random" else _MAX_GRID_CELLS
    if per_layer > _MAX_EMITTER_CELLS or total > most:
        what = "one layer of" if per_layer > _MAX_EMITTER_CELLS else "the"
        raise scene.error(
            f"{what} region holds {per_layer if what != 'the' else total:.3g} {sizes}, far more than "
            f"{count} bodies need (the limit is {_MAX_EMITTER_CELLS:.0e} cells); make the region smaller"
            + (' or use fill = "bottom"' if fill == "random" else ""),
            f"{key}.region",
        )
    n = n.astype(np.int64)
    nb_, nk = int(n[ax_b]), int(n[k])
    per_layer, total = int(n[ax_a]) * nb_, int(n[ax_a]) * nb_ * nk
    obstacles = _Obstacles(scene, origin, origin + n * cell, cell)
    chunk_layers = max(1, _EMITTER_CHUNK // per_layer)
    found, got_layer, got_m = 0, [], []
    for l0 in range(0, nk, chunk_layers):
        l1 = min(nk, l0 + chunk_layers)
        layer = np.repeat(np.arange(l0, l1, dtype=np.int64), per_layer)
        m = np.tile(np.arange(per_layer, dtype=np.int64), l1 - l0)
        gi = _cell_index(layer, m, k, ax_a, ax_b, nb_, nk, ascending)
        krange = (l0, l1 - 1) if ascending else (nk - l1, nk - 1 - l0)

        def local_of(g, l0=l0):
            lay = g[:, k] if ascending else nk - 1 - g[:, k]
            return (lay - l0) * per_layer + g[:, ax_a] * nb_ + g[:, ax_b]

        blocked = obstacles.blocked(origin + (gi + 0.5) * cell, krange, k, local_of)
        keep = ~blocked
        got_layer.append(layer[keep])
        got_m.append(m[keep])
        found += int(keep.sum())
        if fill == "bottom" and found >= count:
            break
    if found < count:
        per = found / nk if found else per_layer
        need = math.ceil(count / max(per, 1e-300)) * cell
        msg = (
            f"the region holds at most {found} bodies, fewer than count = {count}: it is a grid of "
            f"{n[0]} x {n[1]} x {n[2]} {sizes}"
        )
        if total > found:
            msg += f", and {total - found} of its {total} cells cross walls or bodies already in the scene"
        msg += (
            f". Lower count to {found}, or enlarge the region (to about {need:.3g} m along {'xyz'[k]} at this "
            "width, or wider), or lower spacing"
        )
        raise scene.error(msg, f"{key}.count")
    layer = np.concatenate(got_layer)
    m = np.concatenate(got_m)
    if fill == "bottom":
        pick = _lowest_cells(layer, rng.random(found), count)
    else:
        chosen = np.zeros(found, dtype=bool)
        chosen[rng.choice(found, size=count, replace=False)] = True
        pick = np.flatnonzero(chosen)  # the cells drawn, in their order
    gi = _cell_index(layer[pick], m[pick], k, ax_a, ax_b, nb_, nk, ascending)
    return origin + (gi + 0.5) * cell
