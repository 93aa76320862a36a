"""Materials, the mixing rule of a material pair and the table of every pair of a scene."""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

# The contact laws are declared once, in polydem.kernels.laws (no Warp there); the scene package reads
# LAWS and LAW_UNITS from here.
from polydem.kernels.laws import FREE_EXPONENT_LAWS, LAW_SPECS, LAWS
from polydem.kernels.laws import LAW_UNITS as LAW_UNITS
from polydem.scene.errors import SceneError, unknown_name
from polydem.scene.schema import REQUIRED, Key, Table
from polydem.scene.values import read_number, typename

# The laws whose m the material gives, as messages name them: "law = 'power'".
_FREE_EXPONENT = " or ".join(f"law = {name!r}" for name in FREE_EXPONENT_LAWS)

MATERIAL = Table(
    "[materials.NAME]",
    (
        Key(
            "density",
            unit="kg/m^3",
            range="> 0",
            default=REQUIRED,
            hint="density in kg/m^3, e.g. density = 7800.0 for steel",
        ),
        Key(
            "law",
            "choice",
            choices=LAWS,
            what="contact law",
            default=REQUIRED,
            hint="contact law: law = " + ", ".join(map(repr, LAWS[:-1])) + f" or {LAWS[-1]!r}",
        ),
        Key(
            "k",
            range="> 0",
            default=REQUIRED,
            hint="contact stiffness, e.g. k = 1.0e10 ("
            + ", ".join(f"{unit} for {law}" for law, unit in LAW_UNITS.items())
            + ")",
        ),
        Key(
            "restitution",
            range="(0, 1]",
            default=REQUIRED,
            hint="coefficient of restitution e in (0, 1], e.g. restitution = 0.5",
        ),
        Key(
            "friction", range=">= 0", default=REQUIRED, hint="Coulomb friction coefficient mu >= 0, e.g. friction = 0.3"
        ),
        Key(
            "m",
            range=">= 1",
            why=" (m < 1 gives an infinite force at first touch)",
            hint="power-law exponent, m >= 1",
        ),
        Key(
            "tangential_stiffness",
            unit="N/m",
            range="> 0",
            hint="tangential spring stiffness in N/m, or leave it out to have the simulator derive it",
        ),
    ),
)
"""A ``[materials.NAME]`` table: the fields of :class:`Material` but its name."""

_LAW_KEYS = ("law", "k", "m")


@dataclass(frozen=True, kw_only=True)
class Material:
    """Bulk and contact properties of a material (keyword-only fields, validated on construction).

    Attributes:
        name: label, referenced by bodies and walls.
        density: mass density [kg/m^3], > 0.
        law: contact energy W(V) of the overlap volume V [m^3], a name of
            :class:`polydem.kernels.laws.Law`: ``"linear"`` W = k V; ``"hertz"`` W = 2/3 k V^1.5;
            ``"power"`` W = k V^m / m (:data:`polydem.kernels.laws.LAW_SPECS`).
        k: contact stiffness, > 0; units depend on the law (``LAW_UNITS``): linear Pa (= J/m^3),
            hertz J/m^4.5, power J/m^(3m).
        restitution: normal coefficient of restitution e in (0, 1] [-] (1 = elastic).
        friction: Coulomb friction coefficient mu >= 0 [-].
        m: exponent of the power law, >= 1 (m < 1 gives an infinite force at first touch); only for
            ``law = "power"``, None otherwise.
        tangential_stiffness: tangential (friction) spring stiffness [N/m], > 0, or None to let the
            simulator derive it from the normal stiffness.
    """

    name: str
    density: float
    law: str
    k: float
    restitution: float
    friction: float
    m: float | None = MATERIAL.defaults["m"]
    tangential_stiffness: float | None = MATERIAL.defaults["tangential_stiffness"]

    def __post_init__(self):
        if not isinstance(self.name, str) or not self.name:
            raise SceneError(f"material name must be a non-empty string, got {typename(self.name)}", "materials")
        key = f"materials.{self.name}"
        # str(): a Law is stored by its name, as a scene file gives it.
        law = str(MATERIAL["law"].read(self.law, f"{key}.law"))
        # The law's own keys (k's unit, whether m is given) are read here; every other key as declared.
        values = MATERIAL.read({name: getattr(self, name) for name in MATERIAL.names if name not in _LAW_KEYS}, key)
        k = read_number(self.k, f"{key}.k", positive=True, hint=f" (stiffness in {LAW_UNITS[law]} for law = {law!r})")
        m = self.m
        spec = LAW_SPECS[law]
        if spec.fixed_exponent is None:
            if m is None:
                raise SceneError(f"law = {law!r} needs the exponent m ({spec.formula}), e.g. m = 2.0", f"{key}.m")
            m = MATERIAL["m"].read(m, f"{key}.m")
        elif m is not None:
            raise SceneError(
                f"m is only used by {_FREE_EXPONENT}; law = {law!r} has the fixed exponent "
                f"{spec.fixed_exponent:g}: remove m or use {_FREE_EXPONENT}",
                f"{key}.m",
            )
        for name, value in {**values, "law": law, "k": k, "m": m}.items():
            object.__setattr__(self, name, value)

    @property
    def exponent(self) -> float:
        """Exponent m of W = k V^m / m: 1 for linear, 1.5 for hertz, ``m`` for power."""
        return LAW_SPECS[self.law].exponent(self.m)

    def contact_law(self):
        """This material's :class:`polydem.batch.ContactLaw` (for contacts with itself)."""
        from polydem.batch import ContactLaw  # imports Warp; keep the scene package host-only

        return ContactLaw(kind=self.law, k=self.k, m=self.exponent)

    def to_dict(self) -> dict:
        """The ``[materials.NAME]`` table of a scene file (without the name)."""
        return MATERIAL.write(self)


@dataclass(frozen=True)
class PairMaterial:
    """Contact properties of a pair of materials (see :func:`pair_material`).

    Attributes:
        law: contact law shared by both materials.
        exponent: exponent m of W = k V^m / m [-].
        k: combined stiffness (units of the law).
        restitution: combined coefficient of restitution [-].
        friction: combined friction coefficient [-].
        tangential_stiffness: combined tangential stiffness [N/m] or None (derived by the simulator).
    """

    law: str
    exponent: float
    k: float
    restitution: float
    friction: float
    tangential_stiffness: float | None

    def contact_law(self):
        """The pair's :class:`polydem.batch.ContactLaw`."""
        from polydem.batch import ContactLaw

        return ContactLaw(kind=self.law, k=self.k, m=self.exponent)


def _harmonic(a: float, b: float) -> float:
    return 2.0 * a * b / (a + b)


def pair_material(a: Material, b: Material) -> PairMaterial:
    """Mixing rule for a contact between materials ``a`` and ``b``.

    * The law and its exponent must agree (a contact has a single W(V)); otherwise SceneError. A
      scene therefore requires all its materials to share the law and exponent (checked by
      :meth:`Scene.validate`).
    * ``k = 2 k_a k_b / (k_a + k_b)``: the harmonic mean, i.e. twice the stiffness of the two
      springs in series, so equal materials give ``k``.
    * ``restitution = min(e_a, e_b)`` and ``friction = min(mu_a, mu_b)``: the weaker material rules.
    * ``tangential_stiffness``: harmonic mean when both are given, else None (derived later by the
      simulator).
    """
    if (a.law, a.exponent) != (b.law, b.exponent):
        raise SceneError(
            f"materials {a.name!r} (law {a.law!r}, exponent {a.exponent:g}) and {b.name!r} (law {b.law!r}, exponent "
            f"{b.exponent:g}) can meet in a contact but use different contact laws; a contact needs one W(V), so give "
            "all materials of a scene the same law (and the same m for law = 'power')",
            f"materials.{b.name}.law",
        )
    kt = None
    if a.tangential_stiffness is not None and b.tangential_stiffness is not None:
        kt = _harmonic(a.tangential_stiffness, b.tangential_stiffness)
    return PairMaterial(
        law=a.law,
        exponent=a.exponent,
        k=_harmonic(a.k, b.k),
        restitution=min(a.restitution, b.restitution),
        friction=min(a.friction, b.friction),
        tangential_stiffness=kt,
    )


@dataclass
class MaterialTable:
    """The materials of a scene: name -> :class:`Material` in insertion (= index) order, and each name's index."""

    by_name: dict[str, Material] = field(default_factory=dict)
    index: dict[str, int] = field(default_factory=dict)


def material_index(scene, name: str, *, key: str = "material") -> int:
    """:meth:`Scene.material_index <polydem.scene.Scene.material_index>` of ``scene``."""
    table = scene.material_table
    if isinstance(name, Material):
        if table.by_name.get(name.name) is not name:
            raise scene.error(f"material {name.name!r} is not registered in this scene; use add_material()", key)
        name = name.name
    if not isinstance(name, str):
        raise scene.error(f"expected a material name, got {typename(name)}", key)
    if name not in table.index:
        raise scene.error(
            unknown_name(name, table.by_name, "material", "define one with [materials.NAME] or Scene.add_material()"),
            key,
        )
    return table.index[name]


def add_material(scene, name: str, **props) -> Material:
    """:meth:`Scene.add_material <polydem.scene.Scene.add_material>` of ``scene``."""
    key = f"materials.{name}"
    table = scene.material_table
    MATERIAL.check(props, key, scene.file)
    if name in table.by_name:
        raise scene.error(f"material {name!r} is already defined; choose another name", key)
    try:
        mat = Material(name=name, **props)
    except SceneError as err:
        err.file = scene.file
        raise
    table.index[name] = len(table.by_name)
    table.by_name[name] = mat
    return mat


def scene_pair_material(scene, a, b) -> PairMaterial:
    """:meth:`Scene.pair_material <polydem.scene.Scene.pair_material>` of ``scene``."""
    mats = list(scene.material_table.by_name.values())
    ma = mats[material_index(scene, a, key="material")]
    mb = mats[material_index(scene, b, key="material")]
    try:
        return pair_material(ma, mb)
    except SceneError as err:
        err.file = scene.file
        raise


def pair_table(scene) -> dict:
    """:meth:`Scene.pair_table <polydem.scene.Scene.pair_table>` of ``scene``."""
    mats = list(scene.material_table.by_name.values())
    if not mats:
        raise scene.error("the scene has no materials; add one with [materials.NAME] or add_material()", "materials")
    check_laws(scene)
    nm = len(mats)
    out = {k: np.empty((nm, nm)) for k in ("k", "restitution", "friction", "tangential_stiffness")}
    for i, a in enumerate(mats):
        for j, b in enumerate(mats):
            pm = pair_material(a, b)
            out["k"][i, j] = pm.k
            out["restitution"][i, j] = pm.restitution
            out["friction"][i, j] = pm.friction
            kt = pm.tangential_stiffness
            out["tangential_stiffness"][i, j] = np.nan if kt is None else kt
    out["law"] = mats[0].law
    out["exponent"] = mats[0].exponent
    return out


def check_laws(scene):
    """All materials of ``scene`` share one contact law (the simulator runs one)."""
    mats = list(scene.material_table.by_name.values())
    if not mats:
        return
    ref = mats[0]
    for mat in mats[1:]:
        if (mat.law, mat.exponent) != (ref.law, ref.exponent):
            raise scene.error(
                f"material {mat.name!r} uses law {mat.law!r} (exponent {mat.exponent:g}) but material {ref.name!r} "
                f"uses law {ref.law!r} (exponent {ref.exponent:g}); all materials of a scene must share one "
                f"contact law and exponent, since a contact between two of them needs a single W(V): use law = "
                f"{ref.law!r}"
                + (f" with m = {ref.exponent:g}" if ref.law in FREE_EXPONENT_LAWS else "")
                + f" for {mat.name!r} (and convert its k)",
                f"materials.{mat.name}.law",
            )
