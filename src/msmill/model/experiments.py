"""Experiment and plant-survey files: one validated TOML file per experiment.

Two kinds share one folder (``docs/validation.md``):

* ``kind = "survey"``: a mill run (plant survey or pilot experiment)::

      kind = "survey"
      id = "ug2-s01"                     # unique in the folder
      ore = "UG2"                        # ore registry name
      source = "who measured it, when, how (free text)"
      weight = 1.0                       # optional weight in calibration

      [feed]
      rate_tph = 30.0
      size_mm = [2.0, 4.75, 9.5, 19.0, 31.5]
      passing_pct = [2.0, 6.0, 18.0, 58.0, 100.0]

      [operating]                        # as in run files (msmill.model.runfile)
      speed_rpm = 1500.0                 # or stage_speeds_rpm = [...]
      bottom_speed_factor = 2.0
      gate_deg = 40.0

      [product]                          # measured product PSD
      size_mm = [0.075, 0.15, ...]
      passing_pct = [3.1, 5.0, ...]

      [measured]                         # optional
      power_kw = 120.0

* ``kind = "single_impact"``: a laboratory single-impact test (one impact per
  rock at ``impact_speed_m_s``) with ``id``, ``ore``, ``source``,
  ``impact_speed_m_s``, ``[feed]`` (``size_mm``, ``passing_pct``; no rate)
  and ``[product]``.

Instead of inline ``size_mm`` / ``passing_pct`` a ``[feed]`` or ``[product]``
section may give ``file = "product.csv"`` (columns ``size_mm, passing_pct``;
``#`` lines are comments; relative to the experiment file). Written back
(:func:`write_experiment`) the table is inline.

Every error is one line naming the file and the field
(``ug2-s01.toml.feed.rate_tph: got -3; allowed: ...``).
"""

from __future__ import annotations

import tomllib
from collections.abc import Iterable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Literal

import numpy as np
from pydantic import BaseModel, ConfigDict, Field, ValidationError, model_validator

from msmill.errors import MsmillInputError, from_validation_error
from msmill.model.runfile import OperatingSection
from msmill.psd import PSD
from msmill.validate import one_of

__all__ = ["Experiment", "ExperimentSet", "read_experiment", "read_experiments", "write_experiment"]

KINDS = ("survey", "single_impact")


class _Section(BaseModel):
    model_config = ConfigDict(extra="forbid")


class PassingSection(_Section):
    size_mm: list[float] = Field(min_length=2)
    passing_pct: list[float] = Field(min_length=2)

    @model_validator(mode="after")
    def _check(self) -> PassingSection:
        x, p = np.asarray(self.size_mm), np.asarray(self.passing_pct)
        if x.shape != p.shape:
            raise ValueError(f"size_mm and passing_pct of equal length (got {x.size} and {p.size})")
        if np.any(~np.isfinite(x)) or np.any(x <= 0) or np.any(np.diff(x) <= 0):
            raise ValueError("size_mm strictly increasing, > 0 mm")
        if np.any(~np.isfinite(p)) or np.any(p < 0) or np.any(p > 100) or np.any(np.diff(p) < -1e-9):
            raise ValueError("passing_pct within 0-100 %, non-decreasing with size")
        return self

    def psd(self) -> PSD:
        """The distribution on the table's own sieves (``PSD.from_passing``)."""
        return PSD.from_passing(self.size_mm, self.passing_pct)


class FeedRateSection(PassingSection):
    rate_tph: float = Field(gt=0)


class MeasuredSection(_Section):
    power_kw: float | None = Field(default=None, gt=0)


class _ExperimentFile(_Section):
    """Fields every experiment file has."""

    id: str = Field(min_length=1)
    ore: str = Field(min_length=1)
    source: str = Field(min_length=1)
    weight: float = Field(default=1.0, gt=0)


class _SurveyFile(_ExperimentFile):
    kind: Literal["survey"]
    feed: FeedRateSection
    operating: OperatingSection
    product: PassingSection
    measured: MeasuredSection = Field(default_factory=MeasuredSection)


class _ImpactFile(_ExperimentFile):
    kind: Literal["single_impact"]
    impact_speed_m_s: float = Field(gt=0)
    feed: PassingSection
    product: PassingSection


@dataclass(frozen=True)
class Experiment:
    """One validated experiment (survey or single-impact test).

    Attributes
    ----------
    kind : {"survey", "single_impact"}
    id, ore, source : str
        Identifier, ore registry name, provenance text.
    feed_psd, product_psd : msmill.psd.PSD
        Feed and measured product on their own sieves.
    feed_tph : float or None
        Feed rate (t/h) of a survey.
    operating : dict or None
        Operating fields of a survey (``speed_rpm`` ... ``gate_deg``).
    impact_speed_m_s : float or None
        Impact speed of a single-impact test (m/s).
    power_kw : float or None
        Measured power draw of a survey (kW), if any.
    weight : float
        Weight in calibration objectives.
    path : Path or None
        The file it was read from.
    """

    kind: str
    id: str
    ore: str
    source: str
    feed_psd: PSD
    product_psd: PSD
    feed_tph: float | None = None
    operating: dict[str, Any] | None = None
    impact_speed_m_s: float | None = None
    power_kw: float | None = None
    weight: float = 1.0
    path: Path | None = None
    raw: dict[str, Any] = field(default_factory=dict, repr=False, compare=False)

    def operating_point(self) -> Any:
        """The survey's :class:`msmill.machine.OperatingPoint` (feed rate included)."""
        from msmill.machine import OperatingPoint

        if self.kind != "survey":
            raise MsmillInputError(f"{self.id}.kind", self.kind, "a survey (only surveys have an operating point)")
        try:
            return OperatingPoint.model_validate({**self.operating, "feed_tph": self.feed_tph})
        except ValidationError as exc:
            raise from_validation_error(exc, prefix=f"{self.id}.operating") from None

    def to_dict(self) -> dict[str, Any]:
        """The TOML layout of the module docstring (what :func:`write_experiment` writes)."""
        def table(psd_or_raw: dict[str, Any]) -> dict[str, Any]:
            return {"size_mm": list(psd_or_raw["size_mm"]), "passing_pct": list(psd_or_raw["passing_pct"])}

        out: dict[str, Any] = {"kind": self.kind, "id": self.id, "ore": self.ore, "source": self.source}
        if self.weight != 1.0:
            out["weight"] = self.weight
        if self.kind == "single_impact":
            out["impact_speed_m_s"] = self.impact_speed_m_s
            out["feed"] = table(self.raw["feed"])
        else:
            out["feed"] = {"rate_tph": self.feed_tph, **table(self.raw["feed"])}
            out["operating"] = dict(self.operating or {})
        out["product"] = table(self.raw["product"])
        if self.power_kw is not None:
            out["measured"] = {"power_kw": self.power_kw}
        return out


def _inline_csv(data: dict[str, Any], origin: str, base: Path | None) -> dict[str, Any]:
    """Replace ``file = "x.csv"`` in ``[feed]`` / ``[product]`` by the table it holds."""
    import pandas as pd

    out = dict(data)
    for sec in ("feed", "product"):
        tab = out.get(sec)
        if not isinstance(tab, dict) or "file" not in tab:
            continue
        tab = dict(tab)
        name = tab.pop("file")
        field = f"{origin}.{sec}.file"
        if "size_mm" in tab or "passing_pct" in tab:
            raise MsmillInputError(field, name, "either file or size_mm + passing_pct, not both")
        p = Path(str(name))
        p = p if p.is_absolute() or base is None else base / p
        if not p.is_file():
            raise MsmillInputError(field, str(name), "an existing CSV file (relative to the experiment file)")
        try:
            frame = pd.read_csv(p, comment="#", skipinitialspace=True)
        except (pd.errors.ParserError, pd.errors.EmptyDataError, UnicodeDecodeError) as exc:
            raise MsmillInputError(field, str(name), f"a readable CSV file ({exc})") from None
        frame.columns = [str(c).strip() for c in frame.columns]
        if not {"size_mm", "passing_pct"} <= set(frame.columns):
            raise MsmillInputError(f"{field}.columns", list(frame.columns), "columns size_mm and passing_pct")
        vals = frame[["size_mm", "passing_pct"]].apply(pd.to_numeric, errors="coerce")
        if vals.isna().any().any():
            raise MsmillInputError(f"{field}.rows", str(name), "numbers in every row")
        tab["size_mm"] = [float(v) for v in vals["size_mm"]]
        tab["passing_pct"] = [float(v) for v in vals["passing_pct"]]
        out[sec] = tab
    return out


def experiment_from_dict(data: dict[str, Any], origin: str = "experiment", path: Path | None = None,
                         ores: Iterable[str] = ()) -> Experiment:
    """Validate a parsed experiment document (errors name ``origin`` and the field).

    ``ores``: ore names known besides the registry (a user's own ore files).
    """
    if not isinstance(data, dict):
        raise MsmillInputError(origin, type(data).__name__, "a TOML table")
    data = _inline_csv(data, origin, path.parent if path is not None else None)
    kind = one_of(data.get("kind"), f"{origin}.kind", KINDS)
    model = _SurveyFile if kind == "survey" else _ImpactFile
    try:
        v = model.model_validate(data)
    except ValidationError as exc:
        raise from_validation_error(exc, prefix=origin) from None
    from msmill.ore import get_ore

    known = tuple(ores)
    try:
        if v.ore not in known:
            get_ore(v.ore)
    except MsmillInputError as exc:
        allowed = exc.allowed + (f", or an ore file's name ({', '.join(known)})" if known else "")
        raise MsmillInputError(f"{origin}.ore", v.ore, allowed) from None
    raw = {"feed": v.feed.model_dump(), "product": v.product.model_dump()}
    common = dict(kind=kind, id=v.id, ore=v.ore, source=v.source, feed_psd=v.feed.psd(),
                  product_psd=v.product.psd(), weight=v.weight, path=path, raw=raw)
    if isinstance(v, _SurveyFile):
        exp = Experiment(**common, feed_tph=v.feed.rate_tph,
                         operating=v.operating.model_dump(exclude_none=True),
                         power_kw=v.measured.power_kw)
        exp.operating_point()  # stage speeds / design-space checks now, naming the file
        return exp
    return Experiment(**common, impact_speed_m_s=v.impact_speed_m_s)


def read_experiment(path: str | Path, ores: Iterable[str] = ()) -> Experiment:
    """Read and validate one experiment TOML file (``ores``: as :func:`experiment_from_dict`)."""
    p = Path(path)
    if not p.is_file():
        raise MsmillInputError("experiment file", str(p), "an existing TOML file")
    try:
        data = tomllib.loads(p.read_text(encoding="utf-8"))
    except (tomllib.TOMLDecodeError, UnicodeDecodeError) as exc:
        raise MsmillInputError(p.name, str(exc).split("\n")[0], "valid TOML") from None
    return experiment_from_dict(data, origin=p.name, path=p, ores=ores)


def write_experiment(exp: Experiment, path: str | Path) -> Path:
    """Write ``exp`` as TOML (temp file, then rename: never a half-written file)."""
    import tomli_w

    p = Path(path)
    tmp = p.with_name(p.name + ".tmp")
    tmp.write_text(tomli_w.dumps(exp.to_dict()), encoding="utf-8")
    tmp.replace(p)
    return p


@dataclass(frozen=True)
class ExperimentSet:
    """The experiments of one folder, in file-name order."""

    folder: Path
    experiments: tuple[Experiment, ...]

    @property
    def surveys(self) -> list[Experiment]:
        """Mill surveys."""
        return [e for e in self.experiments if e.kind == "survey"]

    @property
    def impact_tests(self) -> list[Experiment]:
        """Laboratory single-impact tests."""
        return [e for e in self.experiments if e.kind == "single_impact"]

    def ores(self, kind: str = "survey") -> list[str]:
        """Ore names with at least one experiment of ``kind``, in order of appearance."""
        return list(dict.fromkeys(e.ore for e in self.experiments if e.kind == kind))


def read_experiments(folder: str | Path, ores: Iterable[str] = (),
                     skip: Iterable[str | Path] = ()) -> ExperimentSet:
    """Read every ``*.toml`` in ``folder`` (not recursive); ids must be unique.

    ``ores``: ore names known besides the registry (:func:`experiment_from_dict`);
    ``skip``: files that are not experiments (a user's ore files kept in the folder).

    Raises
    ------
    MsmillInputError
        Missing folder, no experiment files, a bad file (named), a repeated id.
    """
    d = Path(folder)
    if not d.is_dir():
        raise MsmillInputError("experiments folder", str(d), "an existing folder of experiment TOML files")
    skipped = {Path(f).resolve() for f in skip}
    files = sorted(f for f in d.glob("*.toml") if f.resolve() not in skipped)
    if not files:
        raise MsmillInputError("experiments folder", str(d), "a folder with at least one *.toml experiment file")
    known = tuple(ores)
    exps = [read_experiment(f, known) for f in files]
    seen: dict[str, str] = {}
    for e, f in zip(exps, files, strict=True):
        if e.id in seen:
            raise MsmillInputError(f"{f.name}.id", e.id, f"an id not used already (by {seen[e.id]})")
        seen[e.id] = f.name
    return ExperimentSet(d, tuple(exps))
