"""Ray caster and PNG writer (polydem.render, polydem.kernels.raycast): small images, CPU and GPU."""

import struct
import zlib

import numpy as np
import pytest

import polydem
from polydem.render import PALETTE, Camera, render, render_layers, render_simulation, save_png
from polydem.scene import quat_from_axis_angle, quat_to_matrix

W, H = 64, 48
IDENTITY = (0.0, 0.0, 0.0, 1.0)


def random_quats(rng, n):
    q = rng.normal(size=(n, 4))
    return q / np.linalg.norm(q, axis=1, keepdims=True)


def world_vertices(shape, position, quat):
    return np.asarray(shape.vertices) @ quat_to_matrix(np.asarray(quat)).T + np.asarray(position)


def hull_signed_distance(points, pixels):
    """Signed distance [pixels] of pixel-space points to the convex hull of ``points``; < 0 inside."""
    pts = sorted(map(tuple, np.asarray(points)))

    def half(seq):
        out = []
        for p in seq:
            while len(out) >= 2:
                a, b = np.subtract(out[-1], out[-2]), np.subtract(p, out[-2])
                if a[0] * b[1] - a[1] * b[0] > 0:
                    break
                out.pop()
            out.append(p)
        return out

    lower, upper = half(pts), half(pts[::-1])
    hull = np.array(lower[:-1] + upper[:-1])  # counter-clockwise in (column, row) coordinates
    dist = np.full(len(pixels), -np.inf)
    for a, b in zip(hull, np.roll(hull, -1, axis=0), strict=True):
        e = b - a
        outward = np.array([e[1], -e[0]]) / np.linalg.norm(e)
        dist = np.maximum(dist, (pixels - a) @ outward)
    return dist


def pixel_centres(width, height):
    j, i = np.meshgrid(np.arange(width) + 0.5, np.arange(height) + 0.5)
    return np.column_stack([j.ravel(), i.ravel()])


def check_silhouette(hit, body, verts, camera, margin=0.02):
    """Pixels whose centre is inside the projected hull hit ``body``; those outside do not."""
    px, depth = camera.project(verts, W, H)
    assert np.all(depth > 0.0)
    dist = hull_signed_distance(px, pixel_centres(W, H)).reshape(H, W)
    inside, outside = dist < -margin, dist > margin
    assert inside.sum() > 20 and outside.sum() > 20
    assert np.all(hit[inside] == body)
    assert np.all(hit[outside] != body)
    return hit == body


# ------------------------------------------------------------------------------------ camera


def test_camera_project_inverts_rays():
    cam = Camera(position=(3.0, -4.0, 2.5), target=(0.1, 0.2, -0.3), fov=40.0)
    d = cam.ray_directions(W, H)
    points = np.array(cam.position) + 7.5 * d.reshape(-1, 3)
    px, depth = cam.project(points, W, H)
    np.testing.assert_allclose(px, pixel_centres(W, H), atol=1e-9)
    assert np.all(depth > 0.0)
    with pytest.raises(ValueError, match="parallel"):
        Camera(position=(0, 0, 5), target=(0, 0, 0), up=(0, 0, 1))


def test_auto_camera_frames_every_body(device):
    rng = np.random.default_rng(4)
    shapes = [polydem.ConvexShape.box(1.0, 0.4, 0.2), polydem.ConvexShape.rock(n_points=12, size=0.7, seed=2)]
    pos = rng.uniform(-3.0, 3.0, size=(12, 3)) * [1.0, 0.5, 0.3]
    quat = random_quats(rng, 12)
    kinds = rng.integers(2, size=12)
    layers = render_layers(pos, quat, kinds, shapes, width=W, height=H, device=device, shadows=False)
    cam = layers["camera"]
    verts = np.concatenate([world_vertices(shapes[k], p, q) for k, p, q in zip(kinds, pos, quat, strict=True)])
    px, depth = cam.project(verts, W, H)
    assert np.all(depth > 0.0)
    assert np.all((px >= 0.0) & (px <= [W, H]))
    # Not loose either: the bodies come near a border (the frame fits a box around them).
    assert min(px[:, 0].min(), px[:, 1].min(), W - px[:, 0].max(), H - px[:, 1].max()) < 0.2 * H
    assert set(np.unique(layers["hit"])) == set(range(12)) | {-1}


# ------------------------------------------------------------------------------------ geometry


def test_single_cube_covers_its_projection(device):
    cube = polydem.ConvexShape.box(1.0)
    cam = Camera(position=(2.5, -3.5, 2.0), target=(0.0, 0.0, 0.0), fov=40.0)
    layers = render_layers([[0.0, 0.0, 0.0]], [IDENTITY], [0], [cube], width=W, height=H, camera=cam, device=device)
    mask = check_silhouette(layers["hit"], 0, world_vertices(cube, (0, 0, 0), IDENTITY), cam)
    assert set(np.unique(layers["hit"])) == {0, -1}
    assert np.all(np.isinf(layers["depth"][~mask]))
    # Depth is a distance from the eye, between the nearest and farthest corner.
    corner = np.linalg.norm(world_vertices(cube, (0, 0, 0), IDENTITY) - cam.position, axis=1)
    assert corner.min() - 1e-5 <= layers["depth"][mask].min() and layers["depth"][mask].max() <= corner.max() + 1e-5
    # Background is the sky, the cube is drawn in palette colour 0 (orange: red > green > blue).
    img = layers["image"]
    assert img.shape == (H, W, 3) and img.dtype == np.uint8
    c = img[mask].astype(int)
    assert np.all(c[:, 0] > c[:, 2])
    assert np.all(img[~mask].astype(int).min(axis=1) > 140)  # light sky


def test_nearest_body_wins(device):
    shapes = [polydem.ConvexShape.box(1.0), polydem.ConvexShape.octahedron(1.2)]
    cam = Camera(position=(0.0, -6.0, 0.5), target=(0.0, 0.0, 0.0), fov=40.0)
    front, back = (0.0, -1.0, 0.0), (0.45, 1.0, 0.25)
    for order in ((0, 1), (1, 0)):  # shape 0 in front, then shape 1 in front
        pos = [front, back] if order == (0, 1) else [back, front]
        layers = render_layers(
            pos, [IDENTITY, IDENTITY], [0, 1], shapes, width=W, height=H, camera=cam, device=device, shadows=False
        )
        hit = layers["hit"]
        near = 0 if order == (0, 1) else 1
        far = 1 - near
        verts = [world_vertices(shapes[k], pos[k], IDENTITY) for k in range(2)]
        d = [hull_signed_distance(cam.project(v, W, H)[0], pixel_centres(W, H)).reshape(H, W) for v in verts]
        overlap = (d[0] < -0.02) & (d[1] < -0.02)
        assert overlap.sum() > 20
        assert np.all(hit[overlap] == near)
        only_far = (d[far] < -0.02) & (d[near] > 0.02)
        assert only_far.sum() > 5 and np.all(hit[only_far] == far)
        # Colour of the nearest body's shape: a scalar multiple of its palette entry.
        rgb = layers["color"][overlap]
        ratio = rgb / PALETTE[near]
        np.testing.assert_allclose(ratio, ratio[:, :1].repeat(3, axis=1), rtol=1e-5)


def test_rotation_turns_the_silhouette(device):
    rock = polydem.ConvexShape.rock(n_points=14, size=1.0, seed=7)
    slab = polydem.ConvexShape.box(1.4, 0.6, 0.25)
    cam = Camera(position=(1.5, -4.0, 1.2), target=(0.0, 0.0, 0.0), fov=35.0)
    rng = np.random.default_rng(11)
    for shape in (rock, slab):
        masks = []
        for q in [IDENTITY, *random_quats(rng, 3)]:
            layers = render_layers([[0, 0, 0]], [q], [0], [shape], width=W, height=H, camera=cam, device=device)
            masks.append(check_silhouette(layers["hit"], 0, world_vertices(shape, (0, 0, 0), q), cam))
        assert all(np.sum(masks[0] != m) > 10 for m in masks[1:])
    # A half turn about z maps the box onto itself: the same picture (the ray's pixels are exact).
    turned = quat_from_axis_angle((0, 0, 1), np.pi)
    a = render_layers([[0, 0, 0]], [IDENTITY], [0], [slab], width=W, height=H, camera=cam, device=device)
    b = render_layers([[0, 0, 0]], [turned], [0], [slab], width=W, height=H, camera=cam, device=device)
    assert np.sum(a["hit"] != b["hit"]) <= 2  # rounding at most on an edge


# ------------------------------------------------------------------------------------ reference


def reference_cast(camera, width, height, pos, quat, body_shape, shapes, planes, jitter=(0.0, 0.0)):
    """float64 ray vs half-spaces: (hit item, depth) of each pixel, rays through centre + jitter."""
    eye, forward, right, up = camera.kernel_basis(width, height)
    u = 2.0 * (np.arange(width) + 0.5 + jitter[0]) / width - 1.0
    v = 1.0 - 2.0 * (np.arange(height) + 0.5 + jitter[1]) / height
    d = forward + u[None, :, None] * right + v[:, None, None] * up
    d = (d / np.linalg.norm(d, axis=-1, keepdims=True)).reshape(-1, 3)
    best = np.full(len(d), np.inf)
    item = np.full(len(d), -1)
    for p, (point, normal) in enumerate(planes):
        n = np.asarray(normal, dtype=np.float64) / np.linalg.norm(normal)
        denom = d @ n
        with np.errstate(divide="ignore", invalid="ignore"):
            t = (np.dot(point, n) - eye @ n) / denom
        take = (denom < 0.0) & (t > 0.0) & (t < best)
        best[take], item[take] = t[take], -2 - p
    for b in range(len(pos)):
        shape = shapes[body_shape[b]]
        rot = quat_to_matrix(quat[b])
        o = rot.T @ (eye - pos[b])
        db = d @ rot  # rows: R^T d
        normals, offsets = np.asarray(shape.face_normals), np.asarray(shape.face_offsets)
        denom = db @ normals.T  # (rays, faces)
        gap = offsets - normals @ o
        with np.errstate(divide="ignore", invalid="ignore"):
            t = gap / denom
        t_enter = np.where(denom < 0.0, t, -np.inf).max(axis=1)
        t_exit = np.where(denom > 0.0, t, np.inf).min(axis=1)
        parallel_out = ((denom == 0.0) & (gap < 0.0)).any(axis=1)
        take = ~parallel_out & (t_enter <= t_exit) & (t_enter >= 0.0) & (t_enter < best)
        best[take], item[take] = t_enter[take], b
    return item.reshape(height, width), best.reshape(height, width)


def test_matches_float64_reference(device):
    rng = np.random.default_rng(2024)
    shapes = [
        polydem.ConvexShape.box(1.0, 0.7, 0.4),
        polydem.ConvexShape.tetrahedron(1.3),
        polydem.ConvexShape.octahedron(0.9),
        polydem.ConvexShape.rock(n_points=16, size=1.0, seed=5),
    ]
    radius = max(s.radius for s in shapes)
    pos = []
    while len(pos) < 9:  # bounding spheres apart: no two bodies overlap, no ties in depth
        p = rng.uniform([-2.5, -2.5, 0.0], [2.5, 2.5, 1.5])
        if all(np.linalg.norm(p - q) > 2.0 * radius for q in pos):
            pos.append(p)
    pos = np.array(pos)
    quat = random_quats(rng, len(pos))
    kinds = rng.integers(len(shapes), size=len(pos))
    planes = [((0.0, 0.0, -radius), (0.0, 0.0, 1.0))]
    layers = render_layers(pos, quat, kinds, shapes, planes, width=W, height=H, device=device, elevation=35.0)
    cam = layers["camera"]
    item, depth = reference_cast(cam, W, H, pos, quat, kinds, shapes, planes)
    # Pixels whose answer changes when the ray moves by 1e-3 pixel are on an edge: either answer is right.
    edge = np.zeros((H, W), dtype=bool)
    for jit in ((1e-3, 0.0), (-1e-3, 0.0), (0.0, 1e-3), (0.0, -1e-3)):
        edge |= reference_cast(cam, W, H, pos, quat, kinds, shapes, planes, jit)[0] != item
    assert edge.sum() < 0.05 * W * H
    hit = layers["hit"]
    assert len(set(np.unique(item[item >= 0]))) >= 6  # most bodies are in view
    assert (item == -2).sum() > 100  # and so is the ground
    np.testing.assert_array_equal(hit[~edge], item[~edge])
    same = (hit == item) & (item != -1)
    np.testing.assert_allclose(layers["depth"][same], depth[same], rtol=2e-5)
    assert np.all(np.isinf(layers["depth"][hit == -1]))


def test_hidden_bodies_and_colours(device):
    shapes = [polydem.ConvexShape.box(1.0)]
    cam = Camera(position=(0.0, -6.0, 0.0), target=(0.0, 0.0, 0.0), fov=40.0)
    pos = [(0.0, -1.0, 0.0), (0.0, 1.0, 0.0)]
    layers = render_layers(
        pos,
        [IDENTITY] * 2,
        [0, 0],
        shapes,
        width=W,
        height=H,
        camera=cam,
        device=device,
        visible=[False, True],
        body_colors=[(1.0, 0.0, 0.0), (0.0, 0.0, 1.0)],
        shadows=False,
    )
    assert set(np.unique(layers["hit"])) == {1, -1}
    blue = layers["color"][layers["hit"] == 1]
    assert np.all(blue[:, 2] > 0.2) and np.all(blue[:, :2] == 0.0)
    # No bodies at all: sky and ground only.
    img = render(np.zeros((0, 3)), np.zeros((0, 4)), [], shapes, [((0, 0, 0), (0, 0, 1))], W, H, device=device)
    assert img.shape == (H, W, 3)


def test_supersample_shape_and_agreement(device):
    shapes = [polydem.ConvexShape.box(1.0)]
    img1 = render([[0, 0, 0]], [IDENTITY], [0], shapes, width=W, height=H, device=device)
    img2 = render([[0, 0, 0]], [IDENTITY], [0], shapes, width=W, height=H, device=device, supersample=2)
    assert img2.shape == img1.shape == (H, W, 3)
    assert np.mean(np.abs(img1.astype(int) - img2.astype(int))) < 6.0


# ------------------------------------------------------------------------------------ PNG


def _unfilter(rows, channels):
    """Undo PNG's per-row filters (0 None, 1 Sub, 2 Up, 3 Average, 4 Paeth) of 8-bit rows."""
    h = rows.shape[0]
    out = np.zeros((h, rows.shape[1] - 1), dtype=np.int64)
    for y in range(h):
        kind, line = int(rows[y, 0]), rows[y, 1:].astype(np.int64)
        up = out[y - 1] if y else np.zeros_like(line)
        if kind in (0, 2):
            out[y] = (line + (up if kind == 2 else 0)) % 256
            continue
        row = out[y]
        for i in range(len(line)):
            left = row[i - channels] if i >= channels else 0
            up_left = up[i - channels] if i >= channels else 0
            if kind == 1:
                pred = left
            elif kind == 3:
                pred = (left + up[i]) // 2
            else:
                p = left + up[i] - up_left
                pa, pb, pc = abs(p - left), abs(p - up[i]), abs(p - up_left)
                pred = left if pa <= pb and pa <= pc else up[i] if pb <= pc else up_left
            row[i] = (line[i] + pred) % 256
    return out


def decode_png(data):
    """(width, height, colour type, pixels) of an 8-bit, non-interlaced PNG, decoded here independently."""
    assert data[:8] == b"\x89PNG\r\n\x1a\n"
    pos, chunks = 8, []
    while pos < len(data):
        (length,) = struct.unpack(">I", data[pos : pos + 4])
        kind, body = data[pos + 4 : pos + 8], data[pos + 8 : pos + 8 + length]
        (crc,) = struct.unpack(">I", data[pos + 8 + length : pos + 12 + length])
        assert crc == zlib.crc32(kind + body) & 0xFFFFFFFF
        chunks.append((kind, body))
        pos += 12 + length
    assert chunks[0][0] == b"IHDR" and chunks[-1] == (b"IEND", b"")
    w, h, depth, ctype, comp, filt, interlace = struct.unpack(">IIBBBBB", chunks[0][1])
    assert (depth, comp, filt, interlace) == (8, 0, 0, 0)
    channels = {0: 1, 2: 3, 6: 4}[ctype]
    raw = zlib.decompress(b"".join(body for kind, body in chunks if kind == b"IDAT"))
    assert len(raw) == h * (1 + w * channels)
    rows = np.frombuffer(raw, dtype=np.uint8).reshape(h, 1 + w * channels)
    assert set(np.unique(rows[:, 0])) <= {0, 1, 2, 3, 4}
    out = _unfilter(rows, channels).reshape(h, w, channels)
    return w, h, ctype, out.astype(np.uint8)


def test_png_round_trip(tmp_path, device):
    shapes = [polydem.ConvexShape.box(1.0), polydem.ConvexShape.tetrahedron(1.2)]
    img = render(
        [[0, 0, 0], [1.5, 0.3, 0.0]], [IDENTITY] * 2, [0, 1], shapes, [((0, 0, -0.5), (0, 0, 1))], W, H, device=device
    )
    path = save_png(img, tmp_path / "frame.png")
    w, h, ctype, pixels = decode_png(path.read_bytes())
    assert (w, h, ctype) == (W, H, 2)
    np.testing.assert_array_equal(pixels, img)
    rng = np.random.default_rng(0)
    for shape, ctype in (((5, 7), 0), ((5, 7, 4), 6)):
        data = rng.integers(0, 256, size=shape, dtype=np.uint8)
        w, h, got, pixels = decode_png(save_png(data, tmp_path / "x.PNG").read_bytes())
        assert (w, h, got) == (7, 5, ctype)
        np.testing.assert_array_equal(pixels.reshape(data.shape), data)


def test_bad_path_and_image(tmp_path):
    img = np.zeros((4, 4, 3), dtype=np.uint8)
    for name in ("frame.jpg", "frame", "frame.png.gz"):
        with pytest.raises(ValueError, match=r"\.png"):
            save_png(img, tmp_path / name)
    with pytest.raises(ValueError, match="\\.png"):
        render_simulation(None, tmp_path / "frame.tiff")  # checked before anything is rendered
    with pytest.raises(ValueError, match="uint8"):
        save_png(img.astype(float), tmp_path / "frame.png")
    with pytest.raises(ValueError, match="shape"):
        save_png(np.zeros((4, 4, 2), dtype=np.uint8), tmp_path / "frame.png")


def test_render_simulation(tmp_path, device):
    scene = polydem.Scene(gravity=(0, 0, -9.81), dt="auto")
    scene.add_material("steel", density=7800, law="hertz", k=1e10, restitution=0.5, friction=0.0)
    scene.add_shape("cube", polydem.ConvexShape.box(0.1))
    scene.add_body("cube", "steel", position=(0, 0, 0.06))
    scene.add_body("cube", "steel", position=(0.3, 0, 0.06), kind="fixed")
    scene.add_plane(point=(0, 0, 0), normal=(0, 0, 1), material="steel")
    sim = polydem.Simulation(scene, device=device)
    img = render_simulation(sim, tmp_path / "sim.png", width=W, height=H)
    assert img.shape == (H, W, 3)
    w, h, _, pixels = decode_png((tmp_path / "sim.png").read_bytes())
    assert (w, h) == (W, H)
    np.testing.assert_array_equal(pixels, img)


# ------------------------------------------------------------------------------------ views and cut-away


@pytest.mark.parametrize("elevation, sign", [(90.0, -1.0), (-90.0, 1.0)])
def test_top_and_bottom_views(device, elevation, sign):
    """Elevation +-90: a camera straight above (below) the box, looking along -up (+up); the image
    keeps the roll of the views just short of it."""
    lo, hi = (-1.0, -0.5, 0.0), (1.0, 0.5, 0.4)
    cam = Camera.frame_box(lo, hi, W, H, elevation=elevation, azimuth=-60.0)
    _, forward, right, _ = cam.frame()
    np.testing.assert_allclose(forward, [0.0, 0.0, sign], atol=1e-12)
    near = Camera.frame_box(lo, hi, W, H, elevation=elevation + sign * 1e-3, azimuth=-60.0)
    np.testing.assert_allclose(near.frame()[2], right, atol=1e-4)
    # A cube seen from above shows its top face only: a square, every pixel of it the cube.
    shapes = [polydem.ConvexShape.box(1.0)]
    layers = render_layers([(0, 0, 0)], [IDENTITY], [0], shapes, width=W, height=H, device=device, elevation=elevation)
    assert np.all(np.abs(layers["camera"].frame()[1] - [0, 0, sign]) < 1e-12)
    assert (layers["hit"] == 0).sum() > 0.2 * W * H
    with pytest.raises(ValueError, match=r"elevation in \[-90, 90\]"):
        Camera.frame_box(lo, hi, W, H, elevation=91.0)


def closed_box_scene():
    """A free cube inside a closed box of six fixed slabs: from outside, nothing of it shows."""
    scene = polydem.Scene(gravity=(0, 0, -9.81), dt="auto")
    scene.add_material("steel", density=7800, law="hertz", k=1e10, restitution=0.5, friction=0.0)
    scene.add_shape("cube", polydem.ConvexShape.box(0.2))
    scene.add_shape("slab_x", polydem.ConvexShape.box(0.02, 0.5, 0.5))
    scene.add_shape("slab_y", polydem.ConvexShape.box(0.5, 0.02, 0.5))
    scene.add_shape("slab_z", polydem.ConvexShape.box(0.5, 0.5, 0.02))
    scene.add_body("cube", "steel", position=(0, 0, 0.11))
    for axis, name in enumerate(("slab_x", "slab_y", "slab_z")):
        for side in (-1, 1):
            p = [0.0, 0.0, 0.2]
            p[axis] += side * 0.26
            scene.add_body(name, "steel", position=tuple(p), kind="fixed")
    return scene


def test_render_simulation_cuts_away_what_hides_the_free_bodies(tmp_path, device):
    sim = polydem.Simulation(closed_box_scene(), device=device)
    colors = np.zeros((7, 3))
    colors[0] = (1.0, 0.0, 0.0)  # the cube red, the box green
    colors[1:] = (0.0, 1.0, 0.0)
    options = dict(width=W, height=H, body_colors=colors, shadows=False, light=(0, 0, 1))

    def red(image):
        return int(np.sum((image[..., 0] > 60) & (image[..., 1] < 20)))

    closed = render_simulation(sim, cutaway=False, **options)
    assert red(closed) == 0
    opened = render_simulation(sim, tmp_path / "open.png", **options)
    assert red(opened) > 0.03 * W * H
    assert np.sum(opened[..., 1] > 60) > 0.2 * W * H  # the walls behind the cube stay
    # The camera still frames the whole box, as without the cut-away.
    lo_rows = np.flatnonzero((closed != closed[0, 0]).any(axis=(1, 2)))
    hi_rows = np.flatnonzero((opened != opened[0, 0]).any(axis=(1, 2)))
    assert abs(lo_rows[0] - hi_rows[0]) <= 2 and abs(lo_rows[-1] - hi_rows[-1]) <= 2


def test_drum_scene_shows_its_grains(device):
    """The shipped drum: closed by its slabs and end plates, its grains show once the near parts go."""
    from pathlib import Path

    from polydem.cli.poses import Poses

    scene = polydem.Scene.from_toml(Path(__file__).resolve().parents[1] / "scenes" / "drum.toml")
    free = np.asarray(scene.body_kind) == 0
    colors = np.where(free[:, None], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0])
    poses = Poses(scene, scene.body_position, scene.body_orientation, device)
    image = render_simulation(poses, width=80, height=60, body_colors=colors, shadows=False)
    grains = np.sum((image[..., 0] > 40) & (image[..., 1] < 20))
    assert grains > 0.1 * 80 * 60
    assert np.sum((image[..., 1] > 40) & (image[..., 0] < 20)) > 0.1 * 80 * 60  # the drum's far half


def test_container_bodies_are_grey(device):
    """Fixed and kinematic bodies (a drum turns) are drawn in FIXED_COLOR, free ones by shape."""
    from polydem.render import FIXED_COLOR

    scene = polydem.Scene(gravity=(0, 0, -9.81), dt="auto")
    scene.add_material("steel", density=7800, law="hertz", k=1e10, restitution=0.5, friction=0.0)
    scene.add_shape("cube", polydem.ConvexShape.box(0.1))
    scene.add_body("cube", "steel", position=(-0.2, 0, 0.0), kind="fixed")
    scene.add_body("cube", "steel", position=(0.0, 0, 0.0), kind="kinematic", angular_velocity=(0, 0, 1))
    scene.add_body("cube", "steel", position=(0.2, 0, 0.0))
    sim = polydem.Simulation(scene, device=device)
    seen = {}

    def fake_render(positions, orientations, body_shape, shapes, **kw):
        seen.update(kw)
        return np.zeros((H, W, 3), dtype=np.uint8)

    import polydem.render as render_module

    original = render_module.render
    render_module.render = fake_render
    try:
        render_simulation(sim, width=W, height=H, cutaway=False)
    finally:
        render_module.render = original
    np.testing.assert_allclose(seen["body_colors"][:2], [FIXED_COLOR, FIXED_COLOR])
    np.testing.assert_allclose(seen["body_colors"][2], PALETTE[0])


# ------------------------------------------------------------------------------------ mesh walls


def square_floor(half=1.0, z=0.0):
    v = np.array([[-half, -half, z], [half, -half, z], [half, half, z], [-half, half, z]], dtype=float)
    return v, np.array([[0, 1, 2], [0, 2, 3]])


def test_mesh_floor_drawn_like_a_plane_from_its_front_only(device):
    shapes = [polydem.ConvexShape.box(0.1)]
    args = ([(0, 0, 0.05)], [IDENTITY], [0], shapes)
    cam = Camera.frame_box((-0.3, -0.3, 0.0), (0.3, 0.3, 0.1), W, H)
    common = dict(width=W, height=H, camera=cam, device=device, shadows=False)
    bare = render_layers(*args, **common)
    mesh = render_layers(*args, mesh_walls=[square_floor()], **common)
    plane = render_layers(*args, planes=[((0, 0, 0), (0, 0, 1))], **common)
    floor = mesh["hit"] == -2  # no planes: mesh wall 0 is item -2
    assert floor.sum() > 0.2 * W * H
    assert np.all(bare["hit"][floor] == -1)  # the sky without the mesh
    assert np.abs(mesh["image"].astype(int) - bare["image"]).max(axis=2)[floor].min() > 10
    # Where the square floor is, the picture is the plane's: same items, depths, and the wall colour
    # (the plane's checker differs by its small contrast only).
    assert np.all(plane["hit"][floor] == -2)
    np.testing.assert_allclose(mesh["depth"][floor], plane["depth"][floor], rtol=1e-4)
    np.testing.assert_allclose(mesh["color"][floor], plane["color"][floor], atol=0.05)
    np.testing.assert_array_equal(mesh["hit"] == 0, bare["hit"] == 0)
    # Seen from below, its back, it is not drawn.
    below = render_layers(*args, mesh_walls=[square_floor()], elevation=-40.0, **{**common, "camera": None})
    assert not np.any(below["hit"] == -2)


def test_closed_mesh_drum_shows_its_grains(device):
    trimesh = pytest.importorskip("trimesh")
    scene = polydem.Scene(gravity=(0, 0, -9.81), dt="auto")
    scene.add_material("steel", density=7800, law="hertz", k=1e10, restitution=0.5, friction=0.0)
    scene.add_shape("cube", polydem.ConvexShape.box(0.1))
    for k in range(4):
        scene.add_body("cube", "steel", position=(0.12 * (k - 1.5), 0.0, -0.3))
    drum = trimesh.creation.cylinder(radius=0.5, height=0.6, sections=24)
    drum.apply_transform(trimesh.transformations.rotation_matrix(np.pi / 2, (1, 0, 0)))
    scene.add_mesh_wall(drum, "steel", flip_normals=True, angular_velocity=(0, 1.0, 0), thickness=0.1)
    sim = polydem.Simulation(scene, device=device)
    colors = np.tile([1.0, 0.0, 0.0], (4, 1))
    image = render_simulation(sim, width=80, height=60, body_colors=colors, shadows=False)
    grains = np.sum((image[..., 0] > 40) & (image[..., 1] < 20))
    assert grains > 0.02 * 80 * 60
    grey = (np.abs(image[..., 0].astype(int) - image[..., 2]) < 8) & (image[..., 0] > 60)
    assert grey.sum() > 0.1 * 80 * 60  # the drum's far side behind them


def test_turning_mesh_wall_drawn_at_its_current_pose(device):
    """render_simulation poses a moving mesh wall from mesh_q; the CLI's Poses (a checkpoint's
    mesh_q) gives the same picture, and the wall's initial pose a different one."""
    from polydem.cli.poses import Poses

    scene = polydem.Scene(gravity=(0, 0, -9.81), dt=1e-3)  # no contact in the stepped time
    scene.add_material("steel", density=7800, law="hertz", k=1e6, restitution=0.5, friction=0.0)
    scene.add_shape("cube", polydem.ConvexShape.box(0.1))
    scene.add_body("cube", "steel", position=(0, 0, 0.3))
    scene.add_mesh_wall(square_floor(0.4), "steel", angular_velocity=(0, 0, 20.0))
    sim = polydem.Simulation(scene, device=device)
    sim.step(30)
    options = dict(width=W, height=H, shadows=False)
    image = render_simulation(sim, **options)
    st = sim.state()
    mesh_q = sim.current_state.mesh_q.numpy()
    again = render_simulation(Poses(scene, st["body_position"], st["body_orientation"], device, mesh_q), **options)
    np.testing.assert_array_equal(again, image)
    start = render_simulation(Poses(scene, st["body_position"], st["body_orientation"], device), **options)
    assert (np.abs(start.astype(int) - image).max(axis=2) > 10).sum() > 0.01 * W * H
