"""Ore parameter sets: breakage (A, b, L_ref), physical, elastic, t_n and damage constants.

Each ore is one TOML file (built-ins in ``msmill/data/ores/``), with one
section per parameter set and a ``source`` text in every section::

    name = "UG2"
    description = "..."

    [breakage]            # paper Eqs. 11-12
    A_pct = 71.8
    b_t_per_kwh = 1.67
    # l_ref_mm = 25.0     # optional; omitted -> DEFAULT_L_REF_MM (flagged)
    source = "..."

    [physical]
    density_kg_m3 = ...
    source = "..."

    [elastic]             # for the DEM contact model
    youngs_modulus_pa = ...
    poisson_ratio = ...
    source = "..."

    [tn]                  # optional; omitted -> packaged fit (tn_constants.toml)
    t2 = [k, s]           # ... t4, t25, t50, t75
    source = "..."

    [damage]              # Tavares damage model
    gamma = ...
    damage_threshold = 1.0
    source = "..."

The registry is case-insensitive: :func:`get_ore`, :func:`list_ores`,
:func:`register_ore` (an :class:`Ore` or a TOML path).

``L_ref`` default
-----------------
:data:`DEFAULT_L_REF_MM` (29.0 mm) is the geometric mean of the
representative sizes of the five standard JK drop-weight size fractions
(63x53, 45x37.5, 31.5x26.5, 22.4x19, 16x13.2 mm), each the geometric mean of
its sieve pair. A and b are fitted to drop-weight data pooled over these
fractions with the size-free law ``t10 = A (1 - exp(-b E))``; with
``L_ref`` at the (log-)centre of those sizes, Eq. 11 reproduces that law at
``L = L_ref`` and spreads the size effect symmetrically in log size around the
data the constants came from. See ``docs/breakage.md``.
"""

from __future__ import annotations

import difflib
import math
import tomllib
from importlib import resources
from pathlib import Path
from typing import Any

from pydantic import ConfigDict, Field, ValidationError, field_validator, model_validator

from msmill.breakage import GAMMA_RANGE, TN_SIZES, TnConstants, default_tn_constants
from msmill.errors import MsmillInputError, from_validation_error
from msmill.validate import InputModel

__all__ = [
    "DEFAULT_L_REF_MM",
    "JK_DROP_WEIGHT_FRACTIONS_MM",
    "Ore",
    "get_ore",
    "list_ores",
    "register_ore",
]

#: Sieve pairs (mm) of the standard JK drop-weight test size fractions.
JK_DROP_WEIGHT_FRACTIONS_MM: tuple[tuple[float, float], ...] = (
    (63.0, 53.0),
    (45.0, 37.5),
    (31.5, 26.5),
    (22.4, 19.0),
    (16.0, 13.2),
)

#: Default reference size (mm): geometric mean of the JK fractions' geometric-mean sizes.
DEFAULT_L_REF_MM: float = round(
    math.exp(
        sum(0.5 * (math.log(a) + math.log(b)) for a, b in JK_DROP_WEIGHT_FRACTIONS_MM)
        / len(JK_DROP_WEIGHT_FRACTIONS_MM)
    ),
    1,
)

DEFAULT_L_REF_SOURCE = (
    f"msmill default L_ref = {DEFAULT_L_REF_MM} mm: geometric mean of the standard JK "
    "drop-weight size fractions (63x53 ... 16x13.2 mm); not calibrated for this ore "
    "(run `msmill ore calibrate`)"
)

_SECTIONS = ("breakage", "physical", "elastic", "tn", "damage")


class Ore(InputModel):
    """Validated parameter set of one ore.

    Attributes
    ----------
    name : str
        Ore name (registry key, case-insensitive).
    description : str
        Free text.
    A_pct : float
        Ab-t10 parameter ``A`` (%), in (0, 100].
    b_t_per_kwh : float
        Ab-t10 parameter ``b`` (t/kWh), > 0.
    l_ref_mm : float
        Reference size ``L_ref`` of Eq. 11 (mm). If not given, set to
        :data:`DEFAULT_L_REF_MM` and ``l_ref_is_default`` is ``True``.
    l_ref_is_default : bool
        Whether ``l_ref_mm`` is the uncalibrated default.
    density_kg_m3 : float
        Rock (particle) density (kg/m³).
    youngs_modulus_pa : float
        Young's modulus of the rock (Pa), for the DEM.
    poisson_ratio : float
        Poisson's ratio, in (-1, 0.5).
    tn : TnConstants
        ``t_n = k t10**s`` constants (default: the packaged fit).
    gamma : float
        Tavares damage exponent ``γ`` (published ~3-5.4).
    damage_threshold : float
        Accumulated damage at which a rock breaks, in (0, 1].
    fineness_ratio : float or None
        ``energy_t10`` breakage only (``[breakage]`` section): the fragments' ``t10 = A (1 - exp(-c x))``
        with ``x`` the Eq. 11 exponent, ``c`` this ratio (dimensionless, > 0); None: not measured.
    sources : dict[str, str]
        Provenance per parameter set: keys ``breakage``, ``l_ref``,
        ``physical``, ``elastic``, ``tn``, ``damage``.
    """

    model_config = ConfigDict(frozen=True, extra="forbid")

    name: str = Field(min_length=1)
    description: str = ""
    A_pct: float = Field(gt=0, le=100)
    b_t_per_kwh: float = Field(gt=0)
    l_ref_mm: float | None = Field(default=None, gt=0)
    l_ref_is_default: bool = False
    density_kg_m3: float = Field(gt=0)
    youngs_modulus_pa: float = Field(gt=0)
    poisson_ratio: float = Field(gt=-1, lt=0.5)
    tn: TnConstants = Field(default_factory=default_tn_constants)
    gamma: float = Field(ge=GAMMA_RANGE[0], le=GAMMA_RANGE[1])
    damage_threshold: float = Field(default=1.0, gt=0, le=1)
    fineness_ratio: float | None = Field(default=None, gt=0)
    sources: dict[str, str] = Field(default_factory=dict)

    @model_validator(mode="before")
    @classmethod
    def _fill_l_ref(cls, data: Any) -> Any:
        if isinstance(data, dict):
            data = dict(data)
            if data.get("l_ref_mm") is None:
                data["l_ref_mm"] = DEFAULT_L_REF_MM
                data["l_ref_is_default"] = True
                srcs = dict(data.get("sources") or {})
                srcs.setdefault("l_ref", DEFAULT_L_REF_SOURCE)
                data["sources"] = srcs
            if data.get("tn") is None:
                data.pop("tn", None)
            elif isinstance(data["tn"], dict) and "k" not in data["tn"]:
                tn = dict(data["tn"])
                src = str(tn.pop("source", "user"))
                data["tn"] = TnConstants.from_mapping(tn, source=src)
        return data

    @field_validator("A_pct", "b_t_per_kwh", "density_kg_m3", "youngs_modulus_pa", "gamma", "fineness_ratio")
    @classmethod
    def _finite(cls, v: float | None) -> float | None:
        if v is not None and not math.isfinite(v):
            raise ValueError("a finite number")
        return v

    @property
    def ab(self) -> float:
        """Product ``A * b`` (a common single-number hardness index)."""
        return self.A_pct * self.b_t_per_kwh

    @classmethod
    def from_dict(cls, data: dict[str, Any], origin: str = "ore") -> Ore:
        """Build from the sectioned TOML layout (see module docstring).

        Parameters
        ----------
        data : dict
            Parsed TOML document.
        origin : str
            Prefix for error messages (e.g. the file name).
        """
        if not isinstance(data, dict):
            raise MsmillInputError(origin, data, "a TOML table")
        flat: dict[str, Any] = {}
        sources: dict[str, str] = {}
        for key, val in data.items():
            if key in _SECTIONS:
                if not isinstance(val, dict):
                    raise MsmillInputError(f"{origin}.{key}", val, "a TOML table [section]")
                sec = dict(val)
                src = sec.pop("source", None)
                if src is None:
                    raise MsmillInputError(f"{origin}.{key}.source", None, "a provenance text")
                sources[key] = str(src)
                if key == "tn":
                    sec["source"] = str(src)
                    flat["tn"] = _tn_from_section(sec, f"{origin}.tn")
                else:
                    if key == "breakage" and sec.get("l_ref_mm") is not None:
                        sources["l_ref"] = str(sec.pop("l_ref_source", src))
                    for k2, v2 in sec.items():
                        flat[k2] = v2
            elif key in ("name", "description"):
                flat[key] = val
            else:
                raise MsmillInputError(
                    f"{origin}.{key}", val, f"keys name, description or sections {', '.join(_SECTIONS)}"
                )
        if "tn" not in flat:
            sources["tn"] = default_tn_constants().source
        flat["sources"] = sources
        try:
            return cls.model_validate(flat)
        except ValidationError as exc:
            raise from_validation_error(exc, origin) from exc

    @classmethod
    def from_toml(cls, path: str | Path) -> Ore:
        """Load an ore from a TOML file (layout in the module docstring)."""
        from msmill.validate import read_text

        text = read_text(path, "path", "ore TOML file")  # exists, a file, UTF-8, not huge
        try:
            data = tomllib.loads(text)
        except tomllib.TOMLDecodeError as exc:
            raise MsmillInputError("path", str(path), f"valid TOML ({str(exc).splitlines()[0]})") from None
        return cls.from_dict(data, origin=Path(path).name)

    def to_dict(self) -> dict[str, Any]:
        """The sectioned TOML layout (``l_ref_mm`` omitted when it is the default)."""
        s = self.sources
        out: dict[str, Any] = {"name": self.name, "description": self.description}
        brk: dict[str, Any] = {"A_pct": self.A_pct, "b_t_per_kwh": self.b_t_per_kwh}
        if not self.l_ref_is_default:
            brk["l_ref_mm"] = self.l_ref_mm
            brk["l_ref_source"] = s.get("l_ref", "")
        if self.fineness_ratio is not None:
            brk["fineness_ratio"] = self.fineness_ratio
        brk["source"] = s.get("breakage", "")
        out["breakage"] = brk
        out["physical"] = {"density_kg_m3": self.density_kg_m3, "source": s.get("physical", "")}
        out["elastic"] = {
            "youngs_modulus_pa": self.youngs_modulus_pa,
            "poisson_ratio": self.poisson_ratio,
            "source": s.get("elastic", ""),
        }
        tn = {f"t{n}": [k, sv] for n, (k, sv) in self.tn.as_dict().items()}
        tn["source"] = self.tn.source
        out["tn"] = tn
        out["damage"] = {
            "gamma": self.gamma,
            "damage_threshold": self.damage_threshold,
            "source": s.get("damage", ""),
        }
        return out

    def with_l_ref(self, l_ref_mm: float, source: str) -> Ore:
        """Copy with a calibrated ``L_ref`` (mm) and its provenance."""
        if not (isinstance(l_ref_mm, int | float) and math.isfinite(l_ref_mm) and l_ref_mm > 0):
            raise MsmillInputError("l_ref_mm", l_ref_mm, "a reference size > 0 mm")
        srcs = dict(self.sources)
        srcs["l_ref"] = source
        return self.model_copy(update={"l_ref_mm": float(l_ref_mm), "l_ref_is_default": False, "sources": srcs})


def _tn_from_section(sec: dict[str, Any], origin: str) -> TnConstants:
    src = str(sec.pop("source"))
    expected = {f"t{n}" for n in TN_SIZES}
    if set(sec) != expected:
        raise MsmillInputError(origin, sorted(sec), f"keys {', '.join(sorted(expected))} as [k, s]")
    return TnConstants.from_mapping(sec, source=src)


# --------------------------------------------------------------------------- registry

_REGISTRY: dict[str, Ore] = {}
_BUILTINS_LOADED = False


def _load_builtins() -> None:
    global _BUILTINS_LOADED
    if _BUILTINS_LOADED:
        return
    _BUILTINS_LOADED = True
    folder = resources.files("msmill").joinpath("data/ores")
    for entry in sorted(folder.iterdir(), key=lambda e: e.name):
        if entry.name.endswith(".toml"):
            data = tomllib.loads(entry.read_text(encoding="utf-8"))
            ore = Ore.from_dict(data, origin=entry.name)
            _REGISTRY.setdefault(ore.name.lower(), ore)


def list_ores() -> list[str]:
    """Names of all registered ores (built-in and user), sorted case-insensitively."""
    _load_builtins()
    return sorted((o.name for o in _REGISTRY.values()), key=str.lower)


def get_ore(name: str) -> Ore:
    """Look an ore up by name (case-insensitive).

    Raises
    ------
    MsmillInputError
        Unknown name (with close matches suggested).
    """
    _load_builtins()
    if not isinstance(name, str):
        raise MsmillInputError("ore", name, f"one of {', '.join(list_ores())}")
    key = name.strip().lower()
    if key in _REGISTRY:
        return _REGISTRY[key]
    close = difflib.get_close_matches(key, list(_REGISTRY), n=2)
    hint = f" (did you mean {', '.join(_REGISTRY[c].name for c in close)}?)" if close else ""
    raise MsmillInputError("ore", name, f"one of {', '.join(list_ores())}{hint}")


def register_ore(ore: Ore | str | Path, *, overwrite: bool = False) -> Ore:
    """Add an ore to the registry (an :class:`Ore` or the path of a TOML file).

    Parameters
    ----------
    ore : Ore or path
        The ore or its TOML file.
    overwrite : bool, optional
        Replace an existing ore of the same (case-insensitive) name.
    """
    _load_builtins()
    if not isinstance(ore, Ore):
        ore = Ore.from_toml(ore)
    key = ore.name.lower()
    if key in _REGISTRY and not overwrite:
        raise MsmillInputError("name", ore.name, "a name not yet registered (or overwrite=True)")
    _REGISTRY[key] = ore
    return ore
