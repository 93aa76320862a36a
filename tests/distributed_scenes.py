"""Scenes for the decomposed-run tests (tests/test_distributed.py and tests/mpi_job.py)."""

import tomllib
from pathlib import Path

from polydem import Scene

SCENES = Path(__file__).resolve().parents[1] / "scenes"


def box_pour():
    """Cubes and larger tetrahedra (two size classes) thrown into a box container of fixed slabs."""
    return Scene.from_dict(
        {
            "simulation": {"gravity": [0, 0, -9.81], "precision": "mixed", "dt": "auto"},
            "materials": {"g": {"density": 2500, "law": "hertz", "k": 1e9, "restitution": 0.4, "friction": 0.5}},
            "shapes": {"cube": {"type": "box", "size": 0.01}, "big": {"type": "tetrahedron", "edge": 0.022}},
            "walls": [{"type": "box", "center": [0.0, 0.0, 0.2], "inner_size": [0.24, 0.08, 0.4], "material": "g"}],
            "emitters": [
                {
                    "shape": ["cube", "big"],
                    "weights": [3, 1],
                    "material": "g",
                    "count": 80,
                    "region": {"min": [-0.115, -0.035, 0.005], "max": [0.115, 0.035, 0.2]},
                    "orientation": "random",
                    "velocity": [0.0, 0.0, -1.0],
                    "velocity_jitter": 1.0,
                    "seed": 3,
                }
            ],
        }
    )


def mixer():
    """scenes/mixer.toml (a turning drum and baffles of triangle meshes) with non-convex elbows added."""
    data = tomllib.loads((SCENES / "mixer.toml").read_text())
    heap = tomllib.loads((SCENES / "heap.toml").read_text())
    data["shapes"]["elbow"] = heap["shapes"]["elbow"]
    data["emitters"][0]["shape"] = ["cube", "tetrahedron", "elbow"]
    data["emitters"][0]["count"] = 90
    data["emitters"][0]["velocity_jitter"] = 0.5
    data.pop("output", None)
    return Scene.from_dict(data, file=SCENES / "mixer.toml", base_dir=SCENES)


def chain():
    """A row of 24 cubes pressed together on a floor, the first one pushed along the row: a pulse crosses
    the slab boundaries through contacts every step, so ghosts that were not kept exact would show."""
    h = 0.01
    bodies = [
        {
            "shape": "cube",
            "material": "g",
            "position": [i * (h - 5e-5), 0.0, 0.5 * h - 1e-5],
            "velocity": [0.8 if i == 0 else 0.0, 0.0, 0.0],
            "angular_velocity": [0.0, 0.0, 3.0 if i == 5 else 0.0],
        }
        for i in range(24)
    ]
    return Scene.from_dict(
        {
            "simulation": {"gravity": [0, 0, -9.81], "precision": "mixed", "dt": "auto"},
            "materials": {"g": {"density": 2500, "law": "hertz", "k": 1e9, "restitution": 0.5, "friction": 0.3}},
            "shapes": {"cube": {"type": "box", "size": h}},
            "walls": [{"type": "plane", "point": [0, 0, 0], "normal": [0, 0, 1], "material": "g"}],
            "bodies": bodies,
        }
    )


def box_pour_long():
    """box_pour at 4 times the recommended step: grains resting on several others carry damping loads above
    the share (kernels/response.py DAMPING_SHARE), which their ghosts must have from their owners."""
    scene = box_pour()
    scene.dt = 4.0 * scene.time_step().recommended
    return scene


def build(name):
    return {"box_pour": box_pour, "box_pour_long": box_pour_long, "mixer": mixer, "chain": chain}[name]()
