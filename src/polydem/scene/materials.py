"""Materials, the mixing rule of a material pair and the table of every pair of a scene."""

from __future__ import annotations

from dataclasses import dataclass, fields

import numpy as np

from polydem.scene.errors import SceneError, unknown_name
from polydem.scene.values import as_given, check_keys, read_choice, read_number, typename

LAWS = ("linear", "hertz", "power")
"""Contact laws W(V): linear W = k V; hertz W = 2/3 k V^1.5; power W = k V^m / m."""

LAW_UNITS = {"linear": "Pa", "hertz": "J/m^4.5", "power": "J/m^(3m)"}
"""Units of a law's stiffness k, for messages."""

MATERIAL_HINTS = {
    "density": "density in kg/m^3, e.g. density = 7800.0 for steel",
    "law": "contact law: law = 'linear', 'hertz' or 'power'",
    "k": "contact stiffness, e.g. k = 1.0e10 (Pa for linear, J/m^4.5 for hertz, J/m^(3m) for power)",
    "m": "power-law exponent, m >= 1",
    "restitution": "coefficient of restitution e in (0, 1], e.g. restitution = 0.5",
    "friction": "Coulomb friction coefficient mu >= 0, e.g. friction = 0.3",
    "tangential_stiffness": "tangential spring stiffness in N/m, or leave it out to have the simulator derive it",
}


@dataclass(frozen=True, kw_only=True)
class Material:
    """Bulk and contact properties of a material (keyword-only fields, validated on construction).

    Attributes:
        name: label, referenced by bodies and walls.
        density: mass density [kg/m^3], > 0.
        law: contact energy W(V) of the overlap volume V [m^3]: ``"linear"`` W = k V; ``"hertz"``
            W = 2/3 k V^1.5; ``"power"`` W = k V^m / m.
        k: contact stiffness, > 0; units depend on the law: linear Pa (= J/m^3), hertz J/m^4.5,
            power J/m^(3m).
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
    m: float | None = None
    tangential_stiffness: float | None = None

    def __post_init__(self):
        if not isinstance(self.name, str) or not self.name:
            raise SceneError(f"material name must be a non-empty string, got {typename(self.name)}", "materials")
        key = f"materials.{self.name}"
        h = MATERIAL_HINTS
        law = read_choice(self.law, LAWS, f"{key}.law", what="contact law")
        density = read_number(self.density, f"{key}.density", positive=True, hint=f" ({h['density']})")
        k = read_number(self.k, f"{key}.k", positive=True, hint=f" (stiffness in {LAW_UNITS[law]} for law = {law!r})")
        e = read_number(self.restitution, f"{key}.restitution", hint=f" ({h['restitution']})")
        if not 0.0 < e <= 1.0:
            raise SceneError(
                f"must be in (0, 1], got {as_given(self.restitution)} ({h['restitution']})", f"{key}.restitution"
            )
        mu = read_number(self.friction, f"{key}.friction", nonneg=True, hint=f" ({h['friction']})")
        m = self.m
        if law == "power":
            if m is None:
                raise SceneError("law = 'power' needs the exponent m (W = k V^m / m), e.g. m = 2.0", f"{key}.m")
            m = read_number(m, f"{key}.m", hint=f" ({h['m']})")
            if m < 1.0:
                raise SceneError(
                    f"must be >= 1 (m < 1 gives an infinite force at first touch), got {as_given(self.m)}", f"{key}.m"
                )
        elif m is not None:
            raise SceneError(
                f"m is only used by law = 'power'; law = {law!r} has the fixed exponent "
                f"{1.0 if law == 'linear' else 1.5:g}: remove m or use law = 'power'",
                f"{key}.m",
            )
        kt = self.tangential_stiffness
        if kt is not None:
            kt = read_number(kt, f"{key}.tangential_stiffness", positive=True, hint=f" ({h['tangential_stiffness']})")
        for name, value in (
            ("law", law),
            ("density", density),
            ("k", k),
            ("restitution", e),
            ("friction", mu),
            ("m", m),
            ("tangential_stiffness", kt),
        ):
            object.__setattr__(self, name, value)

    @property
    def exponent(self) -> float:
        """Exponent m of W = k V^m / m: 1 for linear, 1.5 for hertz, ``m`` for power."""
        return {"linear": 1.0, "hertz": 1.5}.get(self.law, self.m)

    def contact_law(self):
        """This material's :class:`polydem.contact.ContactLaw` (for contacts with itself)."""
        from polydem.contact import ContactLaw  # imports Warp; keep the scene package host-only

        return ContactLaw(kind=self.law, k=self.k, m=self.exponent)

    def to_dict(self) -> dict:
        """The ``[materials.NAME]`` table of a scene file (without the name)."""
        d = {
            "density": self.density,
            "law": self.law,
            "k": self.k,
            "restitution": self.restitution,
            "friction": self.friction,
        }
        if self.m is not None:
            d["m"] = self.m
        if self.tangential_stiffness is not None:
            d["tangential_stiffness"] = self.tangential_stiffness
        return d


MATERIAL_FIELDS = tuple(f.name for f in fields(Material) if f.name != "name")
MATERIAL_REQUIRED = ("density", "law", "k", "restitution", "friction")


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
        """The pair's :class:`polydem.contact.ContactLaw`."""
        from polydem.contact import ContactLaw

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


class MaterialMethods:
    """The :class:`~polydem.scene.Scene` methods that register materials and mix material pairs."""

    def __init__(self):
        # The state of this group; Scene.__init__ reaches every group's __init__ through super().
        self._materials: dict[str, Material] = {}
        self._material_index: dict[str, int] = {}
        super().__init__()

    @property
    def materials(self) -> dict[str, Material]:
        """Registered materials, name -> :class:`Material`, in insertion (= index) order (a copy)."""
        return dict(self._materials)

    @property
    def material_names(self) -> list[str]:
        return list(self._materials)

    def material_index(self, name: str, *, key: str = "material") -> int:
        """Index of a material in :attr:`materials` (the value stored in :attr:`body_material`).

        ``name`` may also be a registered :class:`Material`; ``key`` is where the name came from, for
        error messages.
        """
        if isinstance(name, Material):
            if self._materials.get(name.name) is not name:
                raise self.error(f"material {name.name!r} is not registered in this scene; use add_material()", key)
            name = name.name
        if not isinstance(name, str):
            raise self.error(f"expected a material name, got {typename(name)}", key)
        if name not in self._material_index:
            raise self.error(
                unknown_name(
                    name, self._materials, "material", "define one with [materials.NAME] or Scene.add_material()"
                ),
                key,
            )
        return self._material_index[name]

    def add_material(self, name: str, **props) -> Material:
        """Register a material; ``props`` are the :class:`Material` fields (density, law, k,
        restitution, friction, and m / tangential_stiffness where needed)."""
        key = f"materials.{name}"
        check_keys(props, MATERIAL_FIELDS, key, self.file, required=MATERIAL_REQUIRED, hints=MATERIAL_HINTS)
        if name in self._materials:
            raise self.error(f"material {name!r} is already defined; choose another name", key)
        try:
            mat = Material(name=name, **props)
        except SceneError as err:
            err.file = self.file
            raise
        self._material_index[name] = len(self._materials)
        self._materials[name] = mat
        return mat

    def pair_material(self, a, b) -> PairMaterial:
        """Contact properties between two materials (names or :class:`Material`); see :func:`pair_material`."""
        ma = self._materials[self.material_names[self.material_index(a, key="material")]]
        mb = self._materials[self.material_names[self.material_index(b, key="material")]]
        try:
            return pair_material(ma, mb)
        except SceneError as err:
            err.file = self.file
            raise

    def pair_table(self) -> dict:
        """Mixed contact properties of every material pair, as (M, M) float64 arrays indexed like
        :attr:`materials`: ``k``, ``restitution``, ``friction``, ``tangential_stiffness`` (NaN where
        the simulator derives it); plus ``law`` (str) and ``exponent`` (float) shared by all."""
        mats = list(self._materials.values())
        if not mats:
            raise self.error("the scene has no materials; add one with [materials.NAME] or add_material()", "materials")
        self.check_laws()
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

    def check_laws(self):
        """All materials share one contact law (the simulator runs one)."""
        mats = list(self._materials.values())
        if not mats:
            return
        ref = mats[0]
        for mat in mats[1:]:
            if (mat.law, mat.exponent) != (ref.law, ref.exponent):
                raise self.error(
                    f"material {mat.name!r} uses law {mat.law!r} (exponent {mat.exponent:g}) but material {ref.name!r} "
                    f"uses law {ref.law!r} (exponent {ref.exponent:g}); all materials of a scene must share one "
                    f"contact law and exponent, since a contact between two of them needs a single W(V): use law = "
                    f"{ref.law!r}"
                    + (f" with m = {ref.exponent:g}" if ref.law == "power" else "")
                    + f" for {mat.name!r} (and convert its k)",
                    f"materials.{mat.name}.law",
                )
