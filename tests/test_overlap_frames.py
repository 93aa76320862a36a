"""polydem.overlap and contact_forces take poses in the shape's input frame, as scenes do.

Issue: the poses were taken as body-frame poses (centre of mass, principal axes), so a
0.05 x 0.05 x 0.17 box built along z, at the identity orientation, lay on its side (its body x
axis, of least inertia, is its input z axis), and a rock placed where its points were given sat
elsewhere: the README's own example printed V = 0. Here the shapes' input frames differ from their
body frames, and every expectation is a float64 hand calculation, the independent numpy/scipy
reference (tests/reference_geometry.py), the simulator's own contacts of the same scene, or finite
differences.
"""

import contextlib
import io
import re
import warnings
from pathlib import Path

import numpy as np
import pytest
from reference_geometry import reference_overlap
from scipy.spatial.transform import Rotation

from polydem import CompoundShape, ContactLaw, ConvexShape, Scene, Simulation, contact_forces, overlap

README = Path(__file__).resolve().parents[1] / "README.md"
# float32 clips in a pair frame set up in float64: its rounding is ~1e-7 of the bodies' size, which
# the millimetre depths below turn into ~1e-5 of V.
RTOL = {"float64": 1e-9, "float32": 1e-4}
FLOOR = ConvexShape.box(1.0, 1.0, 0.1)  # input frame = body frame; top face at z = 0 at FLOOR_POSE
FLOOR_POSE = np.array([0.0, 0.0, -0.05, 0.0, 0.0, 0.0, 1.0])


def pose(position, rotation=None):
    q = [0.0, 0.0, 0.0, 1.0] if rotation is None else rotation.as_quat()
    return np.concatenate([np.asarray(position, dtype=np.float64), q])


def input_vertices(shape, p):
    """World vertices of ``shape`` whose input frame is placed at pose ``p`` (numpy, float64)."""
    return Rotation.from_quat(p[3:]).apply(shape.to_input_frame(shape.vertices)) + p[:3]


def centre_of_mass(shape, p):
    return p[:3] + Rotation.from_quat(p[3:]).apply(np.array(shape.input_translation))


def standing_box():
    box = ConvexShape.box(0.05, 0.05, 0.17)
    # What the issue is about: the principal frame is not the frame the box was built in.
    assert not np.allclose(box.input_rotation, np.eye(3))
    return box


def offset_box():
    """A 0.06 x 0.15 x 0.2 box given by corners off the origin: centroid (0.13, -0.175, 0.6) in the
    input frame and principal axes that are not the input axes."""
    corners = [[x, y, z] for x in (0.1, 0.16) for y in (-0.25, -0.1) for z in (0.5, 0.7)]
    box = ConvexShape.from_points(np.array(corners), name="offset_box")
    np.testing.assert_allclose(box.input_translation, [0.13, -0.175, 0.6], atol=1e-15)
    assert not np.allclose(box.input_rotation, np.eye(3))
    return box


def tetrahedron():
    """An irregular tetrahedron built 3.7 m from the input origin."""
    pts = np.array([[0.0, 0.0, 0.0], [0.3, 0.0, 0.0], [0.0, 0.2, 0.0], [0.05, 0.04, 0.25]]) + [1.0, 2.0, 3.0]
    return ConvexShape.from_points(pts, name="tet")


# ---------------------------------------------------------------------------- hand calculations


@pytest.mark.parametrize("precision", ["float64", "float32"])
def test_standing_box_pressed_into_a_floor(device, precision):
    """The 0.05 x 0.05 x 0.17 box built along z, at the identity orientation (and turned about z),
    its bottom d below the floor's top: V = 0.0025 d, S_A = (0, 0, -0.0025), the centroid d/2 down
    under the box's axis, the contact point there too, depth d and no torque. Before: the box lay on
    its side, 0.06 m above the floor, and V = 0."""
    box = standing_box()
    rows = [(d, x, y, turn) for d in (1e-3, 1e-2) for x, y, turn in ((0.0, 0.0, 0.0), (0.2, -0.1, 0.5))]
    pa = np.array([pose([x, y, 0.085 - d], Rotation.from_euler("z", turn)) for d, x, y, turn in rows])
    res = overlap(box, pa, FLOOR, FLOOR_POSE, device=device, precision=precision)
    d, x, y = (np.array([r[k] for r in rows]) for k in range(3))
    zero = np.zeros_like(d)
    rtol = RTOL[precision]
    np.testing.assert_allclose(res.volume, 0.0025 * d, rtol=rtol)
    np.testing.assert_allclose(res.area_vector, np.tile([0.0, 0.0, -0.0025], (len(d), 1)), atol=rtol * 0.0025)
    np.testing.assert_allclose(res.area_vector_b, -res.area_vector, atol=rtol * 0.0025)
    np.testing.assert_allclose(res.normal, np.tile([0.0, 0.0, -1.0], (len(d), 1)), atol=rtol)
    np.testing.assert_allclose(res.depth, d, rtol=rtol)
    np.testing.assert_allclose(res.centroid, np.column_stack([x, y, -0.5 * d]), atol=rtol * 0.1)
    np.testing.assert_allclose(res.contact_point, np.column_stack([x, y, -0.5 * d]), atol=rtol * 0.1)
    # The bottom face's moment about the world origin; the side strips' cancel in pairs.
    np.testing.assert_allclose(res.moment, 0.0025 * np.column_stack([-y, x, zero]), atol=rtol * 0.0025)
    np.testing.assert_allclose(res.position_a, np.column_stack([x, y, 0.085 - d]), atol=1e-15)
    law = ContactLaw("hertz", k=1e9)
    f = contact_forces(res, law)
    push = law.derivative(0.0025 * d) * 0.0025
    np.testing.assert_allclose(f.force_a, np.column_stack([zero, zero, push]), rtol=rtol, atol=rtol * push.max())
    np.testing.assert_allclose(f.torque_a, 0.0, atol=rtol * push.max() * 0.17)


@pytest.mark.parametrize("precision", ["float64", "float32"])
def test_box_built_along_z_laid_along_y(device, precision):
    """The same box turned 90 degrees about x lies along y, 0.025 m from the floor's edge at x = 0.5:
    V = 0.17 x 0.05 x d, S_A = (0, 0, -0.0085). Before: it lay along x, 0.035 m over the edge."""
    box = standing_box()
    d = np.array([1e-3, 1e-2])
    pa = np.array([pose([0.45, 0.0, 0.025 - di], Rotation.from_euler("x", 90, degrees=True)) for di in d])
    res = overlap(box, pa, FLOOR, FLOOR_POSE, device=device, precision=precision)
    np.testing.assert_allclose(res.volume, 0.0085 * d, rtol=RTOL[precision])
    np.testing.assert_allclose(res.area_vector, [[0.0, 0.0, -0.0085]] * 2, atol=RTOL[precision] * 0.0085)
    np.testing.assert_allclose(res.centroid, np.column_stack([[0.45, 0.45], [0.0, 0.0], -0.5 * d]), atol=1e-5)


@pytest.mark.parametrize("precision", ["float64", "float32"])
def test_box_given_off_its_origin_pressed_into_a_floor(device, precision):
    """A box whose corners were given off the origin, placed by its input frame: at the identity it
    covers x 0.3..0.36, y 0.05..0.2 and its bottom is d into the floor; turned 90 degrees about x, it
    covers x 0.1..0.16, y -0.1..0.1. V, S_A, the centroid and the centre of mass by hand."""
    box = offset_box()
    turn = Rotation.from_euler("x", 90, degrees=True)
    d = 2e-3
    pa = np.array([pose([0.2, 0.3, -0.5 - d]), pose([0.0, 0.6, 0.25 - d], turn)])
    res = overlap(box, pa, FLOOR, FLOOR_POSE, device=device, precision=precision)
    rtol = RTOL[precision]
    np.testing.assert_allclose(res.volume, [0.06 * 0.15 * d, 0.06 * 0.2 * d], rtol=rtol)
    np.testing.assert_allclose(res.area_vector, [[0.0, 0.0, -0.009], [0.0, 0.0, -0.012]], atol=rtol * 0.01)
    np.testing.assert_allclose(res.centroid, [[0.33, 0.125, -d / 2], [0.13, 0.0, -d / 2]], atol=rtol * 0.1)
    np.testing.assert_allclose(res.position_a, [[0.33, 0.125, 0.1 - d], [0.13, 0.0, 0.075 - d]], atol=1e-15)
    np.testing.assert_allclose(res.depth, d, rtol=rtol)


def test_body_frame_keeps_the_old_poses(device):
    """frame="body" places the centre of mass and the principal axes: the box at the identity lies
    on its side (its long body x axis along world x), V = 0.17 x 0.05 x d. At the body poses that
    Scene.add_body stores for input-frame poses, it gives what frame="input" gives for those."""
    box = standing_box()
    d = 1e-3
    res = overlap(box, pose([0.0, 0.0, 0.025 - d]), FLOOR, FLOOR_POSE, frame="body", device=device,
                  precision="float64")  # fmt: skip
    np.testing.assert_allclose(res.volume, 0.0085 * d, rtol=1e-9)
    np.testing.assert_allclose(res.area_vector[0], [0.0, 0.0, -0.0085], atol=1e-12)
    rng = np.random.default_rng(3)
    rock = ConvexShape.rock(n_points=18, size=0.3, seed=6)
    for a in (box, offset_box(), tetrahedron(), rock):
        pa = pose(rng.normal(size=3), Rotation.random(random_state=int(rng.integers(1 << 30))))
        pb = pose(centre_of_mass(a, pa) + 0.02 * rng.normal(size=3) - rock.input_translation)
        scene = Scene(gravity=(0.0, 0.0, 0.0))
        scene.add_material("stone", density=2500.0, law="hertz", k=1e8, restitution=0.5, friction=0.0)
        scene.add_body(a, "stone", pa[:3], pa[3:])
        scene.add_body(rock, "stone", pb[:3], pb[3:])
        body = np.hstack([scene.body_position, scene.body_orientation])
        got = overlap(a, pa, rock, pb, device=device, precision="float64")
        old = overlap(a, body[0], rock, body[1], frame="body", device=device, precision="float64")
        assert got.volume[0] > 0.0
        np.testing.assert_allclose(got.volume, old.volume, rtol=1e-12)
        np.testing.assert_allclose(got.area_vector, old.area_vector, atol=1e-12)
        np.testing.assert_allclose(got.moment, old.moment, atol=1e-12)
        np.testing.assert_allclose(got.contact_point, old.contact_point, atol=1e-12)
        np.testing.assert_allclose(got.position_a, body[:1, :3], atol=1e-15)
        np.testing.assert_allclose(got.position_b, body[1:, :3], atol=1e-15)


def test_unknown_frame_is_refused():
    c = ConvexShape.box(1.0)
    good = pose([0, 0, 0])
    for frame in ("world", "Input", None, 1):
        with pytest.raises(ValueError, match=r"frame must be 'input' .* or 'body'"):
            overlap(c, good, c, good, frame=frame)


# ---------------------------------------------------------------------------- against references


def random_input_poses(rng, a, b, n):
    """n input-frame pose pairs whose centres of mass lie 0.1 to 0.9 of the sum of the radii apart."""
    pa = np.hstack(
        [rng.uniform(-2.0, 2.0, size=(n, 3)), Rotation.random(n, random_state=rng.integers(1 << 30)).as_quat()]
    )
    qb = Rotation.random(n, random_state=rng.integers(1 << 30))
    u = rng.normal(size=(n, 3))
    u /= np.linalg.norm(u, axis=1, keepdims=True)
    cb = np.array([centre_of_mass(a, p) for p in pa]) + u * rng.uniform(0.1, 0.9, (n, 1)) * (a.radius + b.radius)
    pb = np.hstack([cb - qb.apply(np.array(b.input_translation)), qb.as_quat()])
    return pa, pb


@pytest.mark.parametrize("precision", ["float64", "float32"])
def test_shapes_off_their_input_origin_against_the_reference(device, precision):
    """An irregular tetrahedron 3.7 m from its input origin against the offset box and a rock, at
    random input-frame poses: V, S_A, S_B, M_A (about the world origin), the centroid and the centres
    of mass against the float64 numpy/scipy reference of the hulls of their input-frame vertices."""
    rng = np.random.default_rng(12)
    tet = tetrahedron()
    touching = 0
    for b in (offset_box(), ConvexShape.rock(n_points=16, size=0.4, seed=2)):
        pa, pb = random_input_poses(rng, tet, b, 25)
        res = overlap(tet, pa, b, pb, device=device, precision=precision)
        scale = 2.0 * max(tet.radius, b.radius)
        tol = RTOL[precision] * 10.0
        for i in range(len(pa)):
            ref = reference_overlap(input_vertices(tet, pa[i]), input_vertices(b, pb[i]))
            touching += ref["volume"] > 1e-6 * scale**3
            assert abs(res.volume[i] - ref["volume"]) <= tol * scale**3
            np.testing.assert_allclose(res.area_vector[i], ref["area_vector"], atol=tol * scale**2)
            np.testing.assert_allclose(res.area_vector_b[i], ref["area_vector_b"], atol=tol * scale**2)
            # The positions are metres from the origin: compare the moments about A's centre.
            arm = np.cross(res.position_a[i], res.area_vector[i] - ref["area_vector"])
            np.testing.assert_allclose(res.moment[i] - ref["moment"] - arm, 0.0, atol=tol * scale**3)
            if ref["volume"] > 1e-4 * scale**3:
                np.testing.assert_allclose(res.centroid[i], ref["centroid"], atol=1e3 * tol * scale)
        np.testing.assert_allclose(res.position_a, [centre_of_mass(tet, p) for p in pa], atol=1e-14)
        np.testing.assert_allclose(res.position_b, [centre_of_mass(b, p) for p in pb], atol=1e-14)
    assert touching > 20


def test_compound_grain_placed_by_its_input_frame(device):
    """A grain of two boxes that partition the offset box, placed by the frame its parts were given
    in, overlaps a rock as the whole box does in the reference."""
    whole = offset_box()
    parts = [
        ConvexShape.from_points(np.array([[x, y, z] for x in xs for y in (-0.25, -0.1) for z in (0.5, 0.7)]))
        for xs in ((0.1, 0.13), (0.13, 0.16))
    ]
    grain = CompoundShape(parts, name="split_offset_box")
    np.testing.assert_allclose(grain.input_translation, whole.input_translation, atol=1e-14)
    rock = ConvexShape.rock(n_points=16, size=0.4, seed=2)
    rng = np.random.default_rng(5)
    pa, pb = random_input_poses(rng, whole, rock, 20)
    res = overlap(grain, pa, rock, pb, device=device, precision="float64")
    touching = 0
    for i in range(len(pa)):
        ref = reference_overlap(input_vertices(whole, pa[i]), input_vertices(rock, pb[i]))
        touching += ref["volume"] > 1e-7
        assert abs(res.volume[i] - ref["volume"]) <= 1e-12
        np.testing.assert_allclose(res.area_vector[i], ref["area_vector"], atol=1e-10)
    assert touching > 10
    np.testing.assert_allclose(res.position_a, [centre_of_mass(whole, p) for p in pa], atol=1e-14)


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_same_contact_as_the_simulator_for_the_same_scene(device, seed):
    """The scene's bodies at input-frame poses: overlap() and contact_forces() give the volume,
    depth, normal, contact point and normal force of the simulator's own contacts before any step
    (float64, at rest, so no damping)."""
    rng = np.random.default_rng(seed)
    tet, box = tetrahedron(), offset_box()
    k = 1e8
    pa, pb = random_input_poses(rng, tet, box, 100)
    res = overlap(tet, pa, box, pb, device=device, precision="float64")
    # Shallow enough for the scene to accept; deep enough to be a contact of some size.
    i = np.flatnonzero((res.volume > 1e-3 * tet.volume) & (res.volume < 0.05 * tet.volume) & ~res.enclosed)[0]
    pa, pb = pa[i], pb[i]
    res = overlap(tet, pa, box, pb, device=device, precision="float64")
    scene = Scene(gravity=(0.0, 0.0, 0.0), precision="float64", name="frames")
    scene.add_material("stone", density=2500.0, law="hertz", k=k, restitution=0.5, friction=0.0)
    scene.add_shape("tet", tet)
    scene.add_shape("box", box)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # the bodies start overlapping
        scene.add_body("tet", "stone", pa[:3], pa[3:])
        scene.add_body("box", "stone", pb[:3], pb[3:])
        sim = Simulation(scene, device=device)
    c = sim.contacts()
    assert len(c["volume"]) == 1
    sign = 1.0 if (c["body_a"][0], c["body_b"][0]) == (0, 1) else -1.0
    assert (c["body_a"][0], c["body_b"][0]) in ((0, 1), (1, 0))
    f = contact_forces(res, ContactLaw("hertz", k=k))
    np.testing.assert_allclose(c["volume"], res.volume, rtol=1e-10)
    np.testing.assert_allclose(c["depth"], res.depth, rtol=1e-10)
    np.testing.assert_allclose(sign * c["normal"][0], res.normal[0], atol=1e-10)
    np.testing.assert_allclose(c["point"][0], res.contact_point[0], atol=1e-10)
    np.testing.assert_allclose(c["normal_force"][0], np.linalg.norm(f.force_a[0]), rtol=1e-9)
    state = sim.state()
    np.testing.assert_allclose(state["body_position"], [res.position_a[0], res.position_b[0]], atol=1e-14)


# ---------------------------------------------------------------------------- torques


def turned_about(p, centre, rotation):
    """Input-frame pose ``p`` turned by ``rotation`` (world axes) about the point ``centre``."""
    out = p.copy()
    out[:3] = centre + rotation.apply(p[:3] - centre)
    out[3:] = (rotation * Rotation.from_quat(p[3:])).as_quat()
    return out


def test_torques_about_the_centres_of_mass_are_the_gradients_of_v(device):
    """Turning A (B) by a small angle about its centre of mass, at input-frame poses: the finite
    difference of V is M_A - x_A x S_A (M_B - x_B x S_B) with x the reported centre of mass, and,
    under the linear law W = V (W' = 1), minus the reported torque_a (torque_b). Translations give
    S_A. Before: the centre of mass was taken at the input origin, which for this tetrahedron is
    3.7 m away."""
    tet, rock = tetrahedron(), ConvexShape.rock(n_points=20, size=0.4, seed=8)
    rng = np.random.default_rng(4)
    pa, pb = random_input_poses(rng, tet, rock, 40)
    res = overlap(tet, pa, rock, pb, device=device, precision="float64")
    f = contact_forces(res, ContactLaw("linear", k=1.0))
    rows = np.flatnonzero((res.volume > 1e-3 * tet.volume) & ~res.enclosed)[:6]
    assert len(rows) >= 4
    h = 1e-6
    for i in rows:
        ca, cb = centre_of_mass(tet, pa[i]), centre_of_mass(rock, pb[i])
        np.testing.assert_allclose(res.position_a[i], ca, atol=1e-14)
        turned_a, turned_b, moved_a = [], [], []
        for axis in np.eye(3):
            for sign in (1.0, -1.0):
                turn = Rotation.from_rotvec(sign * h * axis)
                turned_a.append(turned_about(pa[i], ca, turn))
                turned_b.append(turned_about(pb[i], cb, turn))
                moved_a.append(np.concatenate([pa[i, :3] + sign * h * axis, pa[i, 3:]]))
        va = overlap(tet, np.array(turned_a + moved_a), rock, pb[i], device=device, precision="float64").volume
        vb = overlap(tet, pa[i], rock, np.array(turned_b), device=device, precision="float64").volume
        grad_rot_a = (va[0:6:2] - va[1:6:2]) / (2 * h)
        grad_move_a = (va[6:12:2] - va[7:12:2]) / (2 * h)
        grad_rot_b = (vb[0::2] - vb[1::2]) / (2 * h)
        atol = 1e-6 * tet.radius**3
        np.testing.assert_allclose(grad_move_a, res.area_vector[i], atol=atol)
        np.testing.assert_allclose(grad_rot_a, res.moment[i] - np.cross(ca, res.area_vector[i]), atol=atol)
        np.testing.assert_allclose(grad_rot_a, -f.torque_a[i], atol=atol)
        np.testing.assert_allclose(grad_rot_b, res.moment_b[i] - np.cross(cb, res.area_vector_b[i]), atol=atol)
        np.testing.assert_allclose(grad_rot_b, -f.torque_b[i], atol=atol)


# ---------------------------------------------------------------------------- the README


def test_readme_example_prints_what_the_readme_says(device):
    """The README's overlap example, run as written (on each test device), prints a real contact
    and exactly the lines its comments show."""
    text = README.read_text()
    block = re.search(r"```python\n(.*?)\n# A simulation", text, re.S)
    assert block, "the README's Python block with the overlap example is missing"
    code = block.group(1)
    lines = code.splitlines()
    last_print = max(k for k, line in enumerate(lines) if line.startswith("print("))
    shown = [line[2:] for line in lines[last_print + 1 :] if line.startswith("# ")]
    assert len(shown) == 3
    out = io.StringIO()
    with contextlib.redirect_stdout(out):
        exec(code.replace('device="cpu"', f'device="{device}"'), {})
    # Warp may log its module loads to stdout first.
    assert out.getvalue().splitlines()[-len(shown) :] == shown
    assert not shown[0].startswith("V 0 ")
