"""The built-in default scene: a few hundred mixed polyhedra poured into a box."""

import numpy as np

from polydem.scene import Scene
from polydem.shapes import ConvexShape


def default_scene(count=300, seed=0):
    """Mixed cubes, tetrahedra, octahedra, prisms and rocks (about 2 cm) dropped into a box.

    The bodies start on a jittered grid with random orientations, none touching, and settle under
    gravity in about half a second. Returns a :class:`~polydem.Scene` with ``duration`` 0.6 s.
    """
    if count < 1:
        raise ValueError(f"count must be at least 1, got {count}")
    rng = np.random.default_rng(seed)
    size = 0.02
    scene = Scene(gravity=(0.0, 0.0, -9.81), dt="auto", name="default", duration=0.6)
    scene.description = f"{count} mixed polyhedra of about {size * 100:g} cm poured into a box"
    scene.add_material("stone", density=2500.0, law="hertz", k=1.0e8, restitution=0.4, friction=0.5)
    shapes = {
        "cube": ConvexShape.box(size),
        "tetrahedron": ConvexShape.tetrahedron(1.4 * size),
        "octahedron": ConvexShape.octahedron(size),
        "prism6": ConvexShape.prism(6, radius=0.55 * size, height=size),
        "rock": ConvexShape.rock(n_points=20, size=1.2 * size, seed=seed),
    }
    for name, shape in shapes.items():
        scene.add_shape(name, shape)
    spacing = 2.0 * max(s.radius for s in shapes.values()) * 1.05
    side = int(np.ceil(np.sqrt(count / 4.0)))
    layers = int(np.ceil(count / side**2))
    inner = side * spacing + spacing
    scene.add_box_container((0.0, 0.0, 0.5 * (layers + 2) * spacing), (inner, inner, (layers + 2) * spacing), "stone")
    grid = np.stack(np.meshgrid(np.arange(side), np.arange(side), np.arange(layers), indexing="ij"), -1).reshape(-1, 3)
    grid = grid[:count].astype(float)
    pos = (grid - [0.5 * (side - 1), 0.5 * (side - 1), 0.0]) * spacing + [0.0, 0.0, 0.5 * spacing + 0.002]
    pos[:, :2] += rng.uniform(-0.1, 0.1, size=(count, 2)) * spacing
    quat = rng.normal(size=(count, 4))
    quat /= np.linalg.norm(quat, axis=1, keepdims=True)
    names = list(shapes)
    kinds = rng.integers(len(names), size=count)
    for k, name in enumerate(names):
        rows = np.flatnonzero(kinds == k)
        if len(rows):
            scene.add_bodies(name, "stone", positions=pos[rows], orientations=quat[rows])
    return scene.validate()
