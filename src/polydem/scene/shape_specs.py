"""Shapes from the ``[shapes.NAME]`` tables of a scene file, and the specs of scaled shapes."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from polydem.scene.errors import SceneError
from polydem.scene.values import (
    check_keys,
    is_number,
    read_choice,
    read_integer,
    read_number,
    read_string,
    read_table,
    read_vector,
    typename,
)
from polydem.shapes import MAX_FACE_VERTICES, MAX_FACES, ConvexShape

SHAPE_TYPES = (
    "box",
    "tetrahedron",
    "octahedron",
    "dodecahedron",
    "icosahedron",
    "prism",
    "rock",
    "sphere",
    "mesh",
    "points",
)
"""Shape ``type`` values of a scene file's ``[shapes.NAME]`` tables."""


_SHAPE_KEYS = {
    "box": ("size",),
    "tetrahedron": ("edge",),
    "octahedron": ("edge",),
    "dodecahedron": ("edge",),
    "icosahedron": ("edge",),
    "prism": ("n", "radius", "height"),
    "rock": ("n_points", "size", "seed", "elongation", "roughness"),
    "sphere": ("subdivisions", "radius"),
    "mesh": ("file", "scale", "tol"),
    "points": ("points", "tol"),
}
_SHAPE_REQUIRED = {
    "box": ("size",),
    "prism": ("n", "radius", "height"),
    "rock": ("n_points", "size"),
    "sphere": ("subdivisions", "radius"),
    "mesh": ("file",),
    "points": ("points",),
}
_SHAPE_HINTS = {
    "size": "edge length(s) in m: size = 0.1 for a cube or size = [sx, sy, sz]; for rock the largest diameter in m",
    "edge": "edge length in m, e.g. edge = 0.1",
    "n": f"number of sides of the base polygon, an integer from 3 to {MAX_FACE_VERTICES}",
    "radius": "circumscribed radius in m",
    "height": "prism height in m",
    "n_points": f"number of hull vertices, an integer from 4 to {MAX_FACES // 2 + 2}",
    "subdivisions": "icosphere subdivision level, 0 to 5",
    "file": "mesh file (OBJ, STL, PLY) relative to the scene file, e.g. file = 'meshes/rock.obj'",
    "points": "array of [x, y, z] points in m",
}


def build_shape(name: str, spec: dict, key: str, file, base_dir: Path) -> tuple[ConvexShape, dict]:
    """Build a shape from a ``[shapes.NAME]`` table; returns it and the normalised spec."""
    spec = read_table(spec, key, file, what=f"a table [shapes.{name}] with a 'type' key")
    if "type" not in spec:
        raise SceneError(f"missing required key 'type' (one of {', '.join(SHAPE_TYPES)})", f"{key}.type", file)
    kind = read_choice(spec["type"], SHAPE_TYPES, f"{key}.type", file, what="shape type")
    edge_required = ("edge",) if kind in ("tetrahedron", "octahedron", "dodecahedron", "icosahedron") else ()
    check_keys(
        spec,
        ("type", *_SHAPE_KEYS[kind]),
        key,
        file,
        required=_SHAPE_REQUIRED.get(kind, edge_required),
        hints=_SHAPE_HINTS,
        context=f" for type = {kind!r}",
    )

    def pos(k):
        return read_number(spec[k], f"{key}.{k}", file, positive=True, hint=f" ({_SHAPE_HINTS.get(k, 'in m')})")

    def count(k, minimum, maximum=None, why=""):
        return read_integer(spec[k], f"{key}.{k}", file, minimum=minimum, maximum=maximum, hint=why)

    def tol():
        if "tol" not in spec:
            return {}
        t = read_number(spec["tol"], f"{key}.tol", file, nonneg=True)
        if t > 1e-3:
            raise SceneError(
                f"relative tolerance must be in [0, 1e-3], got {t:g} (use ~1e-6 for STL files)", f"{key}.tol", file
            )
        return {"tol": t}

    out = {"type": kind}
    try:
        if kind == "box":
            size = spec["size"]
            if is_number(size):
                s = [pos("size")] * 3
            else:
                s = read_vector(size, 3, f"{key}.size", file, label="[sx, sy, sz]").tolist()
                if min(s) <= 0.0:
                    raise SceneError(f"box edge lengths must be positive, got {s}", f"{key}.size", file)
            out["size"] = s
            shape = ConvexShape.box(*s, name=name)
        elif kind in ("tetrahedron", "octahedron", "dodecahedron", "icosahedron"):
            out["edge"] = pos("edge")
            shape = getattr(ConvexShape, kind)(out["edge"], name=name)
        elif kind == "prism":
            why = f" (the contact kernels take faces of at most {MAX_FACE_VERTICES} vertices; use a smaller n)"
            out.update(n=count("n", 3, MAX_FACE_VERTICES, why), radius=pos("radius"), height=pos("height"))
            shape = ConvexShape.prism(out["n"], out["radius"], out["height"], name=name)
        elif kind == "rock":
            why = f" (its hull has 2 n_points - 4 faces, and the contact kernels take at most {MAX_FACES})"
            out.update(n_points=count("n_points", 4, MAX_FACES // 2 + 2, why), size=pos("size"))
            out["seed"] = count("seed", 0) if "seed" in spec else 0
            extra = {}
            if "elongation" in spec:
                el = read_vector(spec["elongation"], 3, f"{key}.elongation", file, label="[ex, ey, ez]")
                if el.min() <= 0.0:
                    raise SceneError(
                        f"elongation factors must be positive, got {el.tolist()}", f"{key}.elongation", file
                    )
                extra["elongation"] = el.tolist()
            if "roughness" in spec:
                r = read_number(spec["roughness"], f"{key}.roughness", file, nonneg=True)
                if r >= 1.0:
                    raise SceneError(f"roughness must be in [0, 1), got {r:g}", f"{key}.roughness", file)
                extra["roughness"] = r
            out.update(extra)
            shape = ConvexShape.rock(out["n_points"], out["size"], out["seed"], name=name, **extra)
        elif kind == "sphere":
            out.update(subdivisions=count("subdivisions", 0, 5), radius=pos("radius"))
            shape = ConvexShape.sphere(out["subdivisions"], out["radius"], name=name)
        elif kind == "mesh":
            rel = read_string(spec["file"], f"{key}.file", file, what="a file path string")
            path = Path(rel).expanduser()
            if not path.is_absolute():
                path = base_dir / path
            if not path.is_file():
                what = "is not a file" if path.exists() else "not found"
                raise SceneError(
                    f"mesh file {rel!r} {what} (looked for '{path}'; relative paths are taken from the folder of the "
                    f"scene file, '{base_dir}')",
                    f"{key}.file",
                    file,
                )
            out["file"] = str(path.resolve())
            t = tol()
            out.update(t)
            shape = ConvexShape.from_file(path, name=name, **t)
            if "scale" in spec:
                out["scale"] = read_number(
                    spec["scale"],
                    f"{key}.scale",
                    file,
                    positive=True,
                    hint=" (factor applied to the file's coordinates, e.g. 0.001 for mm)",
                )
                shape = shape.scaled(out["scale"])
        else:  # points
            pts = spec["points"]
            if not isinstance(pts, list | tuple | np.ndarray) or len(pts) < 4:
                raise SceneError(
                    f"expected an array of at least 4 [x, y, z] points, got {typename(pts)}", f"{key}.points", file
                )
            rows = [read_vector(p, 3, f"{key}.points[{i}]", file) for i, p in enumerate(pts)]
            out["points"] = [r.tolist() for r in rows]
            t = tol()
            out.update(t)
            shape = ConvexShape.from_points(np.array(rows), name=name, **t)
    except SceneError:
        raise
    except (ValueError, OSError) as exc:  # geometry rejected by ConvexShape (degenerate, unreadable file)
        raise SceneError(f"cannot build the {kind} shape: {exc}", key, file) from exc
    return shape, out


_SCALED_KEYS = {
    "box": ("size",),
    "tetrahedron": ("edge",),
    "octahedron": ("edge",),
    "dodecahedron": ("edge",),
    "icosahedron": ("edge",),
    "prism": ("radius", "height"),
    "rock": ("size",),
    "sphere": ("radius",),
    "mesh": ("scale",),
}


def scaled_spec(spec: dict | None, factor: float) -> dict | None:
    """The spec of a shape scaled by ``factor`` about its input origin, or None (then written as points)."""
    if spec is None:
        return None
    out = dict(spec)
    kind = spec["type"]
    if kind == "points":
        out["points"] = [[factor * x for x in p] for p in spec["points"]]
        return out
    for k in _SCALED_KEYS.get(kind, ()):
        value = spec.get(k, 1.0)
        out[k] = [factor * x for x in value] if isinstance(value, list) else factor * value
    return out
