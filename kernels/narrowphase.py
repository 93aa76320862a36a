"""Narrow phase: the overlap geometry of many pairs of convex polyhedra, one thread per pair.

The geometry itself (clipping, fan triangles, cones, the coincident-face rule) lives in
:mod:`polydem.kernels.geometry`; this module holds the kernel that runs it over a batch of
pairs (the batch API :func:`polydem.overlap` and the pair benchmarks) and its launcher, which
grows the per-thread polygon buffer when a facet overflowed it.
"""

import functools
from dataclasses import dataclass
from typing import Any, Protocol

import warp as wp
from polydem.kernels.compound import make_body_geometry
from polydem.kernels.geometry import COINCIDENT_TOL, COORDINATE_NOISE, make_geometry
from polydem.kernels.structs import arrays, filled, make_struct

__all__ = [
    "COINCIDENT_TOL",
    "COORDINATE_NOISE",
    "NARROWPHASE_BLOCK_DIM",
    "BatchPairs",
    "BatchShapes",
    "Narrowphase",
    "launch_depth",
    "launch_overlap",
    "make_depth_kernel",
    "make_narrowphase",
]

# Threads per block of the pair kernels: small blocks suit their large per-thread stack
# (BENCHMARKS.md, "Design measurements").
NARROWPHASE_BLOCK_DIM = 64


class BatchShapes(Protocol):
    """What the batch launches read of a shape set (:class:`polydem.shapeset.ShapeSet`; kernels/ does not
    import the host package): the geometry kernels' ``shapes`` struct, its precision and device, and
    the polygon capacities."""

    scalar: Any
    device: Any
    max_faces: int
    compound: bool
    default_poly_capacity: int
    max_poly_bound: int

    def kernel_args(self) -> list[Any]: ...


@dataclass(frozen=True)
class BatchPairs:
    """N pairs for the batch kernels: the shapes (indices into the shape set) and poses (transforms) of A
    and B, ``wp.array`` each, in the kernels' order."""

    shape_a: wp.array
    shape_b: wp.array
    pose_a: wp.array
    pose_b: wp.array

    def struct(self) -> Any:
        """The arrays in a :func:`batch_pairs_struct` (for the depth kernel)."""
        pose_scalar = wp.float64 if wp.types.types_equal(self.pose_a.dtype, wp.transformd) else wp.float32
        pairs = batch_pairs_struct(pose_scalar)
        return filled(pairs, shape_a=self.shape_a, shape_b=self.shape_b, pose_a=self.pose_a, pose_b=self.pose_b)


@functools.cache
def batch_pairs_struct(pose_scalar: Any) -> Any:
    """The ``wp.struct`` of N pairs' shapes (``shape_a``, ``shape_b``) and poses (``pose_a``, ``pose_b``, transforms
    in ``pose_scalar``)."""
    transform = wp.types.transformation(pose_scalar)
    return make_struct("BatchPairs", **arrays(shape_a=int, shape_b=int, pose_a=transform, pose_b=transform))


@dataclass(frozen=True)
class Narrowphase:
    """The batch overlap kernel of one precision and polygon capacity, with its geometry."""

    scalar: Any
    vec3: Any
    vec4: Any
    transform: Any
    quat: Any
    max_poly: int
    tol_rel: float
    geometry: Any  # polydem.kernels.geometry.Geometry
    pair_geometry: Any
    overlap_kernel: Any


@functools.cache
def make_narrowphase(
    scalar,
    max_poly: int,
    max_faces: int,
    coincident_tol: float | None = None,
    max_registers: int | None = 128,
    pose_scalar=None,
    compound: bool = False,
    count_work: bool = False,
    setup_only: bool = False,
    shared_poly: bool = False,
) -> Narrowphase:
    """Build the batch overlap kernel for one precision and polygon capacity.

    Args:
        scalar: ``wp.float32`` or ``wp.float64``.
        max_poly, max_faces, coincident_tol, pose_scalar: as for
            :func:`polydem.kernels.geometry.make_geometry`.
        max_registers: CUDA register cap per thread (128 is faster than no cap for 20-vertex rocks
            and slightly slower for cubes; see benchmarks/tune_pair_kernel.py and BENCHMARKS.md).
        count_work: the measuring variant (:func:`~polydem.kernels.geometry.make_geometry`'s): ``overflow`` is
            then (N + 1,), entry 1 + i pair i's path word (its bit 0 the pair's own overflow).
        setup_only: the measuring variant of the pairs' set-up alone (make_geometry's).
        shared_poly: the polygon buffer in the block's shared memory (make_geometry's); launch the kernel with
            :data:`NARROWPHASE_BLOCK_DIM` threads a block.
    """
    geom = make_geometry(scalar, max_poly, max_faces, coincident_tol, pose_scalar, count_work, setup_only, shared_poly)
    vec3 = geom.vec3
    transform = geom.transform
    Shapes = geom.shapes
    # With ``compound`` the shapes may be compound grains (summed over their part pairs).
    pair_geometry = make_body_geometry(geom, compound).pair_geometry

    Pairs = batch_pairs_struct(geom.pose_scalar)

    # The outputs stay one array per quantity: benchmarks/pair_kernel.py launches this kernel of older trees
    # too, and reads the outputs by OVERLAP_OUTPUTS.
    @wp.kernel(enable_backward=False, module="unique", cuda_max_registers=max_registers)
    def overlap_kernel(
        # Model
        shapes: Shapes,
        # State in
        pairs: Pairs,
        # Out
        pair_volume: wp.array(dtype=scalar),
        pair_volume_moment: wp.array(dtype=vec3),
        pair_area_a: wp.array(dtype=vec3),
        pair_moment_a: wp.array(dtype=vec3),
        pair_area_b: wp.array(dtype=vec3),
        pair_moment_b: wp.array(dtype=vec3),
        pair_fallback_a: wp.array(dtype=vec3),
        overflow: wp.array(dtype=int),
    ):
        i = wp.tid()
        vol, vol_c, s_a, m_a, s_b, m_b, fb_a, of = pair_geometry(
            shapes, pairs.shape_a[i], pairs.shape_b[i], pairs.pose_a[i], pairs.pose_b[i]
        )
        if wp.static(count_work):
            overflow[i + 1] = of
            of = of & 1
        if of != 0:
            wp.atomic_add(overflow, 0, 1)
        pair_volume[i] = vol
        pair_volume_moment[i] = vol_c
        pair_area_a[i] = s_a
        pair_moment_a[i] = m_a
        pair_area_b[i] = s_b
        pair_moment_b[i] = m_b
        pair_fallback_a[i] = fb_a

    return Narrowphase(
        scalar=scalar,
        vec3=vec3,
        vec4=geom.vec4,
        transform=transform,
        quat=geom.quat,
        max_poly=max_poly,
        tol_rel=geom.tol_rel,
        geometry=geom,
        pair_geometry=pair_geometry,
        overlap_kernel=overlap_kernel,
    )


@functools.cache
def make_depth_kernel(scalar, max_faces: int, pose_scalar=None, compound: bool = False):
    """Kernel: penetration depth (:func:`polydem.kernels.geometry.make_geometry`'s ``pair_depth``) of N pairs."""
    geom = make_geometry(scalar, 1, max_faces, None, pose_scalar)
    body_geom = make_body_geometry(geom, compound)

    @wp.kernel(enable_backward=False, module="unique")
    def depth_kernel(shapes: geom.shapes, pairs: batch_pairs_struct(geom.pose_scalar), depth: wp.array(dtype=scalar)):
        i = wp.tid()
        depth[i] = body_geom.pair_depth(shapes, pairs.shape_a[i], pairs.shape_b[i], pairs.pose_a[i], pairs.pose_b[i])

    return depth_kernel


def launch_depth(shapes: BatchShapes, pairs: BatchPairs, *, pose_scalar: Any = None) -> wp.array:
    """Penetration depth [m] of each pair, a ``wp.array`` of the shape set's precision."""
    n = len(pairs.shape_a)
    depth = wp.zeros(n, dtype=shapes.scalar, device=shapes.device)
    wp.launch(
        make_depth_kernel(shapes.scalar, shapes.max_faces, pose_scalar, shapes.compound),
        dim=n,
        inputs=[*shapes.kernel_args(), pairs.struct()],
        outputs=[depth],
        device=shapes.device,
    )
    return depth


OVERLAP_OUTPUTS = (
    "pair_volume",
    "pair_volume_moment",
    "pair_area_a",
    "pair_moment_a",
    "pair_area_b",
    "pair_moment_b",
    "pair_fallback_a",
)


def launch_overlap(
    shapes: BatchShapes,
    pairs: BatchPairs,
    *,
    out: dict[str, wp.array],
    max_poly: int | None = None,
    pose_scalar: Any = None,
) -> Narrowphase:
    """Run the overlap kernel over all pairs; grow the polygon buffer and redo on overflow.

    ``shapes`` is a :class:`polydem.shapeset.ShapeSet`; ``out`` a dict of output arrays named as
    the kernel's ``# Out`` arguments (``pair_fallback_a`` may be left out). The poses are
    transforms of ``pose_scalar`` (default the shape set's precision). Returns the
    :class:`Narrowphase` that ran.
    """
    n = len(pairs.shape_a)
    capacity = shapes.default_poly_capacity if max_poly is None else max_poly
    if "pair_fallback_a" not in out:
        out = dict(out)
        out["pair_fallback_a"] = wp.zeros(n, dtype=wp.types.vector(3, shapes.scalar), device=shapes.device)
    while True:
        nphase = make_narrowphase(
            shapes.scalar,
            capacity,
            shapes.max_faces,
            pose_scalar=pose_scalar,
            compound=shapes.compound,
        )
        overflow = wp.zeros(1, dtype=int, device=shapes.device)
        wp.launch(
            nphase.overlap_kernel,
            dim=n,
            inputs=[*shapes.kernel_args(), pairs.struct()],
            outputs=[*(out[name] for name in OVERLAP_OUTPUTS), overflow],
            device=shapes.device,
            block_dim=NARROWPHASE_BLOCK_DIM,
        )
        if n == 0 or int(overflow.numpy()[0]) == 0:
            return nphase
        if capacity >= shapes.max_poly_bound:
            raise RuntimeError(
                f"polygon buffer of {capacity} vertices overflowed although it holds the largest possible "
                "clipped facet; this is a bug in polydem, please report it with the shapes involved"
            )
        capacity = min(2 * capacity, shapes.max_poly_bound)
