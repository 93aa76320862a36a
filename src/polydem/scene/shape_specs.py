"""Shapes from the ``[shapes.NAME]`` tables of a scene file, and the specs of scaled shapes."""

from __future__ import annotations

from dataclasses import dataclass
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
    "compound",
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
    "compound": ("parts", "file", "decompose", "threshold", "max_parts", "seed", "scale"),
}
_PART_PLACEMENT = ("position", "orientation", "rotation")
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
    "parts": "array of convex shape tables, each with a 'type', its keys, and position = [x, y, z] and "
    "rotation = {axis = [ax, ay, az], degrees = angle} (or orientation = [x, y, z, w]) placing it in the grain",
    "decompose": "how to cut the mesh file into convex parts: 'coacd' (CoACD) or 'components' (the hull of each "
    "connected piece)",
    "threshold": "CoACD's concavity threshold, in (0, 1], e.g. 0.05 (smaller: more, finer parts)",
    "max_parts": "the most convex parts CoACD may make, e.g. 16",
    "seed": "random seed, an integer >= 0",
    "scale": "factor applied to the file's coordinates, e.g. 0.001 for mm",
}


_PLATONIC = ("tetrahedron", "octahedron", "dodecahedron", "icosahedron")


def build_shape(
    name: str, spec: dict, key: str, file, base_dir: Path, *, part: bool = False
) -> tuple[ConvexShape, dict]:
    """Build a shape from a ``[shapes.NAME]`` table; returns it and the normalised spec. ``part``: the
    table is a part of a compound shape (convex, with its placement in the grain)."""
    spec = read_table(spec, key, file, what=f"a table [shapes.{name}] with a 'type' key")
    if "type" not in spec:
        raise SceneError(f"missing required key 'type' (one of {', '.join(SHAPE_TYPES)})", f"{key}.type", file)
    kind = read_choice(spec["type"], SHAPE_TYPES, f"{key}.type", file, what="shape type")
    edge_required = ("edge",) if kind in _PLATONIC else ()
    extra = _PART_PLACEMENT if part else ()
    if part and kind == "compound":
        raise SceneError(
            "a part of a compound shape must be convex: give a convex type, not 'compound'", f"{key}.type", file
        )
    check_keys(
        spec,
        ("type", *_SHAPE_KEYS[kind], *extra),
        key,
        file,
        required=_SHAPE_REQUIRED.get(kind, edge_required),
        hints=_SHAPE_HINTS,
        context=f" for type = {kind!r}",
    )
    r = _Spec(spec, key, file, name, base_dir, {"type": kind})
    try:
        shape = _BUILDERS[kind](r)
    except SceneError:
        raise
    except (ValueError, OSError) as exc:  # geometry rejected by ConvexShape (degenerate, unreadable file)
        raise SceneError(f"cannot build the {kind} shape: {exc}", key, file) from exc
    if part:
        shape = _place_part(r, shape)
    return shape, r.out


def _place_part(r: _Spec, shape: ConvexShape) -> ConvexShape:
    from polydem.compound import place
    from polydem.scene.loader import read_rotation

    spec, key, file = r.spec, r.key, r.file
    if "orientation" in spec and "rotation" in spec:
        raise SceneError(
            "give either orientation (quaternion) or rotation (axis and angle), not both", f"{key}.rotation", file
        )
    q = np.array([0.0, 0.0, 0.0, 1.0])
    if "rotation" in spec:
        q = read_rotation(spec["rotation"], f"{key}.rotation", file)
        r.out["orientation"] = q.tolist()
    elif "orientation" in spec:
        q = read_vector(spec["orientation"], 4, f"{key}.orientation", file, label="[x, y, z, w]")
        if abs(np.linalg.norm(q) - 1.0) > 1e-6:
            raise SceneError(
                f"orientation {q.tolist()} is not a unit quaternion (norm {np.linalg.norm(q):.9g}); give "
                "rotation = {axis = [ax, ay, az], degrees = angle} instead",
                f"{key}.orientation",
                file,
            )
        r.out["orientation"] = q.tolist()
    p = np.zeros(3)
    if "position" in spec:
        p = read_vector(spec["position"], 3, f"{key}.position", file, label="[x, y, z]")
        r.out["position"] = p.tolist()
    return place(shape, p, q)


def _compound(r: _Spec):
    from polydem.compound import MAX_PARTS, CompoundShape, CompoundShapeError

    spec, key, file = r.spec, r.key, r.file
    if ("parts" in spec) == ("file" in spec):
        raise SceneError(
            "a compound shape needs either parts = [...] (convex shape tables) or file = '...' with decompose = "
            "'coacd' or 'components', not both or neither",
            key,
            file,
        )
    try:
        if "parts" in spec:
            for k in ("decompose", "threshold", "max_parts", "seed", "scale"):
                if k in spec:
                    raise SceneError(f"{k!r} applies to a mesh file; parts are given as they are", f"{key}.{k}", file)
            parts_in = spec["parts"]
            if not isinstance(parts_in, list) or not parts_in:
                raise SceneError(
                    f"expected a non-empty array of part tables, got {typename(parts_in)}", f"{key}.parts", file
                )
            if len(parts_in) > MAX_PARTS:
                raise SceneError(f"at most {MAX_PARTS} parts, got {len(parts_in)}", f"{key}.parts", file)
            parts, specs = [], []
            for k, p in enumerate(parts_in):
                part, out = build_shape(f"{r.name}[{k}]", p, f"{key}.parts[{k}]", file, r.base_dir, part=True)
                parts.append(part)
                specs.append(out)
            r.out["parts"] = specs
            return CompoundShape(parts, name=r.name)
        path = _mesh_path(r)
        r.out["file"] = str(path.resolve())
        method = read_choice(
            spec.get("decompose", "coacd"), ("coacd", "components"), f"{key}.decompose", file, what="decomposition"
        )
        r.out["decompose"] = method
        opts = {}
        if "threshold" in spec:
            t = read_number(spec["threshold"], f"{key}.threshold", file, positive=True)
            if t > 1.0:
                raise SceneError(f"threshold must be in (0, 1], got {t:g}", f"{key}.threshold", file)
            opts["threshold"] = r.out["threshold"] = t
        if "max_parts" in spec:
            opts["max_parts"] = r.out["max_parts"] = r.count("max_parts", 1, MAX_PARTS)
        if "seed" in spec:
            opts["seed"] = r.out["seed"] = r.count("seed", 0)
        from polydem.shapes import load_mesh

        mesh = load_mesh(path)
        if "scale" in spec:
            r.out["scale"] = read_number(
                spec["scale"], f"{key}.scale", file, positive=True, hint=" (" + _SHAPE_HINTS["scale"] + ")"
            )
            mesh.apply_scale(r.out["scale"])
        return CompoundShape.from_mesh(mesh, name=r.name, decompose=method, **opts)
    except CompoundShapeError as exc:
        raise SceneError(f"cannot build the compound shape: {exc}", key, file) from None


def _mesh_path(r: _Spec) -> Path:
    spec, key, file, base_dir = r.spec, r.key, r.file, r.base_dir
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
    return path


@dataclass
class _Spec:
    """A ``[shapes.NAME]`` table being read: its readers name the key; ``out`` is the normalised spec."""

    spec: dict
    key: str
    file: object
    name: str
    base_dir: Path
    out: dict

    def pos(self, k):
        return read_number(
            self.spec[k], f"{self.key}.{k}", self.file, positive=True, hint=f" ({_SHAPE_HINTS.get(k, 'in m')})"
        )

    def count(self, k, minimum, maximum=None, why=""):
        return read_integer(self.spec[k], f"{self.key}.{k}", self.file, minimum=minimum, maximum=maximum, hint=why)

    def tol(self):
        if "tol" not in self.spec:
            return {}
        t = read_number(self.spec["tol"], f"{self.key}.tol", self.file, nonneg=True)
        if t > 1e-3:
            raise SceneError(
                f"relative tolerance must be in [0, 1e-3], got {t:g} (use ~1e-6 for STL files)",
                f"{self.key}.tol",
                self.file,
            )
        return {"tol": t}


def _box(r: _Spec) -> ConvexShape:
    size = r.spec["size"]
    if is_number(size):
        s = [r.pos("size")] * 3
    else:
        s = read_vector(size, 3, f"{r.key}.size", r.file, label="[sx, sy, sz]").tolist()
        if min(s) <= 0.0:
            raise SceneError(f"box edge lengths must be positive, got {s}", f"{r.key}.size", r.file)
    r.out["size"] = s
    return ConvexShape.box(*s, name=r.name)


def _platonic(r: _Spec) -> ConvexShape:
    r.out["edge"] = r.pos("edge")
    return getattr(ConvexShape, r.out["type"])(r.out["edge"], name=r.name)


def _prism(r: _Spec) -> ConvexShape:
    why = f" (the contact kernels take faces of at most {MAX_FACE_VERTICES} vertices; use a smaller n)"
    r.out.update(n=r.count("n", 3, MAX_FACE_VERTICES, why), radius=r.pos("radius"), height=r.pos("height"))
    return ConvexShape.prism(r.out["n"], r.out["radius"], r.out["height"], name=r.name)


def _rock(r: _Spec) -> ConvexShape:
    spec, key, file, out = r.spec, r.key, r.file, r.out
    why = f" (its hull has 2 n_points - 4 faces, and the contact kernels take at most {MAX_FACES})"
    out.update(n_points=r.count("n_points", 4, MAX_FACES // 2 + 2, why), size=r.pos("size"))
    out["seed"] = r.count("seed", 0) if "seed" in spec else 0
    extra = {}
    if "elongation" in spec:
        el = read_vector(spec["elongation"], 3, f"{key}.elongation", file, label="[ex, ey, ez]")
        if el.min() <= 0.0:
            raise SceneError(f"elongation factors must be positive, got {el.tolist()}", f"{key}.elongation", file)
        extra["elongation"] = el.tolist()
    if "roughness" in spec:
        rough = read_number(spec["roughness"], f"{key}.roughness", file, nonneg=True)
        if rough >= 1.0:
            raise SceneError(f"roughness must be in [0, 1), got {rough:g}", f"{key}.roughness", file)
        extra["roughness"] = rough
    out.update(extra)
    return ConvexShape.rock(out["n_points"], out["size"], out["seed"], name=r.name, **extra)


def _sphere(r: _Spec) -> ConvexShape:
    r.out.update(subdivisions=r.count("subdivisions", 0, 5), radius=r.pos("radius"))
    return ConvexShape.sphere(r.out["subdivisions"], r.out["radius"], name=r.name)


def _mesh(r: _Spec) -> ConvexShape:
    spec, key, file = r.spec, r.key, r.file
    path = _mesh_path(r)
    r.out["file"] = str(path.resolve())
    t = r.tol()
    r.out.update(t)
    shape = ConvexShape.from_file(path, name=r.name, **t)
    if "scale" in spec:
        r.out["scale"] = read_number(
            spec["scale"],
            f"{key}.scale",
            file,
            positive=True,
            hint=" (factor applied to the file's coordinates, e.g. 0.001 for mm)",
        )
        shape = shape.scaled(r.out["scale"])
    return shape


def _points(r: _Spec) -> ConvexShape:
    pts = r.spec["points"]
    if not isinstance(pts, list | tuple | np.ndarray) or len(pts) < 4:
        raise SceneError(
            f"expected an array of at least 4 [x, y, z] points, got {typename(pts)}", f"{r.key}.points", r.file
        )
    rows = [read_vector(p, 3, f"{r.key}.points[{i}]", r.file) for i, p in enumerate(pts)]
    r.out["points"] = [row.tolist() for row in rows]
    t = r.tol()
    r.out.update(t)
    return ConvexShape.from_points(np.array(rows), name=r.name, **t)


_BUILDERS = {
    "box": _box,
    **dict.fromkeys(_PLATONIC, _platonic),
    "prism": _prism,
    "rock": _rock,
    "sphere": _sphere,
    "mesh": _mesh,
    "points": _points,
    "compound": _compound,
}


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
    if kind == "compound":
        if "parts" in spec:
            out["parts"] = []
            for p in spec["parts"]:
                q = scaled_spec(p, factor)
                if "position" in p:
                    q["position"] = [factor * x for x in p["position"]]
                out["parts"].append(q)
        else:
            out["scale"] = factor * spec.get("scale", 1.0)
        return out
    for k in _SCALED_KEYS.get(kind, ()):
        value = spec.get(k, 1.0)
        out[k] = [factor * x for x in value] if isinstance(value, list) else factor * value
    return out
