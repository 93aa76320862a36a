"""The built-in default scene: a few hundred mixed polyhedra poured into a box.

The scene is the scene file ``default.toml`` shipped inside the package (``polydem/scenes/``; the
repository's ``scenes/default.toml`` is the same file), so it reads like any other scene and
``polydem run`` without a scene file runs exactly that file.
"""

import copy
import math
import tomllib
from importlib import resources

from polydem.scene import Scene, SceneError

DEFAULT_COUNT = 300
"""Number of bodies of the packaged default scene."""


def default_scene_path():
    """The packaged ``default.toml`` (a :class:`importlib.resources.abc.Traversable`; a path on disk
    for a normal install)."""
    return resources.files("polydem").joinpath("scenes", "default.toml")


def default_scene(count=DEFAULT_COUNT, seed=0):
    """Mixed cubes, tetrahedra, octahedra, hexagonal prisms and rocks (about 2 cm) poured into a box.

    Loads the packaged ``default.toml``: 300 bodies, 60 of each shape, on a jittered grid at the
    bottom of an open box, randomly oriented and at rest, none touching; they settle under gravity
    in about half a second (``duration`` 0.6 s).

    Args:
        count: number of bodies (the emitter's ``count``); above 300 the box and the emitter's
            region grow in height to hold them.
        seed: the emitter's seed (placement, orientations and the order of the shapes).

    Returns:
        The validated :class:`~polydem.Scene`.
    """
    if isinstance(count, bool) or not isinstance(count, int) or count < 1:
        raise SceneError(f"count must be an integer >= 1, got {count!r}", "emitters[0].count")
    path = default_scene_path()
    if not path.is_file():
        raise FileNotFoundError(
            f"the packaged default scene '{path}' is missing: polydem was installed without its package data "
            '(pyproject.toml needs [tool.setuptools.package-data] polydem = ["scenes/*.toml"]); reinstall it'
        )
    with path.open("rb") as fh:
        data = tomllib.load(fh)
    if count != DEFAULT_COUNT or seed != 0:
        data = copy.deepcopy(data)
        emitter = data["emitters"][0]
        emitter["count"] = count
        emitter["seed"] = seed
        if count > DEFAULT_COUNT:
            # The packaged region holds 600 bodies; grow the box and the region in height alike.
            grow = math.ceil(count / DEFAULT_COUNT)
            box = data["walls"][0]
            box["inner_size"][2] *= grow
            box["center"][2] = box["center"][2] - 0.5 * box["inner_size"][2] / grow + 0.5 * box["inner_size"][2]
            emitter["region"]["max"][2] = emitter["region"]["min"][2] + box["inner_size"][2]
        data["simulation"]["description"] = f"{count} mixed polyhedra of about 2 cm poured into a box"
    return Scene.from_dict(data, file=str(path), base_dir=None)
