"""Measures of packings (polydem.measures, issue 26), each against a case worked by hand.

Packing fractions are exact, so a simple cubic stack of cubes fills a box aligned with its faces to
rounding (1 - phi below 1e-14), a box half outside it half, and a cut through a centrally symmetric
grain's centre leaves half of it; the general clipping is checked against scipy's half-space
intersection. Contact types come from the overlap's shape, V / (S d): a cube sunk by d into a
plane on a face gives exactly 1, on an edge 1/2 (V = L d^2, S = 2 L d), on a corner 1/3
(V = sqrt(3)/2 d^3, S = 3 sqrt(3)/2 d^2); crossed edges give 1/3 too, but a normal 45 degrees from
every face. The simple cubic lattice's contacts, written by hand, give Z = 6 and fabric I/3; a cube
held on its six faces by fixed cubes, simulated, the same. A column of cubes settled on a floor
carries its weight: the Love-Weber stress over a cube is the weight above the cube's centre over the
cross-section, over a slab between two centres the weight above the contact between them.
"""

import json
import math

import numpy as np
import pytest
from scipy.optimize import linprog
from scipy.spatial import ConvexHull, HalfspaceIntersection
from scipy.spatial.transform import Rotation

import polydem
from polydem import CompoundShape, ConvexShape
from polydem import measures as M
from polydem.quaternions import quat_from_matrix, quat_multiply, quat_rotate

EDGE = 0.01  # [m]
DENSITY = 2500.0  # [kg/m^3]
K = 4.9e8  # [J/m^4.5] (tests/test_settled_pile.py)
G = 9.81  # [m/s^2]
SINK = 1e-6  # [m], 1e-4 of a cube: far below the initial-overlap warning
IDENTITY = np.array([0.0, 0.0, 0.0, 1.0])


def lattice(n, edge=EDGE):
    """Cubes of ``edge`` filling [0, n edge]^3 face to face."""
    idx = np.stack(np.meshgrid(*[np.arange(n)] * 3, indexing="ij"), -1).reshape(-1, 3)
    return M.Grains(
        [ConvexShape.box(edge)], np.zeros(len(idx), int), (idx + 0.5) * edge, np.tile(IDENTITY, (len(idx), 1))
    )


def reference_volume(shape, position, quat, box):
    """Volume of a convex shape at a body-frame pose inside ``box``, by scipy (qhull)."""
    rot = Rotation.from_quat(quat).as_matrix()
    n = shape.face_normals @ rot.T
    spaces = [np.column_stack([n, -(shape.face_offsets + n @ position)])]
    for k in range(3):
        e = np.eye(3)[k]
        spaces.append(np.r_[e, -box.upper[k]][None])
        spaces.append(np.r_[-e, box.lower[k]][None])
    hs = np.vstack(spaces)
    a = np.hstack([hs[:, :3], np.ones((len(hs), 1))])
    res = linprog([0, 0, 0, -1], A_ub=a, b_ub=-hs[:, 3], bounds=[(None, None)] * 3 + [(None, 10.0)])
    if res.status != 0 or -res.fun < 1e-9:
        return 0.0
    return ConvexHull(HalfspaceIntersection(hs, res.x[:3]).intersections).volume


def body_poses(shape, position, quat):
    """Body-frame poses of ``shape`` whose input frame is placed at (position, quat)."""
    q_in = np.broadcast_to(quat_from_matrix(shape.input_rotation), quat.shape)
    t_in = np.broadcast_to(shape.input_translation, position.shape)
    return position + quat_rotate(quat, t_in), quat_multiply(quat, q_in)


# ---------------------------------------------------------------------------------- packing fraction


def test_clipped_volume_matches_halfspace_intersection():
    rng = np.random.default_rng(0)
    shapes = [
        ConvexShape.box(1.0, 0.6, 0.3),
        ConvexShape.from_points(rng.normal(size=(30, 3))),
        ConvexShape.tetrahedron(1.3),
        ConvexShape.dodecahedron(0.7),
    ]
    n = 120
    body_shape = rng.integers(0, len(shapes), n)
    pos = rng.uniform(-2.0, 2.0, (n, 3))
    quat = Rotation.random(n, random_state=1).as_quat()
    box = M.Box((-1.1, -0.7, -1.3), (1.2, 0.9, 0.8))
    got = M.clipped_volumes(M.Grains(shapes, body_shape, pos, quat), box)
    want = [reference_volume(shapes[s], p, q, box) for s, p, q in zip(body_shape, pos, quat, strict=True)]
    whole = np.array([shapes[s].volume for s in body_shape])
    assert np.sum(got > 0.0) > 40 and np.sum((got > 0.0) & (got < 0.999 * whole)) > 30  # many grains are cut
    np.testing.assert_allclose(got, want, rtol=0.0, atol=1e-12)


@pytest.mark.parametrize("name", ["box", "octahedron", "dodecahedron"])
def test_a_cut_through_the_centre_halves_a_symmetric_grain(name):
    shape = {"box": ConvexShape.box(EDGE), "octahedron": ConvexShape.octahedron(EDGE),
             "dodecahedron": ConvexShape.dodecahedron(EDGE)}[name]  # fmt: skip
    quat = Rotation.random(20, random_state=4).as_quat()
    centre = np.array([0.3, -0.2, 0.1])
    grains = M.Grains([shape], np.zeros(20, int), np.tile(centre, (20, 1)), quat)
    for axis in range(3):
        lower = centre - 1.0
        lower[axis] = centre[axis]
        half = M.clipped_volumes(grains, M.Box(lower, centre + 1.0))
        np.testing.assert_allclose(half, 0.5 * shape.volume, rtol=1e-14)


def test_a_corner_cut_off_a_tetrahedron():
    """A plane at t of the height below a corner cuts off t^3 of a tetrahedron (a similar one)."""
    shape = ConvexShape.tetrahedron(EDGE)
    top = shape.vertices[0]
    # The corner straight up: its direction from the centroid is normal to the opposite face.
    v = top / np.linalg.norm(top)
    axis = np.cross(v, [0.0, 0.0, 1.0])
    rot = Rotation.from_rotvec(axis / np.linalg.norm(axis) * math.acos(v[2]))
    height = np.linalg.norm(top) * 4.0 / 3.0  # corner to opposite face: 4/3 of the corner's distance
    grains = M.Grains([shape], [0], [[0.0, 0.0, 0.0]], [rot.as_quat()])
    for t in (0.1, 0.5, 0.9):
        box = M.Box((-1.0, -1.0, np.linalg.norm(top) - t * height), (1.0, 1.0, 1.0))
        np.testing.assert_allclose(M.clipped_volumes(grains, box)[0], t**3 * shape.volume, rtol=1e-12)


def test_simple_cubic_stack_fills_space():
    n = 4
    grains = lattice(n)
    edge = EDGE
    aligned = M.Box((edge, 0.0, edge), (3 * edge, 4 * edge, 4 * edge))
    assert abs(M.packing_fraction(grains, aligned) - 1.0) < 1e-14
    anywhere = M.Box((0.37 * edge, 0.5 * edge, 1.01 * edge), (2.9 * edge, 3.3 * edge, 3.999 * edge))
    assert abs(M.packing_fraction(grains, anywhere) - 1.0) < 1e-13
    half = M.Box((2.0 * edge, 1.3 * edge, 0.2 * edge), (6.0 * edge, 3.1 * edge, 2.7 * edge))  # half beyond x = 4 edge
    assert abs(M.packing_fraction(grains, half) - 0.5) < 1e-14
    # The default region is the box around the grains; the margin moves its faces in by grain sizes.
    assert abs(M.packing_fraction(grains) - 1.0) < 1e-14
    size = grains.grain_size()
    assert size == pytest.approx(edge * (6.0 / math.pi) ** (1.0 / 3.0), rel=1e-14)
    assert abs(M.packing_fraction(grains, margin=1.0) - 1.0) < 1e-13
    assert M.Box.around(grains).shrunk(size).lower == pytest.approx([size] * 3, rel=1e-14)
    profile = M.packing_profile(grains, "z", edge / 4, M.Box((0.0, 0.0, -edge), (n * edge, n * edge, (n + 1) * edge)))
    inside = (profile.centres > 0.0) & (profile.centres < n * edge)
    assert len(profile.fraction) == 4 * (n + 2)
    np.testing.assert_allclose(profile.fraction[inside], 1.0, rtol=0.0, atol=1e-13)
    np.testing.assert_allclose(profile.fraction[~inside], 0.0, rtol=0.0, atol=1e-13)


def test_profile_splits_each_grain_exactly_between_slabs():
    rng = np.random.default_rng(2)
    shapes = [ConvexShape.box(1.0), ConvexShape.octahedron(1.2), ConvexShape.from_points(rng.normal(size=(20, 3)))]
    n = 300
    grains = M.Grains(
        shapes, rng.integers(0, 3, n), rng.uniform(-3.0, 3.0, (n, 3)), Rotation.random(n, random_state=5).as_quat()
    )
    box = M.Box((-2.0, -2.5, -2.2), (2.4, 2.0, 1.9))
    profile = M.packing_profile(grains, 0, 0.37, box)
    assert profile.edges[0] == box.lower[0] and profile.edges[-1] == box.upper[0]
    assert profile.edges[-1] - profile.edges[-2] < 0.37  # the last slab is what is left
    for k in range(len(profile.centres)):
        lo, hi = box.lower.copy(), box.upper.copy()
        lo[0], hi[0] = profile.edges[k], profile.edges[k + 1]
        slab = M.clipped_volumes(grains, M.Box(lo, hi)).sum()
        assert profile.solid_volume[k] == pytest.approx(slab, rel=1e-12, abs=1e-12)
    assert profile.solid_volume.sum() == pytest.approx(M.clipped_volumes(grains, box).sum(), rel=1e-13)
    np.testing.assert_allclose(profile.fraction, profile.solid_volume / profile.slab_volume)
    # A margin moves only the faces across the profile's axis.
    narrow = M.packing_profile(grains, 0, 0.37, box, margin=0.5)
    d = 0.5 * grains.grain_size()
    assert narrow.box.lower == pytest.approx(box.lower + [0.0, d, d]) and narrow.box.upper == pytest.approx(
        box.upper - [0.0, d, d]
    )


def test_compound_grains_count_their_union_once():
    eye = np.eye(3)
    touching = CompoundShape(
        [ConvexShape.box(1.0).placed(eye, (0.5, 0, 0)), ConvexShape.box(1.0).placed(eye, (-0.5, 0, 0))]
    )
    # Three overlapping parts whose union is the box 1.5 x 1 x 1.
    overlapping = CompoundShape([
        ConvexShape.box(1.0).placed(eye, (0.25, 0, 0)),
        ConvexShape.box(1.0).placed(eye, (-0.25, 0, 0)),
        ConvexShape.box(0.5, 0.6, 1.0).placed(eye, (0.0, 0.1, 0.0)),
    ])  # fmt: skip
    assert not touching.overlapping and overlapping.overlapping
    rng = np.random.default_rng(3)
    n = 100
    pos, quat = rng.uniform(-1.0, 1.0, (n, 3)), Rotation.random(n, random_state=3).as_quat()
    box = M.Box((-0.6, -0.5, -0.4), (0.7, 0.8, 0.3))
    for grain, union in ((touching, ConvexShape.box(2.0, 1.0, 1.0)), (overlapping, ConvexShape.box(1.5, 1.0, 1.0))):
        got = M.clipped_volumes(M.Grains([grain], np.zeros(n, int), *body_poses(grain, pos, quat)), box)
        want = M.clipped_volumes(M.Grains([union], np.zeros(n, int), *body_poses(union, pos, quat)), box)
        assert got.max() > 0.5
        np.testing.assert_allclose(got, want, rtol=0.0, atol=1e-13)


# ------------------------------------------------------------------------------------- contact types


def cube_scene(gravity=(0.0, 0.0, 0.0)):
    scene = polydem.Scene(gravity=gravity, dt="auto", precision="mixed")
    scene.add_material("grain", density=DENSITY, law="hertz", k=K, restitution=0.3, friction=0.5)
    scene.add_shape("cube", ConvexShape.box(EDGE))
    return scene


def extent(rotation, up=True):
    """Highest (or lowest) height of a cube's vertices turned by ``rotation`` about its centre [m]."""
    z = (ConvexShape.box(EDGE).vertices @ rotation.as_matrix().T)[:, 2]
    return z.max() if up else z.min()


FACE = Rotation.identity()
EDGE_DOWN = Rotation.from_rotvec([math.pi / 4, 0.0, 0.0])  # an edge along x lowest
EDGE_DOWN_Y = Rotation.from_rotvec([0.0, math.pi / 4, 0.0])
_AXIS = np.cross([1.0, 1.0, 1.0], [0.0, 0.0, -1.0]) / math.sqrt(2.0)
CORNER_DOWN = Rotation.from_rotvec(_AXIS * math.acos(-1.0 / math.sqrt(3.0)))  # the corner (1, 1, 1) lowest


@pytest.mark.parametrize("wall", ["plane", "mesh"])
def test_a_cube_on_a_plane_by_face_edge_and_corner(device, wall):
    """A mesh wall is taken as the plane of the contact's normal at its depth: exact on a flat mesh."""
    scene = cube_scene((0.0, 0.0, -G))
    for k, rot in enumerate((FACE, EDGE_DOWN, CORNER_DOWN)):
        z = -extent(rot, up=False) - SINK
        scene.add_body("cube", "grain", position=(0.05 * k, 0.0, z), orientation=rot.as_quat())
    if wall == "plane":
        scene.add_plane((0.0, 0.0, 0.0), (0.0, 0.0, 1.0), "grain")
    else:
        square = np.array([[-1.0, -1.0, 0.0], [1.0, -1.0, 0.0], [1.0, 1.0, 0.0], [-1.0, 1.0, 0.0]]) * 0.2
        scene.add_mesh_wall((square, np.array([[0, 1, 2], [0, 2, 3]])), "grain")
    sim = polydem.Simulation(scene, device)
    types = M.classify_contacts(sim)
    assert types.body_b.tolist() == [-1, -1, -1]
    order = np.argsort(types.body_a)
    assert types.names()[order].tolist() == ["face-face", "edge-face", "vertex-face"]
    np.testing.assert_allclose(types.ratio[order], [1.0, 0.5, 1.0 / 3.0], rtol=1e-8)
    want_volume = [EDGE**2 * SINK, EDGE * SINK**2, math.sqrt(3.0) / 2.0 * SINK**3]
    np.testing.assert_allclose(types.volume[order], want_volume, rtol=1e-8)
    np.testing.assert_allclose(types.depth, SINK, rtol=1e-8)
    assert types.counts() == {"face-face": 1, "edge-face": 1, "vertex-face": 1, "edge-edge": 0, "unclassified": 0}
    assert types.feature_a[order].tolist() == [2, 1, 0] and types.feature_b.tolist() == [2, 2, 2]
    features = M.classify_contacts(sim, method="features")
    assert features.names()[np.argsort(features.body_a)].tolist() == ["face-face", "edge-face", "vertex-face"]
    # A box through the face-down cube's centre, wide of the others, holds half of it.
    box = M.Box((-0.02, -0.02, -0.02), (0.0, 0.02, 0.02))
    assert M.packing_fraction(sim, box) == pytest.approx(0.5 * EDGE**3 / box.volume, rel=1e-12)


def test_pairs_of_cubes_face_edge_corner_and_crossed_edges(device):
    """Cube B sunk by SINK onto cube A: face on face, edge on face, corner on face, and A's edge along
    x under B's edge along y (the overlap is a pyramid, so the ratio is 1/3 as for a corner: the
    contact normal, 45 degrees from every face of both cubes, tells the crossed edges apart)."""
    scene = cube_scene()
    cases = [(FACE, FACE), (FACE, EDGE_DOWN), (FACE, CORNER_DOWN), (EDGE_DOWN, EDGE_DOWN_Y)]
    for k, (ra, rb) in enumerate(cases):
        scene.add_body("cube", "grain", position=(0.05 * k, 0.0, 0.0), orientation=ra.as_quat())
        z = extent(ra) - extent(rb, up=False) - SINK
        scene.add_body("cube", "grain", position=(0.05 * k, 0.0, z), orientation=rb.as_quat())
    sim = polydem.Simulation(scene, device)
    types = M.classify_contacts(sim)
    order = np.argsort(types.body_a)
    assert types.body_a[order].tolist() == [0, 2, 4, 6] and types.body_b[order].tolist() == [1, 3, 5, 7]
    assert types.names()[order].tolist() == ["face-face", "edge-face", "vertex-face", "edge-edge"]
    np.testing.assert_allclose(types.ratio[order], [1.0, 0.5, 1.0 / 3.0, 1.0 / 3.0], rtol=1e-6)
    np.testing.assert_allclose(types.face_angle[order], [0.0, 0.0, 0.0, 45.0], atol=1e-4)
    features = M.classify_contacts(sim, method="features")
    assert features.names()[order].tolist() == ["face-face", "edge-face", "vertex-face", "edge-edge"]


@pytest.mark.parametrize("degrees", [0.5, 5.0])
def test_a_tilted_face_by_overlap_and_by_features(device, degrees):
    """A cube turned by a few degrees about x and sunk 1e-6 m into a plane dips one edge in: the
    overlap is a wedge (edge-face), while its face lies within 10 degrees of the plane (face-face by
    its features)."""
    scene = cube_scene((0.0, 0.0, -G))
    rot = Rotation.from_rotvec([math.radians(degrees), 0.0, 0.0])
    scene.add_body("cube", "grain", position=(0.0, 0.0, -extent(rot, up=False) - SINK), orientation=rot.as_quat())
    scene.add_plane((0.0, 0.0, 0.0), (0.0, 0.0, 1.0), "grain")
    sim = polydem.Simulation(scene, device)
    by_overlap = M.classify_contacts(sim, method="overlap")
    assert by_overlap.names().tolist() == ["edge-face"] and by_overlap.ratio[0] == pytest.approx(0.5, rel=1e-8)
    assert by_overlap.face_angle[0] == 0.0  # the plane's own face
    assert M.classify_contacts(sim, method="features").names().tolist() == ["face-face"]
    assert M.classify_contacts(sim, method="features", align_angle=0.1).names().tolist() == ["edge-face"]


def test_classify_thresholds():
    ratio = [1.0, 0.75, 0.7499, 0.5, 5.0 / 12.0, 0.4166, 1.0 / 3.0, np.nan, 0.3]
    angle = [0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 10.5]
    assert M.classify(ratio, angle).tolist() == [0, 0, 1, 1, 1, 2, 2, -1, 3]
    assert M.classify([0.6], [20.0], align_angle=30.0).tolist() == [1]


# ---------------------------------------------------------------------------------------- a cubic stack


def lattice_contacts(n):
    """The contacts of lattice(n) (a unit normal force each) and of its faces with six walls, by hand."""
    idx = np.stack(np.meshgrid(*[np.arange(n)] * 3, indexing="ij"), -1).reshape(-1, 3)
    index = {tuple(v): i for i, v in enumerate(idx.tolist())}
    a, b, normal, point = [], [], [], []
    for i, v in enumerate(idx.tolist()):
        for k in range(3):
            e = np.eye(3)[k]
            for side in (1, -1):
                w = list(v)
                w[k] += side
                centre = (np.array(v) + 0.5) * EDGE
                if tuple(w) in index:
                    if side < 0:
                        continue  # each pair once
                    a.append(i), b.append(index[tuple(w)])
                else:
                    a.append(i), b.append(-1 - (2 * k + (side < 0)))
                normal.append(side * e), point.append(centre + 0.5 * EDGE * side * e)
    c = len(a)
    return {"body_a": np.array(a), "body_b": np.array(b), "normal": np.array(normal), "point": np.array(point),
            "normal_force": np.ones(c), "tangential_force": np.zeros((c, 3))}  # fmt: skip


def test_simple_cubic_lattice_by_hand():
    """3 x 3 x 3 cubes face to face in a box of walls: every cube has 6 contacts (walls included), the
    centre one 6 with cubes; the normals are the axes in equal numbers: fabric I/3."""
    grains = lattice(3)
    c = lattice_contacts(3)
    pairs = c["body_b"] >= 0
    assert pairs.sum() == 54 and (~pairs).sum() == 54
    z = M.coordination(grains, c, False)
    assert z.z == 6.0 and z.grains == 27 and len(z.rattlers) == 0 and z.z_by_kind == {}
    assert M.coordination(grains, c, False, walls=False, min_contacts=0).contacts[13] == 6
    # Without the walls the corners have 3 contacts: rattlers; then the edges have 3, the faces 3...
    assert len(M.coordination(grains, c, False, walls=False).rattlers) == 8
    assert len(M.coordination(grains, c, False, walls=False, iterate=True).rattlers) == 27
    np.testing.assert_allclose(M.fabric(c), np.eye(3) / 3.0, rtol=0.0, atol=1e-15)
    np.testing.assert_allclose(M.fabric(c, walls=True), np.eye(3) / 3.0, rtol=0.0, atol=1e-15)
    centre = M.Box((EDGE, EDGE, EDGE), (2 * EDGE, 2 * EDGE, 2 * EDGE))  # the contact points on its faces
    np.testing.assert_allclose(M.fabric(c, box=centre), np.eye(3) / 3.0, rtol=0.0, atol=1e-15)
    # Unit forces along the axes: sigma = 1 N x EDGE per contact over the lattice, 54 pair and 54 wall
    # (half-length branch) contacts: (18 EDGE + 18 EDGE / 2) / (27 EDGE^3) on each axis.
    sigma = M.stress(grains, M.Box((0.0, 0.0, 0.0), (3 * EDGE, 3 * EDGE, 3 * EDGE)), c)
    np.testing.assert_allclose(sigma, np.eye(3) * 27.0 / (27.0 * EDGE**2), rtol=1e-12)


def test_a_cube_held_on_its_six_faces(device):
    """A free cube with six fixed half-size cubes sunk SINK into its faces: six face-face contacts,
    Z = 6, fabric I/3, isotropic stress."""
    scene = cube_scene()
    scene.add_shape("small", ConvexShape.box(0.5 * EDGE))
    scene.add_body("cube", "grain")
    for k in range(3):
        for side in (1.0, -1.0):
            x = np.zeros(3)
            x[k] = side * (0.75 * EDGE - SINK)
            scene.add_body("small", "grain", position=x, kind="fixed")
    sim = polydem.Simulation(scene, device)
    c = sim.contacts()
    assert len(c["body_a"]) == 6
    types = M.classify_contacts(sim, c)
    assert types.counts()["face-face"] == 6
    np.testing.assert_allclose(types.ratio, 1.0, rtol=1e-8)
    z = M.coordination(sim, c, types)
    assert z.z == 6.0 and z.grains == 1 and len(z.rattlers) == 0 and z.z_by_kind["face-face"] == 6.0
    np.testing.assert_allclose(M.fabric(c), np.eye(3) / 3.0, rtol=0.0, atol=1e-12)
    box = M.Box.around(sim)
    np.testing.assert_allclose(box.upper, [0.5 * EDGE] * 3, rtol=1e-12)
    sigma = M.stress(sim, box, c)
    assert sigma[0, 0] > 0.0
    np.testing.assert_allclose(sigma, np.eye(3) * sigma[0, 0], rtol=1e-5, atol=1e-5 * sigma[0, 0])
    # Normals along +-x, +-y, +-z: a sixth of the weight at each pole, the rest in the equator band.
    dist = M.normal_orientations(c, polar_bins=9, azimuth_bins=4, reference=(1.0, 1.0, 0.0))
    solid = np.outer(np.cos(dist.polar_edges[:-1]) - np.cos(dist.polar_edges[1:]), np.diff(dist.azimuth_edges))
    weight = dist.density * solid
    np.testing.assert_allclose(weight.sum(axis=1), [1 / 6, 0, 0, 0, 2 / 3, 0, 0, 0, 1 / 6], atol=1e-12)
    np.testing.assert_allclose(weight[4], [1 / 6] * 4, atol=1e-12)
    # In the x-z plane from (1, 0, 1): x normals at -45 and 135 degrees, z normals at 45 and -135; y ones left out.
    rose = M.normal_rose(c, plane=((1.0, 0.0, 1.0), (-1.0, 0.0, 1.0)), bins=4)
    np.testing.assert_allclose(rose.fraction, [0.25] * 4, atol=1e-12)
    assert rose.count == 4
    out = M.summary(sim)
    json.dumps(out)
    assert out["coordination"]["z"] == 6.0 and out["contact_types"]["face-face"] == 6
    assert out["contact_features"]["face-face"] == 6
    assert out["packing_fraction"] == pytest.approx(1.0, rel=1e-12)


def test_rattlers_are_removed_until_none_is_left():
    """Bodies 0-3 touch each other and a wall (4 contacts each); 4 touches 0, 1, 2 and 5; 5 touches
    only 4. 5 is a rattler; without it 4 has three contacts and is one too; 0-3 keep four."""
    grains = M.Grains(
        [ConvexShape.box(1.0)], np.zeros(6, int), np.arange(18.0).reshape(6, 3), np.tile(IDENTITY, (6, 1))
    )
    a = [0, 0, 0, 1, 1, 2, 0, 1, 2, 3, 4, 4, 4, 4]
    b = [1, 2, 3, 2, 3, 3, -1, -1, -1, -1, 0, 1, 2, 5]
    kinds = np.array([0, 0, 0, 0, 0, 0, 1, 1, 1, 1, 2, 2, 2, 2])
    contacts = {"body_a": np.array(a), "body_b": np.array(b)}
    types = M.ContactTypes(np.array(a), np.array(b), kinds, *(np.zeros(len(a)),) * 5)
    z = M.coordination(grains, contacts, types, iterate=True)
    assert z.rattlers.tolist() == [4, 5] and z.z == 4.0 and z.grains == 4
    assert z.z_by_kind["face-face"] == 3.0 and z.z_by_kind["edge-face"] == 1.0 and z.z_by_kind["vertex-face"] == 0.0
    once = M.coordination(grains, contacts, types)  # one pass
    assert once.rattlers.tolist() == [5] and once.z == pytest.approx((5 + 5 + 5 + 4 + 3) / 5)
    assert sum(once.z_by_kind.values()) == pytest.approx(once.z)
    assert M.coordination(grains, contacts, False, min_contacts=0).z == pytest.approx(24 / 6)
    assert M.coordination(grains, contacts, False, walls=False, min_contacts=3).rattlers.tolist() == [5]


# --------------------------------------------------------------------------------------- a column


def test_column_stress_is_the_weight_above(device):
    """4 cubes settled in a column on a floor: over cube j, sigma_zz = (4 - j - 1/2) m g / L^2 (the
    weight above its centre), sigma_zz over the column its mean; the other components vanish."""
    n = 4
    scene = cube_scene((0.0, 0.0, -G))
    for k in range(n):
        scene.add_body("cube", "grain", position=(0.0, 0.0, 0.5 * EDGE + 1.01 * EDGE * k))
    scene.add_plane((0.0, 0.0, 0.0), (0.0, 0.0, 1.0), "grain")
    sim = polydem.Simulation(scene, device)
    assert sim.run_until_settled(0.5).settled
    c = sim.contacts()
    weight = DENSITY * EDGE**3 * G
    half = 0.5 * EDGE
    box = M.Box((-half, -half, 0.0), (half, half, n * EDGE))
    area = EDGE**2
    profile = M.stress_profile(sim, "z", EDGE, box)
    want = (n - np.arange(n) - 0.5) * weight / area
    np.testing.assert_allclose(profile.stress[:, 2, 2], want, rtol=1e-4)
    others = profile.stress.reshape(n, 9)[:, :8]
    assert np.abs(others).max() < 1e-6 * want.max()
    assert M.stress(sim, box)[2, 2] == pytest.approx(want.mean(), rel=1e-4)
    # Love-Weber over slabs between centres: each holds one contact's whole branch vector.
    centres = M.stress_profile(sim, "z", EDGE, M.Box((-half, -half, half), (half, half, n * EDGE - half)))
    np.testing.assert_allclose(centres.stress[:, 2, 2], (n - 1 - np.arange(n - 1)) * weight / area, rtol=1e-4)
    types = M.classify_contacts(sim, c)
    assert types.counts()["face-face"] == n
    assert M.coordination(sim, c, types, min_contacts=0).z == pytest.approx((2 * (n - 1) + 1) / n)
    assert len(M.coordination(sim, c, types).rattlers) == n  # a column is held by nothing beside it
    # Normal forces 4, 3, 2, 1 weights: mean 2.5, ratios 1.6, 1.2, 0.8, 0.4.
    forces = M.force_distribution(c, walls=True, bins=[0.0, 0.5, 1.0, 1.5, 2.0])
    assert forces.mean == pytest.approx(2.5 * weight, rel=1e-4) and forces.count == n
    np.testing.assert_allclose(forces.density, 0.5)
    pairs = M.force_distribution(c, bins=2, max_ratio=1.25)  # ratios 1.5, 1, 0.5: one beyond
    assert pairs.mean == pytest.approx(2.0 * weight, rel=1e-4)
    assert pairs.beyond == pytest.approx(1 / 3) and pairs.density * 0.625 == pytest.approx([1 / 3] * 2)


# ----------------------------------------------------------------------------- by hand, without a device


def test_love_weber_signs_and_weightings():
    """Two grains 1 m apart along z pushed apart by 10 N (compression): sigma_zz = 10 N m / V; pulled
    together (tension), -10 N m / V. A wall contact counts from the grain's centre to the point."""
    x = np.array([[0.0, 0.0, 0.0], [0.0, 0.0, 1.0]])
    push = {
        "body_a": np.array([0, 1]),
        "body_b": np.array([1, -1]),
        "normal": np.array([[0.0, 0.0, 1.0], [0.0, 0.0, 1.0]]),
        "normal_force": np.array([10.0, 4.0]),
        "tangential_force": np.zeros((2, 3)),
        "point": np.array([[0.0, 0.0, 0.5], [0.0, 0.0, 1.5]]),
    }
    box = M.Box((-1.0, -1.0, -1.0), (1.0, 1.0, 3.0))
    sigma = M.stress(x, box, push)
    assert sigma[2, 2] == pytest.approx((10.0 * 1.0 + 4.0 * 0.5) / box.volume)
    assert np.abs(sigma.reshape(-1)[:8]).max() == 0.0
    assert M.stress(x, box, push, walls=False)[2, 2] == pytest.approx(10.0 / box.volume)
    pull = dict(push, normal_force=np.array([-10.0, 0.0]))
    assert M.stress(x, box, pull)[2, 2] == pytest.approx(-10.0 / box.volume)
    # Half the branch vector inside: half the contact; by its point, all or nothing.
    lower = M.Box((-1.0, -1.0, -1.0), (1.0, 1.0, 0.5))
    assert M.stress(x, lower, push, walls=False)[2, 2] == pytest.approx(5.0 / lower.volume)
    assert M.stress(x, lower, push, walls=False, weighting="point")[2, 2] == pytest.approx(10.0 / lower.volume)
    # The mean force of a contact average serves as well: the force on A is -f n + f_t.
    average = {k: push[k] for k in ("body_a", "body_b", "point")}
    average["force"] = -push["normal_force"][:, None] * push["normal"]
    np.testing.assert_allclose(M.stress(x, box, average), sigma)


def test_orientation_distributions_of_isotropic_normals():
    rng = np.random.default_rng(7)
    n = rng.normal(size=(200000, 3))
    n /= np.linalg.norm(n, axis=1, keepdims=True)
    c = {"body_a": np.zeros(len(n), int), "body_b": np.ones(len(n), int), "normal": n}
    dist = M.normal_orientations(c, polar_bins=6, azimuth_bins=8)
    np.testing.assert_allclose(dist.density, 1.0 / (4.0 * math.pi), rtol=0.05)
    np.testing.assert_allclose(dist.polar_density(), 1.0 / (4.0 * math.pi), rtol=0.02)
    assert dist.count == len(n)
    rose = M.normal_rose(c, plane=("x", "y"), bins=12)
    np.testing.assert_allclose(rose.fraction, 1.0 / 12.0, rtol=0.05)
    # Without the symmetry, normals on one side stay there.
    up = {"body_a": np.zeros(3, int), "body_b": np.ones(3, int), "normal": np.tile([0.0, 0.0, 1.0], (3, 1))}
    one_sided = M.normal_orientations(up, polar_bins=2, azimuth_bins=1, symmetric=False)
    assert one_sided.density[:, 0] * 2.0 * math.pi == pytest.approx([1.0, 0.0])
    assert M.fabric(up) == pytest.approx(np.diag([0.0, 0.0, 1.0]))


def test_bad_arguments_are_refused():
    grains = lattice(2)
    with pytest.raises(ValueError, match="lower < upper"):
        M.Box((0.0, 0.0, 0.0), (1.0, 0.0, 1.0))
    with pytest.raises(ValueError, match="empty"):
        M.Box((0.0, 0.0, 0.0), (1.0, 1.0, 1.0)).shrunk(0.6)
    with pytest.raises(ValueError, match="axis"):
        M.packing_profile(grains, "w")
    with pytest.raises(ValueError, match="bin_width"):
        M.packing_profile(grains, 2, -1.0)
    with pytest.raises(TypeError, match="Simulation or"):
        M.packing_fraction(np.zeros((3, 3)))
    with pytest.raises(ValueError, match="no contact"):
        M.fabric({"body_a": np.zeros(0, int), "body_b": np.zeros(0, int), "normal": np.zeros((0, 3))})


def test_settled_box_maps_the_summary_region_to_world_axes():
    """The summary's region runs along (e1, e2, up) with e1 the coordinate axis most across up and
    e2 = up x e1: for gravity -z that is (x, y, z); for gravity +x, up = -x, e1 = y, e2 = -z."""
    region = {"bodies": 5, "lower": [1.0, 2.0, 3.0], "upper": [4.0, 5.0, 6.0]}
    down = M.settled_box(polydem.Scene(gravity=(0.0, 0.0, -9.81)), region)
    assert down.lower.tolist() == [1.0, 2.0, 3.0] and down.upper.tolist() == [4.0, 5.0, 6.0]
    sideways = M.settled_box(polydem.Scene(gravity=(9.81, 0.0, 0.0)), region)
    assert sideways.lower.tolist() == [-6.0, 1.0, -5.0] and sideways.upper.tolist() == [-3.0, 4.0, -2.0]
    assert M.settled_box(polydem.Scene(gravity=(0.0, -7.0, -7.0)), region) is None
    assert M.settled_box(polydem.Scene(), {"bodies": 0, "packing_fraction": None}) is None


# --------------------------------------------------------------------------------------- cubic order


def test_cubic_order_by_hand():
    """Aligned cubes give 1 (also turned by any of the cube's rotations); a cube turned 45 degrees about z has
    axes (1, 1, 0)/sqrt(2), (-1, 1, 0)/sqrt(2), z: sum of fourth powers 4 (1/4) + 1 = 2, so (2 - 9/5) / (6/5) = 1/6;
    uniformly random rotations average 0 (their spread, about 0.35 a grain, over 40,000 grains: 0.002)."""
    grains = lattice(3)
    assert M.cubic_order(grains) == 1.0
    quarter = Rotation.from_euler("zx", [90.0, 180.0], degrees=True).as_quat()  # a symmetry of the cube
    turned = M.Grains(grains.shapes, grains.body_shape, grains.position, np.tile(quarter, (27, 1)))
    assert M.cubic_order(turned) == pytest.approx(1.0, abs=1e-14)
    z45 = Rotation.from_euler("z", 45.0, degrees=True).as_quat()
    half = np.where(np.arange(27)[:, None] < 9, z45, IDENTITY)  # 9 turned, 18 aligned
    mixed = M.Grains(grains.shapes, grains.body_shape, grains.position, half)
    assert M.cubic_order(mixed) == pytest.approx((9 / 6 + 18) / 27, abs=1e-14)
    # Only the grains in the box count: the first nine (x = 0.5 edge) are the turned ones.
    assert M.cubic_order(mixed, M.Box((0.0, 0.0, 0.0), (EDGE, 3 * EDGE, 3 * EDGE))) == pytest.approx(1 / 6, abs=1e-14)
    # In the frame the turned grains are aligned with, those are the ordered ones.
    frame = Rotation.from_euler("z", 45.0, degrees=True).as_matrix().T
    assert M.cubic_order(mixed, frame=frame) == pytest.approx((9 + 18 / 6) / 27, abs=1e-14)
    n = 40000
    rng = np.random.default_rng(3)
    turns = Rotation.random(n, rng).as_quat()
    scattered = M.Grains([ConvexShape.box(EDGE)], np.zeros(n, int), rng.random((n, 3)), turns)
    assert abs(M.cubic_order(scattered)) < 0.01


def test_cubic_frame_finds_the_frame_grains_align_in():
    """A lattice turned as a whole: order 1 in its own frame (the box's sees less), found to 1e-9, the frame
    the lattice's axes up to the cube's symmetry. 40% of 5000 grains share a tilted frame, the rest at random:
    the order in that frame is 0.4 + 0.6 x (the random part's, 0.011 here), and the search finds the frame."""
    grains = lattice(3)
    tilt = Rotation.from_rotvec([0.3, -0.5, 0.8])
    turned = M.Grains(grains.shapes, grains.body_shape, grains.position, np.tile(tilt.as_quat(), (27, 1)))
    assert M.cubic_order(turned) < 0.5
    q, frame = M.cubic_frame(turned)
    assert q == pytest.approx(1.0, abs=1e-9)
    assert np.allclose(frame @ frame.T, np.eye(3), atol=1e-12)
    match = np.abs(frame @ tilt.as_matrix())  # a signed permutation for the lattice's own axes
    assert np.allclose(np.sort(match, axis=1)[:, -1], 1.0, atol=1e-5) and np.allclose(match.sum(axis=0), 1.0, atol=1e-4)
    assert M.cubic_order(turned, frame=frame) == pytest.approx(q, abs=1e-15)
    n, shared = 5000, 2000
    rng = np.random.default_rng(4)
    turns = Rotation.random(n, rng).as_quat()
    turns[:shared] = (tilt * Rotation.from_euler("zx", [90.0, 180.0], degrees=True)).as_quat()
    some = M.Grains([ConvexShape.box(EDGE)], np.zeros(n, int), rng.random((n, 3)), turns)
    expected = M.cubic_order(some, frame=tilt.as_matrix().T)
    assert expected == pytest.approx(0.4 + 0.6 * 0.011, abs=0.01)
    q, frame = M.cubic_frame(some)
    assert expected - 1e-12 <= q <= expected + 0.005  # the maximum: at least the shared frame's, biased a little
    assert np.allclose(np.sort(np.abs(frame @ tilt.as_matrix()), axis=1)[:, -1], 1.0, atol=1e-4)
    # Grains at random: no order, up to the maximum's bias.
    turns = Rotation.random(n, rng).as_quat()
    scattered = M.Grains([ConvexShape.box(EDGE)], np.zeros(n, int), rng.random((n, 3)), turns)
    assert 0.0 < M.cubic_frame(scattered)[0] < 0.02
    with pytest.raises(ValueError, match="starts must be at least 1"):
        M.cubic_frame(scattered, starts=0)


def test_cubic_order_refuses_bad_arguments():
    grains = lattice(2)
    with pytest.raises(ValueError, match="frame must be 3 orthonormal rows"):
        M.cubic_order(grains, frame=np.ones((3, 3)))
    with pytest.raises(ValueError, match="no counted grain in the box"):
        M.cubic_order(grains, M.Box((1.0, 1.0, 1.0), (2.0, 2.0, 2.0)))
