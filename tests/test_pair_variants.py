"""The pair kernels' register cap changes how they compile, never what they compute.

The engine keeps one way of holding a pair's working set (the clipping planes recomputed where they
are read, the active faces listed in per-thread memory); the others measured in BENCHMARKS.md
section 7c (per-thread plane tables, faces as bit masks, polygons streamed) live at the git tag
``pair-variants-7c`` with the test that they agree bit for bit. What remains an option is the CUDA
register cap of the pair kernels (:func:`polydem.kernels.forces.make_contact_kernels`,
:func:`polydem.kernels.narrowphase.make_narrowphase`, ``Simulation(pair_max_registers=)``): every
output of the overlap kernel must be the same bits under every cap, on random pairs of cubes, rocks
and a 64-vertex hull (shallow, deep and separated), on stacked aligned cubes (the coincident-face
rule) and on enclosed pairs (the fallback), and a Simulation must build its contact kernels with
the cap it is given and step to the same state with any.
"""

import numpy as np
import pytest
import warp as wp
from polydem.kernels.forces import PAIR_MAX_REGISTERS
from polydem.kernels.narrowphase import NARROWPHASE_BLOCK_DIM, OVERLAP_OUTPUTS, BatchPairs, make_narrowphase
from scipy.spatial.transform import Rotation

from polydem import ConvexShape, Scene, Simulation
from polydem.shapeset import ShapeSet

# The default cap, a lower one and none (the compiler's choice).
CAPS = (PAIR_MAX_REGISTERS, 64, None)
SETS = {
    "cube_rock": lambda: [ConvexShape.box(1.0), ConvexShape.rock(n_points=20, size=0.7, seed=1)],
    "hull64": lambda: [ConvexShape.rock(n_points=64, size=1.0, seed=2), ConvexShape.box(0.5)],
}


def random_pairs(shapes, rng, n):
    """Shape indices and poses: random pairs at every depth (about half touching), aligned stacked
    copies of shape 0 (coincident faces, some shifted sideways) and pairs with one body inside."""
    k = len(shapes)
    sa = rng.integers(0, k, n)
    sb = rng.integers(0, k, n)
    reach = np.array([s.radius for s in shapes])
    qa = Rotation.random(n, random_state=rng).as_quat()
    qb = Rotation.random(n, random_state=rng).as_quat()
    u = rng.normal(size=(n, 3))
    u /= np.linalg.norm(u, axis=1, keepdims=True)
    dist = rng.uniform(0.0, 1.1, n) * (reach[sa] + reach[sb])
    pa = np.hstack([rng.uniform(-2.0, 2.0, (n, 3)), qa])
    pb = np.hstack([pa[:, :3] + u * dist[:, None], qb])
    # Aligned copies of shape 0 stacked along z, 0-2% into each other, some shifted sideways.
    m = n // 8
    rows = np.arange(m)
    sa[rows] = 0
    sb[rows] = 0
    h = 2.0 * np.asarray(shapes[0].vertices)[:, 2].max()
    pa[rows] = [0.3, -0.2, 0.1, 0.0, 0.0, 0.0, 1.0]
    pb[rows, :3] = pa[rows, :3] + np.column_stack(
        [rng.choice([0.0, 0.25], m) * h, np.zeros(m), h * (1.0 - rng.uniform(0.0, 0.02, m))]
    )
    pb[rows, 3:] = pa[rows, 3:]
    # One body (nearly) inside the other: the fallback direction.
    rows = np.arange(m, 2 * m)
    pb[rows, :3] = pa[rows, :3] + rng.uniform(-0.05, 0.05, (m, 3))
    return sa, sb, pa, pb


def run(shapes, sa, sb, pa, pb, max_registers, pose_scalar, device, shared_poly=False, max_poly=None):
    scalar = shapes.scalar
    tf = wp.types.transformation(pose_scalar)
    np_pose = np.float64 if pose_scalar == wp.float64 else np.float32
    n = len(sa)
    vec3 = wp.types.vector(3, scalar)
    out = [wp.zeros(n, dtype=scalar, device=device)]
    out += [wp.zeros(n, dtype=vec3, device=device) for _ in OVERLAP_OUTPUTS[1:]]
    overflow = wp.zeros(1, dtype=int, device=device)
    # Room for the largest clipped facet: no overflow, so one launch per cap.
    ns = make_narrowphase(
        scalar, max_poly or shapes.max_poly_bound, shapes.max_faces, max_registers=max_registers,
        pose_scalar=pose_scalar, shared_poly=shared_poly,
    )  # fmt: skip
    assert ns.overlap_kernel.options.get("cuda_max_registers") == max_registers
    wp.launch(
        ns.overlap_kernel,
        dim=n,
        inputs=[
            *shapes.kernel_args(),
            BatchPairs(
                wp.array(sa.astype(np.int32), dtype=int, device=device),
                wp.array(sb.astype(np.int32), dtype=int, device=device),
                wp.array(pa.astype(np_pose), dtype=tf, device=device),
                wp.array(pb.astype(np_pose), dtype=tf, device=device),
            ).struct(),
        ],
        outputs=[*out, overflow],
        device=device,
        block_dim=NARROWPHASE_BLOCK_DIM,
    )
    assert int(overflow.numpy()[0]) == 0
    return {name: a.numpy() for name, a in zip(OVERLAP_OUTPUTS, out, strict=True)}


def assert_same_bits(got, ref, what):
    """Every output of ``got`` the same bits as ``ref``'s, pair by pair: compared as raw bytes, not merely equal
    values (-0.0 == 0.0)."""
    for name in OVERLAP_OUTPUTS:
        n = len(ref[name])
        a = got[name].reshape(n, -1)
        b = ref[name].reshape(n, -1)
        same = np.all(a.view(np.uint8) == b.view(np.uint8), axis=1)
        assert same.all(), f"{what}: {name} differs in pairs {np.flatnonzero(~same)[:10]}"


@pytest.mark.parametrize("precision", ["float32", "mixed", "float64"])
@pytest.mark.parametrize("shape_set", sorted(SETS))
def test_register_caps_agree_bit_for_bit(device, shape_set, precision):
    shapes_list = SETS[shape_set]()
    shapes = ShapeSet(shapes_list, device=device, precision="float64" if precision == "float64" else "float32")
    pose_scalar = wp.float32 if precision == "float32" else wp.float64
    sa, sb, pa, pb = random_pairs(shapes_list, np.random.default_rng(7), 1024)
    ref = run(shapes, sa, sb, pa, pb, CAPS[0], pose_scalar, device)
    touching = ref["pair_volume"] > 0.0
    assert 0.3 * len(sa) < touching.sum() < 0.9 * len(sa)  # overlapping and separated pairs both
    assert (np.linalg.norm(ref["pair_fallback_a"], axis=1) > 0.0).sum() > 10  # enclosed pairs
    for cap in CAPS[1:]:
        got = run(shapes, sa, sb, pa, pb, cap, pose_scalar, device)
        assert_same_bits(got, ref, f"cap {cap} against cap {CAPS[0]}")


@pytest.mark.parametrize("precision", ["float32", "mixed"])
@pytest.mark.parametrize("shape_set", sorted(SETS))
def test_shared_polygon_buffer_agrees_bit_for_bit(device, shape_set, precision):
    """make_geometry's shared_poly variant (the polygon buffer in the block's shared memory on a GPU, each thread
    its own rows; benchmarks/pair_kernel.py --clips polygon,shared) computes the same bits as the per-thread buffer,
    on the same pairs as the register caps; too large a buffer for a block is a clear error."""
    from polydem.kernels.geometry import SHARED_POLY_BLOCK

    assert NARROWPHASE_BLOCK_DIM == SHARED_POLY_BLOCK  # the buffer's rows are laid out for the pair kernels' block
    shapes_list = SETS[shape_set]()
    shapes = ShapeSet(shapes_list, device=device, precision="float32")
    pose_scalar = wp.float32 if precision == "float32" else wp.float64
    sa, sb, pa, pb = random_pairs(shapes_list, np.random.default_rng(7), 1024)
    room = min(shapes.max_poly_bound, 63)  # 63 rows of 64 threads and Warp's tile storage fit a block's 48 KB
    ref = run(shapes, sa, sb, pa, pb, CAPS[0], pose_scalar, device, max_poly=room)
    got = run(shapes, sa, sb, pa, pb, CAPS[0], pose_scalar, device, shared_poly=True, max_poly=room)
    assert (ref["pair_volume"] > 0.0).sum() > 0.3 * len(sa)
    assert_same_bits(got, ref, "shared polygon buffer")
    with pytest.raises(ValueError, match="shared polygon buffer needs float32 clipping and at most 48896 bytes"):
        make_narrowphase(wp.float32, 64, shapes.max_faces, shared_poly=True)
    with pytest.raises(ValueError, match="shared polygon buffer needs float32 clipping"):
        make_narrowphase(wp.float64, 20, shapes.max_faces, shared_poly=True)


def cuda_binary(kernel, arch=90):
    """Compile ``kernel``'s module for sm_``arch`` with Warp's NVRTC (no GPU needed), at the pair kernels' block."""
    import tempfile

    module = kernel.module
    with tempfile.TemporaryDirectory() as tmp:
        # Warp's own static shared memory (its tile storage) is sized by the block the module compiles for
        options = module.resolve_options(wp.config, block_dim=NARROWPHASE_BLOCK_DIM)
        module._compile(device=None, output_dir=tmp, output_arch=arch, use_ptx=False, options=options)


def test_the_largest_shared_polygon_buffer_compiles_for_a_gpu():
    """The most rows :func:`shared_poly_fits` allows compile for an H100/H200 (sm_90) with Warp's own static shared
    memory beside them: on an H200 ptxas refused a 64-vertex buffer, 49,152 B, by Warp's 256 B of tile storage
    (BENCHMARKS.md section 30). Compiled by Warp's NVRTC, which needs no GPU; skipped where it cannot compile."""
    from polydem.kernels.geometry import shared_poly_fits

    rows = max(k for k in range(1, 256) if shared_poly_fits(wp.float32, k))
    try:
        cuda_binary(make_narrowphase(wp.float32, 8, 6).overlap_kernel)
    except Exception as e:  # a Warp build without NVRTC (no CUDA toolkit in the wheel)
        pytest.skip(f"Warp cannot compile CUDA here: {e}")
    cuda_binary(make_narrowphase(wp.float32, rows, 64, shared_poly=True).overlap_kernel)


def thrown_scene(precision="mixed"):
    # Cubes and rocks thrown at each other over a floor plane: pair and wall contacts.
    scene = Scene(dt="auto", precision=precision)
    scene.add_material("m", density=1000.0, law="hertz", k=1.0e6, restitution=0.5, friction=0.5)
    scene.add_shape("cube", ConvexShape.box(0.1))
    scene.add_shape("rock", ConvexShape.rock(n_points=20, size=0.1, seed=3))
    scene.add_plane((0.0, 0.0, 0.0), (0.0, 0.0, 1.0), "m")
    quats = Rotation.random(4, random_state=1).as_quat()
    for i, q in enumerate(quats):
        scene.add_body(
            ("cube", "rock")[i % 2], "m", position=(0.18 * i, 0.0, 0.1), orientation=q,
            velocity=(0.5 * (-1.0) ** i, 0.0, 0.0), angular_velocity=(0.0, 3.0, 0.0),
        )  # fmt: skip
    return scene


def test_simulation_builds_and_steps_with_its_register_cap(device):
    scene = thrown_scene()
    assert Simulation(scene, device).stepper.kernels.pair_contact_kernel.options["cuda_max_registers"] == 128
    runs = []
    for cap in CAPS:
        sim = Simulation(scene, device, pair_max_registers=cap)
        assert sim.stepper.kernels.pair_contact_kernel.options.get("cuda_max_registers") == cap
        sim.step(400)  # 0.14 s: on the floor, and pairs that met
        runs.append((sim.state(), sim.contacts()))
    (state0, contacts0), *others = runs
    assert len(contacts0["volume"]) >= 3
    for state, contacts in others:
        for k in state0:
            assert np.array_equal(state[k], state0[k]), k
        for k in contacts0:
            assert np.array_equal(contacts[k], contacts0[k]), k


@pytest.mark.parametrize("precision", ["mixed", "float64"])
def test_simulation_steps_alike_with_the_shared_polygon_buffer(device, precision):
    """Stepper.set_shared_poly: the pair kernel clips with its polygon buffer in shared memory where it fits (float32
    clipping; float64 keeps the per-thread buffer), and the run is the same bits."""
    from polydem.kernels.geometry import shared_poly_fits

    assert shared_poly_fits(wp.float32, 63) and not shared_poly_fits(wp.float32, 64)
    assert not shared_poly_fits(wp.float64, 8)  # and a grown polygon capacity falls back to the per-thread buffer
    scene = thrown_scene(precision)
    assert Simulation(scene, device).stepper.shared_poly  # the default
    runs = []
    for on in (False, True):
        sim = Simulation(scene, device)
        sim.stepper.set_shared_poly(on)
        assert sim.stepper.kernels.shared_poly is (on and precision == "mixed")
        sim.step(400)
        runs.append((sim.state(), sim.contacts()))
    (state0, contacts0), (state1, contacts1) = runs
    assert len(contacts0["volume"]) >= 3
    for k in state0:
        assert np.array_equal(state1[k], state0[k]), k
    for k in contacts0:
        assert np.array_equal(contacts1[k], contacts0[k]), k
