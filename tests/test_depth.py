"""Resting depths (polydem.scene.depth) against closed forms, clipped hulls, the contact kernel and the CLI.

A body pressed into a flat face by a load F rests where W'(V(d)) |S(d)| = F. depth.py computes V(d) and
|S(d)| from the hull and solves for d; here the cube's caps are held to their closed forms, any hull's to
scipy's clipped hull, and the depths to the simulator's own force: polydem.overlap + contact_forces (no toe)
and a Simulation's contacts (with the resolved toe of its time step), bracketing d within 1e-3.
"""

import math
import re
from pathlib import Path

import numpy as np
import pytest
from cli_helpers import run
from scipy.spatial import ConvexHull
from scipy.spatial.transform import Rotation

from polydem import ContactLaw, ConvexShape, Scene, Simulation, contact_forces, overlap
from polydem.scene import SceneWarning, depth

REPO = Path(__file__).resolve().parent.parent
EDGE = 0.01
RTOL = 1e-3  # of a depth: the kernel's force at d (1 - RTOL) is below the load, at d (1 + RTOL) above


def pose_pressed(shape, direction, d):
    """Pose (7,) of ``shape`` turned so that its body-frame ``direction`` points down (-z), its lowest point
    ``d`` below z = 0."""
    u = np.asarray(direction) / np.linalg.norm(direction)
    rot, _ = Rotation.align_vectors([[0.0, 0.0, -1.0]], [u])
    reach = float(np.max(np.asarray(shape.vertices) @ u))
    return np.concatenate([[0.0, 0.0, reach - d], rot.as_quat()])


def test_cube_caps_follow_the_closed_forms():
    """A cube's face, edge (at 45 degrees) and corner (along a body diagonal) caps: V = c d^j and
    |S| = j c d^(j-1) over the range where they hold, and the closed-form depths of every law."""
    cube = ConvexShape.box(EDGE)
    checked = 0
    for feature in depth.FEATURES:
        c, j, d_max = depth.cube_cap(EDGE, feature)
        cuts = depth.shape_cuts(cube, feature)
        assert len(cuts) == {"face": 6, "edge": 12, "corner": 8}[feature]
        for cut in cuts:
            for d in d_max * np.array([1e-9, 1e-4, 0.1, 0.5, 0.999]):
                v, s = cut.cap(d)
                assert v == pytest.approx(c * d**j, rel=1e-12)
                assert s == pytest.approx(j * c * d ** (j - 1), rel=1e-12)
        for law, m in (("hertz", None), ("linear", None), ("power", 1.25), ("power", 2.5)):
            mm = {"hertz": 1.5, "linear": 1.0}.get(law, m)
            if j * mm == 1.0:
                continue  # the linear face: below
            # 1e-3 of the cap's range deep under 0.0245 N, deeper under 10 times that
            k = 0.0245 / (j * c**mm * (1e-3 * d_max) ** (j * mm - 1.0))
            for load in (0.0245, 0.245):
                got = depth.resting_depth(cube, law, k, load, feature, m=m)
                want = depth.power_law_depth(load, k, mm, c, j)
                if want < d_max:
                    assert got == pytest.approx(want, rel=1e-9), (feature, law, load)
                    checked += 1
    assert checked == 21  # all but the power law's m = 1.25 face under 10 times the load (10^4 deeper)
    # The linear law's face carries k A at any depth: on the surface below that, through above.
    assert depth.resting_depth(cube, "linear", 30.0, 1e-3, "face") == 0.0
    assert depth.resting_depth(cube, "linear", 30.0, 1.0, "face") == math.inf


def test_cut_matches_the_clipped_hull():
    """V(d) and |S(d)| of a 20-vertex rock, a tetrahedron and a prism pressed along random directions
    against scipy: the hull of the vertices beyond the plane and the edge crossings, and the section's."""
    rng = np.random.default_rng(3)
    shapes = [ConvexShape.rock(20, size=EDGE, seed=1), ConvexShape.tetrahedron(EDGE), ConvexShape.prism(6, 0.006, EDGE)]
    for shape in shapes:
        verts = np.asarray(shape.vertices)
        edges = np.array(
            sorted(
                {tuple(sorted((int(a), int(b)))) for f in shape.faces for a, b in zip(f, np.roll(f, -1), strict=True)}
            )
        )
        for _ in range(4):
            u = rng.normal(size=3)
            u /= np.linalg.norm(u)
            cut = depth.Cut(verts, edges, u)
            h = verts @ u
            for frac in (0.07, 0.3, 0.55, 0.9):
                d = frac * cut.extent
                plane = h.max() - d
                w = (plane - h[edges[:, 0]]) / (h[edges[:, 1]] - h[edges[:, 0]])
                crossing = (w > 0.0) & (w < 1.0)
                section = verts[edges[crossing, 0]] + w[crossing, None] * (
                    verts[edges[crossing, 1]] - verts[edges[crossing, 0]]
                )
                cap = np.vstack([verts[h > plane], section])
                basis = np.linalg.svd(np.eye(3) - np.outer(u, u))[0][:, :2]
                v, s = cut.cap(d)
                assert v == pytest.approx(ConvexHull(cap).volume, rel=1e-9)
                assert s == pytest.approx(ConvexHull(section @ basis).volume, rel=1e-9)


def kernel_force(shape, direction, depths, law):
    """Normal force [N] of the simulator's response (no toe) on ``shape`` pressed along ``direction`` to each
    of ``depths`` [m] into the top face of a large box, float64."""
    floor = ConvexShape.box(0.2, 0.2, 0.05)
    poses = np.array([pose_pressed(shape, direction, d) for d in depths])
    # pose_pressed places the body frame (principal axes), as the simulator's state does
    res = overlap(shape, poses, floor, np.array([0.0, 0.0, -0.025, 0, 0, 0, 1]), frame="body", precision="float64")
    assert np.allclose(res.depth, depths, rtol=1e-9)
    return contact_forces(res, law).force_a[:, 2]


@pytest.mark.parametrize(
    ("name", "law", "m"),
    [("cube", "hertz", None), ("cube", "power", 1.25), ("cube", "linear", None), ("tetrahedron", "hertz", None),
     ("rock", "hertz", None)],
)  # fmt: skip
def test_resting_depth_is_where_the_kernel_carries_the_load(name, law, m):
    """The kernel's force W'(V)|S| crosses the load within 1e-3 of depth.py's depth, for the deepest face,
    edge and corner of a cube (hertz, power m = 1.25, linear: no face depth), a tetrahedron and a rock, at
    a k that puts each 1e-3 of the edge deep under the grain's weight, and under 3 times the weight."""
    shape = {
        "cube": ConvexShape.box(EDGE),
        "tetrahedron": ConvexShape.tetrahedron(EDGE),
        "rock": ConvexShape.rock(20, size=EDGE, seed=1),
    }[name]
    weight = 2500.0 * shape.volume * 9.81
    for feature in depth.FEATURES:
        if law == "linear" and feature == "face":
            continue
        k = depth.stiffness_for_depth(shape, law, 1e-3 * EDGE, weight, feature, m=m)
        contact_law = ContactLaw(law, k=k, m=1.0 if m is None else m)
        for load in (weight, 3.0 * weight):
            rest = depth.resting_contact(shape, law, k, load, feature, m=m)
            assert 1e-4 * EDGE < rest.depth < 0.5 * EDGE, (feature, load, rest.depth)
            forces = kernel_force(shape, rest.direction, rest.depth * np.array([1 - RTOL, 1, 1 + RTOL]), contact_law)
            below, at, above = forces
            assert below < load < above, (feature, load, forces)
            assert at == pytest.approx(load, rel=RTOL)


def cubes_on_a_plane(cube, poses, restitution, precision="float64"):
    """A scene of cubes (hertz k 1e8, no friction) at ``poses`` (rows of 7) on the plane z = 0."""
    scene = Scene(gravity=(0.0, 0.0, -9.81), precision=precision, name="resting")
    scene.add_material("stone", density=2500.0, law="hertz", k=1e8, restitution=restitution, friction=0.0)
    scene.add_shape("cube", cube)
    scene.add_plane((0.0, 0.0, 0.0), (0.0, 0.0, 1.0), "stone")
    for p in poses:
        scene.add_body("cube", "stone", p[:3], p[3:])
    return scene


@pytest.mark.parametrize("restitution", [0.5, 0.05])
def test_toe_depth_is_where_a_resting_simulation_carries_the_load(device, restitution):
    """With the resolved toe (the Simulation's dt, e and mass against a plane): cubes lying on a face and
    on a corner, each at depth.py's depth under its weight and 1e-3 above and below it; the contact's
    normal force brackets the weight. The face rests in the toe, near g dt^2 / e^2 whatever k; the
    corner beyond it for e = 0.5 and in it for e = 0.05 (V_c grows as (dt / e)^4).

    The low restitution was 0.2 while the toe came from a face of 2 r_min^2 at omega dt = 0.5; from the
    cube's own face at omega dt = 1, V_c is about 80 times smaller and at e = 0.2 the corner's resting
    volume is 6.7 V_c (out of the toe). At e = 0.05 it is 0.24 V_c (at 0.08 it would be 1.1 V_c: the
    auto step shortens with e between 0.15 and 0.1, so V_c does not grow there)."""
    cube = ConvexShape.box(EDGE)
    dt = cubes_on_a_plane(cube, [pose_pressed(cube, (0, 0, -1), -EDGE)], restitution).time_step().dt
    mass = 2500.0 * cube.volume
    weight = mass * 9.81
    toe = depth.Toe(restitution, dt, 1.0 / mass)
    rests = [depth.resting_contact(cube, "hertz", 1e8, weight, f, toe=toe) for f in ("face", "corner")]
    # The toe's W' = 1.5 k V_c^0.5 x - 0.5 k V_c^0.5 x^2 (x = V / V_c), its slope a = 1.5 k / V_c^0.5 set by
    # a A_toe^2 / (m e^2) = (1 / dt)^2 with A_toe = EDGE^2, the cube's face: a linear spring, d -> g dt^2 / e^2.
    a = (restitution / dt) ** 2 * mass / (EDGE**2) ** 2
    vc = (1.5 * 1e8 / a) ** 2
    x = 1.5 - math.sqrt(2.25 - 2.0 * weight / (1e8 * math.sqrt(vc) * EDGE**2))
    assert rests[0].in_toe and rests[0].vc == pytest.approx(vc, rel=1e-12)
    assert rests[0].depth == pytest.approx(x * vc / EDGE**2, rel=1e-9)
    assert rests[0].depth == pytest.approx(9.81 * dt**2 / restitution**2, rel=x / 2.0)
    assert rests[0].depth > depth.resting_depth(cube, "hertz", 1e8, weight, "face")  # the law's alone
    assert rests[1].in_toe == (restitution < 0.1)
    poses = []
    for rest in rests:
        for scale in (1.0 - RTOL, 1.0, 1.0 + RTOL):
            poses.append(pose_pressed(cube, rest.direction, scale * rest.depth))
            poses[-1][0] = 3.0 * EDGE * len(poses)
    with pytest.warns(SceneWarning, match="initial overlaps"):  # the corners, 14% to 17% of the edge deep
        sim = Simulation(cubes_on_a_plane(cube, poses, restitution), device=device)
    assert sim.dt == dt
    contacts = sim.contacts()
    order = np.argsort(contacts["body_a"])
    assert np.array_equal(contacts["body_a"][order], np.arange(6)) and np.all(contacts["body_b"] == -1)
    fn = contacts["normal_force"][order]
    np.testing.assert_allclose(contacts["depth"][order][1::3], [r.depth for r in rests], rtol=1e-9)
    for i, rest in enumerate(rests):
        below, at, above = fn[3 * i : 3 * i + 3]
        assert below < weight < above, (rest.feature, below, at, above)
        assert at == pytest.approx(weight, rel=RTOL)


def test_stiffness_for_depth_inverts_the_resting_depth():
    """k for a corner depth: the cube's closed form F / (3 (sqrt 3 / 2)^1.5 d^3.5) under hertz, and the
    depth that k gives back for the deepest corner of other shapes and laws."""
    cube = ConvexShape.box(EDGE)
    load, d = 0.245, 0.01 * EDGE
    k = depth.stiffness_for_depth(cube, "hertz", d, load)
    assert k == pytest.approx(load / (3.0 * (math.sqrt(3.0) / 2.0) ** 1.5 * d**3.5), rel=1e-12)
    for shape in (cube, ConvexShape.tetrahedron(EDGE), ConvexShape.rock(20, size=EDGE, seed=1)):
        for law, m in (("hertz", None), ("linear", None), ("power", 1.8)):
            for feature in ("edge", "corner"):
                k = depth.stiffness_for_depth(shape, law, d, load, feature, m=m)
                assert depth.resting_depth(shape, law, k, load, feature, m=m) == pytest.approx(d, rel=1e-9)


def test_bad_input_says_what_is_wrong():
    cube = ConvexShape.box(EDGE)
    with pytest.raises(ValueError, match="law must be one of linear, hertz, power"):
        depth.resting_depth(cube, "hooke", 1e8, 1.0)
    with pytest.raises(ValueError, match="feature must be one of face, edge, corner"):
        depth.resting_depth(cube, "hertz", 1e8, 1.0, "vertex")
    with pytest.raises(ValueError, match="power law needs an exponent m >= 1"):
        depth.resting_depth(cube, "power", 1e8, 1.0)
    with pytest.raises(ValueError, match="load must be a finite force"):
        depth.resting_depth(cube, "hertz", 1e8, -1.0)
    with pytest.raises(ValueError, match="beyond the shape's extent"):
        depth.stiffness_for_depth(cube, "hertz", 2.0 * EDGE, 1.0)


def test_validate_prints_the_resting_depths(capsys):
    """`polydem validate scenes/cube_drop.toml`: the lone steel cube (k 1e10) on a plane rests on a face in
    the toe, about g dt^2 / e^2 deep, and on a corner by the closed form (F / (3 (sqrt 3/2)^1.5 k))^(2/7).

    The face depth was 9 g dt^2 / e^2 while the toe came from a face of 2 r_min^2 = 1.5 a^2 at omega dt = 0.5
    ((1.5 / 0.5)^2 = 9); the toe now comes from the cube's own largest face a^2 at omega dt = 1
    (kernels/response.py toe_volume), so the reference below is the toe's closed form at that area."""
    path = REPO / "scenes" / "cube_drop.toml"
    code, out, err = run(["validate", path], capsys)
    assert code == 0, err
    dt = float(re.search(r"time step: (\S+) s", out).group(1))
    line = next(s for s in out.splitlines() if s.startswith("    cube (steel, k 1e+10): own weight "))
    face, edge, corner = re.search(r"own weight (\S+) / (\S+) / (\S+);", line).groups()
    a, weight = 0.1, 7800.0 * 0.1**3 * 9.81
    # The toe's W' = 1.5 k V_c^0.5 x - 0.5 k V_c^0.5 x^2 (x = V / V_c), its slope 1.5 k / V_c^0.5 set by
    # slope A_toe^2 / (m e^2) = (TOE_OMEGA_DT / dt)^2 with A_toe = a^2, the cube's face (the plane has none
    # smaller); the face then rests at x V_c / a^2, a little deeper than the linear spring's g dt^2 / e^2.
    mass, e = 7800.0 * a**3, 0.5
    slope = (depth.TOE_OMEGA_DT * e / dt) ** 2 * mass / (a**2) ** 2
    vc = (1.5 * 1e10 / slope) ** 2
    x = 1.5 - math.sqrt(2.25 - 2.0 * weight / (1e10 * math.sqrt(vc) * a**2))
    want = x * vc / a**2
    assert want == pytest.approx(9.81 * dt**2 / e**2, rel=x / 2.0)
    # rel 0.05: validate prints two digits, and its dt (four digits) is squared here
    assert face.endswith("%*") and float(face[:-2]) == pytest.approx(100 * want / a, rel=0.05)
    want = (weight / (3.0 * (math.sqrt(3.0) / 2.0) ** 1.5 * 1e10)) ** (2.0 / 7.0)
    assert corner.endswith("%") and float(corner[:-1]) == pytest.approx(100 * want / a, rel=0.05)
    k = float(re.search(r"a corner 1% deep under its weight needs k (\S+) J/m\^4.5", line).group(1))
    assert k == pytest.approx(weight / (3.0 * (math.sqrt(3.0) / 2.0) ** 1.5 * (0.01 * a) ** 3.5), rel=0.01)


def test_auto_dt_follows_k_as_the_scene_time_step_does():
    """auto_dt(ts, scale) is the dt = "auto" of the same scene with every k scaled: the default scene (where
    the reference contact sets it at its k, the resting rule at 16 and 256 times it)."""
    import dataclasses

    from polydem.default_scene import default_scene_path

    scene = Scene.from_toml(default_scene_path())
    ts = scene.time_step()
    assert depth.auto_dt(ts, "hertz", None, 1.0) == pytest.approx(ts.recommended, rel=1e-12)
    for scale in (4.0, 16.0, 256.0):
        for name, mat in scene.materials.items():
            scene.material_table.by_name[name] = dataclasses.replace(mat, k=scale * 1e8)
        assert depth.auto_dt(ts, "hertz", None, scale) == pytest.approx(scene.time_step().recommended, rel=1e-9)


@pytest.mark.parametrize(
    "k, precision, warned", [(1.0e9, "float32", True), (1.0e7, "float32", False), (1.0e9, "mixed", False)]
)
def test_validate_warns_where_float32_cannot_rest(k, precision, warned):
    """The incline's block at k 1e9 rests on its largest face 5.3e-9 m deep in the toe, and creeps 0.24 mm in
    0.5 s on a 20 degree slope in float32 (BENCHMARKS.md 10a); at k 1e7 it rests 100 times deeper and holds
    (tests/test_at_rest.py). The spacing is float32's at its bounding radius (above its height)."""
    from polydem.cli.validate import float32_rest_warnings

    th = math.radians(20.0)
    scene = Scene(gravity=(9.81 * math.sin(th), 0, -9.81 * math.cos(th)), dt="auto", precision=precision)
    scene.add_material("m", density=2700.0, law="hertz", k=k, restitution=0.3, friction=0.5)
    scene.add_shape("block", ConvexShape.box(0.2, 0.1, 0.05))
    scene.add_body("block", "m", position=(0.0, 0.0, 0.025))
    scene.add_plane((0, 0, 0), (0, 0, 1), "m")
    rows = depth.pile_depths(scene, scene.time_step())
    messages = float32_rest_warnings(scene, rows)
    assert bool(messages) == warned, messages
    if warned:
        assert "shape 'block'" in messages[0] and 'precision = "mixed"' in messages[0]
        spacings = float(re.search(r"m deep, (\S+) float32 spacings", messages[0]).group(1))
        # The toe's closed form (kernels/response.py toe_volume): the face of 0.02 m^2 under the block's
        # normal load, on the plane (the pair's mass is the block's).
        a, mass, e, dt = 0.02, 2.7, 0.3, scene.time_step().dt
        slope = (depth.TOE_OMEGA_DT * e / dt) ** 2 * mass / a**2
        vc = (1.5 * k / slope) ** 2
        load = mass * 9.81  # pile_depths: the weight, not its normal part
        x = 1.5 - math.sqrt(2.25 - 2.0 * load / (k * math.sqrt(vc) * a))
        want = x * vc / a
        assert want == pytest.approx(5.6e-9, rel=0.02)
        spacing = float(np.spacing(np.float32(math.sqrt(0.1**2 + 0.05**2 + 0.025**2))))
        assert spacings == pytest.approx(want / spacing, rel=0.01)
