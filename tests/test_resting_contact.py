"""Resting contacts, enclosed pairs and penetration depth: float32 against float64 and closed forms.

A packing is made of resting contacts: flat faces a few 1e-7 of their size into each other, on
partners of any size. These tests hold float32 to float64 there, check the push of a body wholly
inside another (out through the nearest face, continuous with the force before it sank in), and
the penetration depth against a numpy reference.
"""

import functools

import numpy as np
import pytest
import warp as wp
from polydem.kernels.geometry import make_geometry, make_primitives
from polydem.kernels.narrowphase import BatchPairs, launch_overlap
from reference_geometry import halfspaces_from_points
from scipy.spatial import ConvexHull
from scipy.spatial.transform import Rotation

from polydem import ContactLaw, ConvexShape, contact_forces, overlap
from polydem.shapeset import ShapeSet

F64 = wp.float64
VEC3D = wp.types.vector(3, F64)
TRANSFORM64 = wp.types.transformation(F64)


def f32(x):
    return float(np.float32(x))


def pose(position, rotation=None):
    q = [0.0, 0.0, 0.0, 1.0] if rotation is None else rotation.as_quat()
    return np.concatenate([np.asarray(position, dtype=np.float64), q])


def world(shape, p):
    return Rotation.from_quat(p[3:]).apply(np.array(shape.vertices)) + p[:3]


def projected_area(points, u):
    """Area of the shadow of the hull of ``points`` along the unit vector ``u``."""
    hull = ConvexHull(points)
    p = hull.points[hull.simplices]
    return 0.25 * np.abs(np.cross(p[:, 1] - p[:, 0], p[:, 2] - p[:, 0]) @ u).sum()


def resting_cubes(cube, floors, rel_depths, tilts):
    """Poses of a cube lying face down on each floor box (its centre half a thickness below the
    top face z = 0), tilted about x, its lowest vertex rel_depth * edge below the top face."""
    edge = np.ptp(np.array(cube.vertices)[:, 0])
    rows = []
    for floor, xy in floors:
        thickness = np.ptp(np.array(floor.vertices)[:, 2])
        for tilt in tilts:
            rot = Rotation.from_rotvec([tilt, 0.3 * tilt, 0.0])
            low = rot.apply(np.array(cube.vertices))[:, 2].min()
            for rel in rel_depths:
                rows.append((floor, pose([*xy, -low - rel * edge], rot), pose([0.0, 0.0, -0.5 * thickness])))
    return rows


def test_float32_flat_contact_force_follows_float64(device):
    """A 1 cm cube flat (tilt 0, 1e-7, 1e-4 rad) on a 20 cm and an 18 m floor box, 1e-6 to 1e-2 of
    its edge deep, Hertz k = 1e9: the float32 force follows float64 from 1e-6 of the edge up, to
    1e-3 of itself. Before: 0 N in float32 at 1e-6 and 1e-5 of the edge (float64: 0.1 and 0.32 N),
    and up to 1e-4 of the edge on the 18 m box (the coplanar rule dropped the faces from S_A; the
    0.5 m between the floor's centre and its top face ate a 1e-8 m depth in float32). Midway, with
    the float64 set-up but float32 shape tables, the decimal sizes alone (0.018 m is 4e-10 m off in
    float32) left 2.7% at 1e-6 of the edge flat and 10% tilted by 1e-4."""
    cube = ConvexShape.box(0.01)
    small_floor = ConvexShape.box(0.2, 0.2, 0.018)
    tilts, rtol = (0.0, 1e-7, 1e-4), 1e-3
    big_floor = ConvexShape.box(18.0, 18.0, 1.0)
    floors = [(small_floor, (0.013, -0.021)), (small_floor, (0.08, 0.05)), (big_floor, (0.013, -0.021))]
    floors.append((big_floor, (7.31, -4.2)))
    rel_depths = (1e-6, 1e-5, 1e-4, 1e-3, 1e-2)
    rows = resting_cubes(cube, floors, rel_depths, tilts)
    law = ContactLaw("hertz", k=1e9)
    force = {}
    for precision in ("float32", "float64"):
        fz = []
        for floor in (small_floor, big_floor):
            sel = [r for r in rows if r[0] is floor]
            res = overlap(cube, np.array([r[1] for r in sel]), floor, np.array([r[2] for r in sel]), device=device,
                          precision=precision)  # fmt: skip
            assert not res.enclosed.any()
            f = contact_forces(res, law).force_a
            # Pushed straight up (the tilt leans it by at most 1e-4).
            assert (np.abs(f[:, :2]) <= 2e-4 * f[:, 2:3] + 1e-12).all()
            fz.append(f[:, 2])
        force[precision] = np.concatenate(fz)
    assert (force["float64"] > 0.0).all()
    np.testing.assert_allclose(force["float32"], force["float64"], rtol=rtol)


@pytest.mark.parametrize("precision", ["float32", "float64"])
def test_plates_overlapping_by_half_their_thickness(device, precision):
    """Two 1 x 1 x 1e-6 m plates, one 0.5 um above the other: V = 5e-7 m^3 and S_A = -S_B = the
    plate's face. Before: float32 V = 6.7e-7 with S = 0 (the top faces, 0.5 um apart, were taken
    as coincident, and the opposite faces left out of S)."""
    plate = ConvexShape.box(1.0, 1.0, 1e-6)
    turn = Rotation.from_rotvec([0.3, -0.7, 0.4])
    up = turn.apply([0.0, 0.0, 1.0])
    pa = np.array([pose([0, 0, 0]), pose([3.0, -2.0, 1.0], turn)])
    pb = np.array([pose([0, 0, 0.5e-6]), pose(np.array([3.0, -2.0, 1.0]) + 0.5e-6 * up, turn)])
    res = overlap(plate, pa, plate, pb, device=device, precision=precision)
    np.testing.assert_allclose(res.volume, 5e-7, rtol=1e-3)
    normal = np.array([[0.0, 0.0, 1.0], up])
    np.testing.assert_allclose(res.area_vector, normal, atol=1e-3)
    np.testing.assert_allclose(res.area_vector_b, -normal, atol=1e-3)
    assert not res.enclosed.any()


@pytest.mark.parametrize("precision", ["float32", "float64"])
def test_plate_barely_inside_a_big_cube(device, precision):
    """A 1 x 1 x 1e-6 m plate 0.1 um into the top of a 1 m cube, over 0.9 x 0.8 m of it:
    V = 7.2e-8 m^3, S_A = -0.72 z = -S_B. Before: float32 S_A = 0 while S_B = (0, 0, 0.36)."""
    plate = ConvexShape.box(1.0, 1.0, 1e-6)
    big = ConvexShape.box(1.0)
    res = overlap(plate, pose([0.1, 0.2, 0.5 + 0.5e-6 - 1e-7]), big, pose([0, 0, 0]), device=device,
                  precision=precision)  # fmt: skip
    np.testing.assert_allclose(res.volume[0], 7.2e-8, rtol=1e-3)
    np.testing.assert_allclose(res.area_vector[0], [0.0, 0.0, -0.72], atol=1e-4)
    np.testing.assert_allclose(res.area_vector_b[0], [0.0, 0.0, 0.72], atol=1e-4)


@pytest.mark.parametrize("precision", ["float32", "float64"])
@pytest.mark.parametrize("law", [ContactLaw("linear", 1e6), ContactLaw("hertz", 1e9)])
def test_cube_sinking_into_a_plate_leaves_through_the_nearest_face(device, precision, law):
    """A 2 cm cube sinks into a 1 x 1 x 0.05 m plate at x = 0.4: pushed up, through the top face,
    while its centre is above the plate's middle plane and down below it; the force W'(V) |S|
    does not jump where the cube goes wholly in. Before: (100, 0, 0)-like sideways pushes inside
    the plate and a jump by 1e4 at the switch to the enclosed push."""
    cube = ConvexShape.box(0.02)
    plate = ConvexShape.box(1.0, 1.0, 0.05)
    # The cube's bottom face enters the plate at z = 0.035; it is wholly in below z = 0.015.
    z = np.array([0.03, 0.02, 0.015 + 1e-6, 0.015 - 1e-6, 0.01, 0.004, -0.004, -0.01, -0.02, -0.03])
    pa = np.array([pose([0.4, 0.0, zi]) for zi in z])
    res = overlap(cube, pa, plate, pose([0, 0, 0]), device=device, precision=precision)
    f = contact_forces(res, law).force_a
    area = 4e-4
    expected_dir = np.where(z > 0.0, 1.0, -1.0)
    np.testing.assert_allclose(f[:, :2], 0.0, atol=1e-6 * np.abs(f[:, 2]).max())
    np.testing.assert_allclose(np.sign(f[:, 2]), expected_dir)
    np.testing.assert_allclose(np.abs(f[:, 2]), law.derivative(res.volume) * area, rtol=1e-3)
    inside = np.abs(z) < 0.015
    assert (res.enclosed == inside).all()
    # Across the switch (z = 0.015 +- 1e-6): the same force to within a few per cent.
    assert abs(f[3, 2] / f[2, 2] - 1.0) < 0.02


@functools.cache
def wall_kernel(scalar, pose_scalar):
    prim = make_primitives(scalar, pose_scalar)
    vec3 = prim.vec3
    vec3p = wp.types.vector(3, pose_scalar)
    transform = wp.types.transformation(pose_scalar)

    @wp.kernel(enable_backward=False, module="unique")
    def kernel(
        shapes: prim.shapes,
        poses: wp.array(dtype=transform),
        normal: vec3p,
        offset: pose_scalar,
        out: wp.array2d(dtype=vec3),
        volume: wp.array(dtype=scalar),
        depth: wp.array(dtype=scalar),
    ):
        i = wp.tid()
        vol, vol_c, s_a, m_a, fb = prim.plane_geometry(shapes, 0, poses[i], normal, offset)
        volume[i] = vol
        out[i, 0] = s_a
        out[i, 1] = fb
        depth[i] = prim.plane_depth(shapes, 0, poses[i], normal, offset)

    return kernel


def run_wall(shape, poses, normal, offset, device, precision, pose_precision="float64"):
    shapes = ShapeSet([shape], device=device, precision=precision)
    scalar = shapes.scalar
    pose_scalar = wp.float64 if pose_precision == "float64" else wp.float32
    np_pose = np.float64 if pose_precision == "float64" else np.float32
    vec3 = wp.types.vector(3, scalar)
    n = len(poses)
    out = wp.zeros((n, 2), dtype=vec3, device=device)
    volume = wp.zeros(n, dtype=scalar, device=device)
    depth = wp.zeros(n, dtype=scalar, device=device)
    wp.launch(
        wall_kernel(scalar, pose_scalar),
        dim=n,
        inputs=[
            *shapes.kernel_args(),
            wp.array(np.asarray(poses, dtype=np_pose), dtype=wp.types.transformation(pose_scalar), device=device),
            wp.types.vector(3, pose_scalar)(*normal),
            pose_scalar(offset),
        ],
        outputs=[out, volume, depth],
        device=device,
    )
    return volume.numpy().astype(np.float64), out.numpy().astype(np.float64), depth.numpy().astype(np.float64)


@pytest.mark.parametrize("precision", ["float32", "float64"])
def test_body_wholly_inside_a_wall(device, precision):
    """A cube sinking face first through a wall n.x <= offset: just before its top face goes in,
    S_A = -(face area) n; just after, the fallback pushes it out along n with its projected area,
    the same. A turned rock wholly in: -(its projected area along n) n. Before: pushed along n
    with the effective area V^(2/3) (a jump by 1.1 for this cube, by 1e4 at the threshold)."""
    n = np.array([0.3, -0.5, 0.8])
    n /= np.linalg.norm(n)
    offset = 2.0
    side = np.array([0.5, 0.2, -0.1]) - np.dot([0.5, 0.2, -0.1], n) * n
    cube = ConvexShape.box(0.1)
    face_up = Rotation.align_vectors([n], [[0.0, 0.0, 1.0]])[0]
    # Centre 0.05 -+ 1e-6 below the wall: the top face just out, just in.
    poses = np.array([pose((offset - 0.05 + dz) * n + side, face_up) for dz in (1e-6, -1e-6)])
    vol, out, _ = run_wall(cube, poses, n, offset, device, precision)
    s_a, fb = out[:, 0], out[:, 1]
    np.testing.assert_allclose(vol, cube.volume, rtol=1e-3)
    assert np.linalg.norm(fb[0]) == 0.0
    np.testing.assert_allclose(s_a[0], -0.01 * n, atol=1e-3 * 0.01)
    np.testing.assert_allclose(fb[1], -0.01 * n, atol=1e-3 * 0.01)

    rock = ConvexShape.rock(n_points=20, size=0.3, seed=3)
    turn = Rotation.from_rotvec([0.4, 0.1, -0.9])
    vol, out, _ = run_wall(rock, pose((offset - 0.5) * n + side, turn)[None], n, offset, device, precision)
    np.testing.assert_allclose(vol[0], rock.volume, rtol=1e-4)
    p_area = projected_area(turn.apply(np.array(rock.vertices)), n)
    np.testing.assert_allclose(out[0, 1], -p_area * n, atol=1e-4 * p_area)


def depth_reference(a_pts, b_pts):
    """The penetration depth by brute force: the least overlap of the two hulls' extents over the
    face normals and the cross products of every pair of vertex-to-vertex directions (a superset of
    the edge directions: no axis gives less than the depth, and the separating-axis theorem puts the
    depth on a face normal or an edge-edge axis); 0 when an axis separates them."""
    normals = [halfspaces_from_points(a_pts)[0], halfspaces_from_points(b_pts)[0]]
    ia, ja = np.triu_indices(len(a_pts), 1)
    ib, jb = np.triu_indices(len(b_pts), 1)
    da = a_pts[ja] - a_pts[ia]
    db = b_pts[jb] - b_pts[ib]
    cross = np.cross(da[:, None, :], db[None, :, :]).reshape(-1, 3)
    norm = np.linalg.norm(cross, axis=1)
    normals.append(cross[norm > 1e-9] / norm[norm > 1e-9, None])
    axes = np.vstack(normals)
    pa = a_pts @ axes.T
    pb = b_pts @ axes.T
    overlap = np.minimum(pa.max(axis=0) - pb.min(axis=0), pb.max(axis=0) - pa.min(axis=0))
    return max(0.0, overlap.min())


def test_depth_of_crossing_edges(device):
    """Two cubes turned 45 degrees about x and about y, so that an edge of one crosses an edge of
    the other 2 mm deep: no vertex of either lies inside the other (the deepest vertex gave 0) and
    every face normal shows an overlap of more than 2 mm (the face normals alone overestimated)."""
    cube = ConvexShape.box(0.1, 0.1, 0.1)
    half_diag = 0.05 * np.sqrt(2.0)
    pa = np.array([[0.0, 0.0, 0.0, *Rotation.from_rotvec([np.pi / 4, 0.0, 0.0]).as_quat()]])
    pb = np.array([[0.0, 0.0, 2 * half_diag - 0.002, *Rotation.from_rotvec([0.0, np.pi / 4, 0.0]).as_quat()]])
    res = overlap(cube, pa, cube, pb, device=device, precision="float64")
    assert res.volume[0] > 0.0
    assert res.depth[0] == pytest.approx(0.002, abs=1e-12)
    assert depth_reference(world(cube, pa[0]), world(cube, pb[0])) == pytest.approx(0.002, abs=1e-12)


@pytest.mark.parametrize("precision", ["float32", "float64"])
def test_depth_against_numpy(device, precision):
    """overlap().depth is the shortest separating translation, on random poses (0 where V = 0)."""
    rng = np.random.default_rng(11)
    a = ConvexShape.rock(n_points=16, size=1.0, seed=4)
    b = ConvexShape.box(1.2, 0.7, 0.4)
    n = 40
    pa = np.hstack([rng.normal(size=(n, 3)) + 5.0, Rotation.random(n, random_state=1).as_quat()])
    d = rng.normal(size=(n, 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    pb = np.hstack([pa[:, :3] + d * rng.uniform(0.1, 1.2, size=(n, 1)), Rotation.random(n, random_state=2).as_quat()])
    res = overlap(a, pa, b, pb, frame="body", device=device, precision=precision)  # world() takes body frames
    ref = np.array([depth_reference(world(a, pa[i]), world(b, pb[i])) for i in range(n)])
    ref[res.volume <= 0.0] = 0.0
    assert (ref > 0.0).sum() > 10 and (ref == 0.0).sum() > 3
    tol = 1e-12 if precision == "float64" else 1e-6
    np.testing.assert_allclose(res.depth, ref, atol=tol)


@pytest.mark.parametrize("precision", ["float32", "float64"])
def test_wall_depth_against_numpy(device, precision):
    """plane_depth: offset - min n.v over the vertices, 0 when the body does not reach the wall."""
    rock = ConvexShape.rock(n_points=20, size=0.5, seed=8)
    rng = np.random.default_rng(2)
    n = np.array([0.2, 0.4, -0.9])
    n /= np.linalg.norm(n)
    offset = -1.5
    poses = np.hstack([offset * n + rng.normal(size=(30, 3)) * 0.3, Rotation.random(30, random_state=5).as_quat()])
    _, _, depth = run_wall(rock, poses, n, offset, device, precision)
    ref = np.array([max(0.0, offset - (world(rock, p) @ n).min()) for p in poses])
    assert (ref > 0.0).sum() > 5 and (ref == 0.0).sum() > 3
    np.testing.assert_allclose(depth, ref, atol=1e-12 if precision == "float64" else 1e-6)


def test_mixed_precision_far_from_the_origin(device):
    """float64 poses, float32 clipping (make_geometry's pose_scalar): a 1 cm cube resting 1e-6 of
    its edge deep on an 18 m floor 1 km from the origin gets the overlap it gets at the origin."""
    cube = ConvexShape.box(f32(0.01))
    floor = ConvexShape.box(18.0, 18.0, 1.0)
    shapes = ShapeSet([cube, floor], device=device, precision="float32")
    vec3 = wp.types.vector(3, wp.float32)
    rows = {}
    for far in (0.0, 1000.0):
        shift = np.array([far, -far, far])
        pa = pose(shift + [2.1, 0.3, f32(0.005) - 1e-8], Rotation.from_rotvec([1e-7, 0.0, 0.0]))
        pb = pose(shift + [0.0, 0.0, -0.5])
        out = {k: wp.zeros(1, dtype=vec3, device=device) for k in
               ("pair_volume_moment", "pair_area_a", "pair_moment_a", "pair_area_b", "pair_moment_b")}  # fmt: skip
        out["pair_volume"] = wp.zeros(1, dtype=wp.float32, device=device)
        launch_overlap(
            shapes,
            BatchPairs(
                wp.zeros(1, dtype=int, device=device),
                wp.ones(1, dtype=int, device=device),
                wp.array(pa[None], dtype=TRANSFORM64, device=device),
                wp.array(pb[None], dtype=TRANSFORM64, device=device),
            ),
            out=out,
            pose_scalar=wp.float64,
        )
        rows[far] = (out["pair_volume"].numpy()[0], out["pair_area_a"].numpy()[0])
    v0, s0 = rows[0.0]
    v1, s1 = rows[1000.0]
    assert v0 > 0.0
    np.testing.assert_allclose(v1, v0, rtol=1e-3)
    np.testing.assert_allclose(s1, s0, atol=1e-3 * 1e-4)
    # And the geometry factory takes float64 poses for the pair depth as well.
    assert make_geometry(wp.float32, 8, 6, pose_scalar=wp.float64).transform == TRANSFORM64
