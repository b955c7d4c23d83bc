"""The paper's three observations on its machine as statistical statements about DEM runs (issue 37).

The paper says of its mill: (a) "the top stage of the machine has lower material kicked back",
(b) "the pass-through percentage increases with rotor speed", (c) "the refeed percentage is
lower for bigger particles". Over runs of one machine configuration at several rock sizes,
upper-stage speeds and feed seeds (``scripts/rotation_sense_study.py``) each becomes a test:

(a) ``top_least_kickback``: per stage ``s = 2..n`` the contrast ``k_s - k_1`` (kickback fractions),
    averaged over the (size, speed) points; the statement's effect and ``z`` are those of the stage
    closest to stage 1 (the smallest ``z``): stage 1 must be lower than **every** other stage.
(b) ``pass_rises_with_speed``: the pass-through at the highest speed minus that at the lowest,
    averaged over the sizes that have both; decided on the pass-through averaged over the stages
    (per stage reported too). Paper's sign: positive.
(c) ``refeed_falls_with_size``: the least-squares slope of the stage-1 refeed against
    ``log2(size)`` (per doubling of the rock size) at each speed, averaged over the speeds; decided on
    stage 1 (per stage and averaged over stages reported too). Paper's sign: negative.

**Errors.** A group is the runs of one configuration at one (size, speed): its feed seeds are
replicas. The per-run variance of a quantity is the larger of the between-seed sample variance
(with two seeds or more) and the mean of the runs' own squared sampling errors (batch means,
``StageStatistics.sampling_error``; a quantity made of several stages adds them in quadrature);
the group mean's error is ``sqrt(variance / n_seeds)``. Taking the larger guards against a scatter
estimated from two or three seeds that happens to be small. Contrasts are linear in group means
of independent runs, so their errors add in quadrature. A quantity made of several stages of one
run (a difference of two stages, an average over stages) is formed per run first, so the
between-seed scatter carries the correlation between the stages of a run.

**Agreement.** A statement *agrees* when its ``z`` has the paper's sign and ``|z| > Z_AGREE`` (2):
``z`` is the contrast over its error, compared in the paper's direction (positive: agrees).
:func:`pick_default` ranks the configurations by the number of statements that agree, then by the
share of their runs that reached steady state (the paper's machine runs steady at its operating
points; a run that chokes is left out of the statements), then by the number of statements with the
paper's sign, then by the sum of the signed ``z`` clipped to ``+-Z_CLIP`` (5), so one very strong
statement cannot outweigh two weak ones.
"""

from __future__ import annotations

import json
import math
from collections.abc import Callable, Iterable, Sequence
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from msmill.errors import MsmillInputError

#: rotation-sense configurations of the study, in the order they are run and reported
CONFIGS: tuple[str, ...] = ("down_down", "up_up", "down_up", "up_down", "co_rotating")
#: the three statements, in the order they are reported, with the paper's sign of each contrast
STATEMENTS: dict[str, int] = {"top_least_kickback": +1, "pass_rises_with_speed": +1, "refeed_falls_with_size": -1}
#: |z| above which a statement with the paper's sign agrees
Z_AGREE = 2.0
#: clip of the signed z in the tie-break sum (pick_default)
Z_CLIP = 5.0
STREAMS = ("kickback", "refeed", "pass_through")


def run_dir_name(size_mm: float, speed_rpm: float, seed: int) -> str:
    """Folder name of one run's export: ``<size>mm_<rpm>rpm_seed<k>``."""
    return f"{size_mm:g}mm_{speed_rpm:g}rpm_seed{seed}"


@dataclass(frozen=True)
class RunStreams:
    """The per-stage streams of one DEM run and their sampling errors.

    Attributes
    ----------
    config : str
        Rotation-sense configuration (machine name).
    size_mm, speed_rpm : float
        Rock size (mm) and upper-stage shaft speed (rpm).
    seed : int
        Feed seed.
    streams : ndarray, shape (n_stages, 3)
        ``kickback, refeed, pass_through`` per stage (mass fractions per characteristic time).
    sampling_se : ndarray, shape (n_stages, 3)
        Their sampling errors (NaN where the run reports none).
    outcome : str
        ``steady``, ``not_steady`` or ``choked``.
    wall_s : float
        Wall time of the run (s; NaN if unknown).
    """

    config: str
    size_mm: float
    speed_rpm: float
    seed: int
    streams: np.ndarray
    sampling_se: np.ndarray
    outcome: str = "steady"
    wall_s: float = math.nan

    def __post_init__(self) -> None:
        s = np.asarray(self.streams, dtype=float)
        e = np.asarray(self.sampling_se, dtype=float)
        if s.ndim != 2 or s.shape[1] != 3 or s.shape[0] < 2:
            raise MsmillInputError("streams", f"shape {s.shape}", "(n_stages >= 2, 3) kickback, refeed, pass_through")
        if e.shape != s.shape:
            raise MsmillInputError("sampling_se", f"shape {e.shape}", f"the streams' shape {s.shape}")
        if not np.all(np.isfinite(s)) or np.any(s < 0) or np.any(s > 1):
            raise MsmillInputError("streams", s.tolist(), "finite fractions in [0, 1]")
        if not self.size_mm > 0 or not self.speed_rpm > 0:
            raise MsmillInputError("size_mm / speed_rpm", (self.size_mm, self.speed_rpm), "numbers > 0")
        object.__setattr__(self, "streams", s)
        object.__setattr__(self, "sampling_se", e)

    @property
    def n_stages(self) -> int:
        """Number of stages."""
        return int(self.streams.shape[0])


def read_run(run_dir: str | Path, config: str | None = None) -> RunStreams:
    """One run's export (``statistics.json`` and ``provenance.json`` of the study driver).

    ``config`` defaults to the provenance's, else the parent folder's name.
    """
    d = Path(run_dir)
    f = d / "statistics.json"
    if not f.is_file():
        raise MsmillInputError("run_dir", str(d), "a folder holding a statistics.json")
    st = json.loads(f.read_text(encoding="utf-8"))
    prov_f = d / "provenance.json"
    prov = json.loads(prov_f.read_text(encoding="utf-8")) if prov_f.is_file() else {}
    stages = sorted(st["stages"], key=lambda s: s["stage"])
    streams = np.array([[s[k] for k in STREAMS] for s in stages], dtype=float)
    se = np.array([[s.get("sampling_error", {}).get(k, math.nan) for k in STREAMS] for s in stages], dtype=float)
    inputs = prov.get("inputs", {})
    seed = inputs.get("seed", st.get("provenance", {}).get("run_settings", {}).get("seed", 0))
    return RunStreams(config=config or prov.get("config") or d.parent.name, size_mm=float(st["design"]["size_mm"]),
                      speed_rpm=float(st["design"]["speed_rpm"]), seed=int(seed), streams=streams, sampling_se=se,
                      outcome=str(st.get("outcome") or prov.get("outcome") or "steady"),
                      wall_s=float(prov.get("wall_s", st.get("provenance", {}).get("wall_s", math.nan))))


def read_study(root: str | Path) -> list[RunStreams]:
    """Every run export under ``root/<config>/<run>/`` (folders still being written, ``*.partial``, skipped)."""
    r = Path(root)
    if not r.is_dir():
        raise MsmillInputError("root", str(r), "a folder of study exports (<config>/<run>/statistics.json)")
    return [read_run(f.parent) for f in sorted(r.glob("*/*/statistics.json")) if not f.parent.name.endswith(".partial")]


# --------------------------------------------------------------------------- groups and contrasts
#: a quantity of one run: (value, sampling error)
Quantity = Callable[[RunStreams], tuple[float, float]]


def stage_stream(stream: str, stage: int) -> Quantity:
    """The quantity ``stream`` (kickback, refeed or pass_through) of ``stage`` (1 = top)."""
    j = _stream_index(stream)

    def q(r: RunStreams) -> tuple[float, float]:
        return float(r.streams[stage - 1, j]), float(r.sampling_se[stage - 1, j])

    return q


def stage_difference(stream: str, stage: int, minus_stage: int) -> Quantity:
    """``stream`` of ``stage`` minus that of ``minus_stage`` in the same run (errors in quadrature)."""
    j = _stream_index(stream)

    def q(r: RunStreams) -> tuple[float, float]:
        a, b = stage - 1, minus_stage - 1
        return (float(r.streams[a, j] - r.streams[b, j]),
                float(math.hypot(r.sampling_se[a, j], r.sampling_se[b, j])))

    return q


def stage_mean(stream: str) -> Quantity:
    """``stream`` averaged over the stages of a run (errors in quadrature over the stages)."""
    j = _stream_index(stream)

    def q(r: RunStreams) -> tuple[float, float]:
        return float(r.streams[:, j].mean()), float(np.sqrt(np.sum(r.sampling_se[:, j] ** 2)) / r.n_stages)

    return q


def _stream_index(stream: str) -> int:
    if stream not in STREAMS:
        raise MsmillInputError("stream", stream, ", ".join(STREAMS))
    return STREAMS.index(stream)


@dataclass(frozen=True)
class GroupMean:
    """Mean of a quantity over the seeds of one (size, speed) point, and its error.

    ``se = sqrt(max(between-seed variance, mean squared sampling error) / n)``; with one seed the
    sampling error alone.
    """

    value: float
    se: float
    n: int
    between_sd: float
    sampling_rms: float


def group_mean(runs: Sequence[RunStreams], quantity: Quantity) -> GroupMean:
    """:class:`GroupMean` of ``quantity`` over ``runs`` (the seeds of one point)."""
    if not runs:
        raise MsmillInputError("runs", "none", "at least one run of the point")
    vals = np.array([quantity(r) for r in runs], dtype=float)
    x, e = vals[:, 0], vals[:, 1]
    n = x.size
    sd = float(np.std(x, ddof=1)) if n >= 2 else math.nan
    rms = float(np.sqrt(np.nanmean(e**2))) if np.any(np.isfinite(e)) else math.nan
    candidates = [v for v in (sd**2, rms**2) if math.isfinite(v)]
    var = max(candidates) if candidates else math.nan
    return GroupMean(float(x.mean()), float(math.sqrt(var / n)) if math.isfinite(var) else math.nan, n, sd, rms)


@dataclass(frozen=True)
class Contrast:
    """A linear contrast of group means: effect, error and ``z = effect / se``."""

    effect: float
    se: float
    n_runs: int

    @property
    def z(self) -> float:
        """Effect over its error (NaN without an error; +-inf for an exact nonzero effect)."""
        if not math.isfinite(self.se):
            return math.nan
        if self.se == 0:
            return math.copysign(math.inf, self.effect) if self.effect != 0 else 0.0
        return self.effect / self.se


def combine(terms: Iterable[tuple[float, GroupMean]]) -> Contrast:
    """``sum c_g m_g`` over ``(c_g, m_g)`` pairs, errors in quadrature."""
    t = list(terms)
    if not t:
        return Contrast(math.nan, math.nan, 0)
    eff = sum(c * g.value for c, g in t)
    se = math.sqrt(sum((c * g.se) ** 2 for c, g in t))
    return Contrast(float(eff), float(se), sum(g.n for _, g in t))


# --------------------------------------------------------------------------- the three statements
@dataclass
class Statement:
    """One observation tested on one configuration.

    Attributes
    ----------
    name : str
        Key in :data:`STATEMENTS`.
    decision : Contrast
        The contrast the verdict is made on.
    sign : int
        The paper's sign of that contrast.
    details : dict of str to Contrast
        Per stage, per point, pooled variants (reported, not decided on).
    note : str
        Why the statement could not be tested (empty when it was).
    """

    name: str
    decision: Contrast
    sign: int
    details: dict[str, Contrast] = field(default_factory=dict)
    note: str = ""

    @property
    def signed_z(self) -> float:
        """``z`` in the paper's direction (positive: the paper's sign)."""
        return self.sign * self.decision.z

    @property
    def agrees(self) -> bool:
        """The contrast has the paper's sign with ``|z| > Z_AGREE``."""
        return bool(self.signed_z > Z_AGREE)  # NaN (no error) compares false


def _groups(runs: Sequence[RunStreams]) -> dict[tuple[float, float], list[RunStreams]]:
    g: dict[tuple[float, float], list[RunStreams]] = {}
    for r in runs:
        g.setdefault((r.size_mm, r.speed_rpm), []).append(r)
    return g


def top_least_kickback(runs: Sequence[RunStreams]) -> Statement:
    """(a): stage-1 kickback below every other stage's, averaged over the (size, speed) points.

    Details: ``stage<s>`` (pooled over points, ``k_s - k_1``) and ``<size>mm_<rpm>rpm_stage<s>``.
    The decision is the stage with the smallest ``z``.
    """
    groups = _groups(runs)
    n = _n_stages(runs)
    details: dict[str, Contrast] = {}
    pooled = []
    for s in range(2, n + 1):
        q = stage_difference("kickback", s, 1)
        gm = {k: group_mean(v, q) for k, v in sorted(groups.items())}
        c = combine((1 / len(gm), m) for m in gm.values())
        details[f"stage{s}"] = c
        pooled.append(c)
        for (size, rpm), m in gm.items():
            details[f"{size:g}mm_{rpm:g}rpm_stage{s}"] = combine([(1.0, m)])
    worst = min(pooled, key=lambda c: c.z if math.isfinite(c.z) else math.inf)
    return Statement("top_least_kickback", worst, STATEMENTS["top_least_kickback"], details)


def pass_rises_with_speed(runs: Sequence[RunStreams]) -> Statement:
    """(b): pass-through at the highest speed minus that at the lowest, averaged over the sizes with both.

    Decided on the pass-through averaged over the stages; details ``stage<s>``, ``mean`` and
    ``<size>mm_mean``.
    """
    groups = _groups(runs)
    speeds = sorted({r.speed_rpm for r in runs})
    if len(speeds) < 2:
        raise MsmillInputError("runs", f"speeds {speeds} rpm", "runs at two shaft speeds or more")
    lo, hi = speeds[0], speeds[-1]
    sizes = sorted(s for s in {r.size_mm for r in runs} if (s, lo) in groups and (s, hi) in groups)
    if not sizes:
        raise MsmillInputError("runs", "no size at both speeds", f"some size with runs at {lo:g} and {hi:g} rpm")

    def contrast(q: Quantity, at: Sequence[float]) -> Contrast:
        terms = []
        for size in at:
            terms += [(1 / len(at), group_mean(groups[(size, hi)], q)), (-1 / len(at), group_mean(groups[(size, lo)], q))]
        return combine(terms)

    details = {f"stage{s}": contrast(stage_stream("pass_through", s), sizes) for s in range(1, _n_stages(runs) + 1)}
    decision = contrast(stage_mean("pass_through"), sizes)
    details["mean"] = decision
    for size in sizes:
        details[f"{size:g}mm_mean"] = contrast(stage_mean("pass_through"), [size])
    return Statement("pass_rises_with_speed", decision, STATEMENTS["pass_rises_with_speed"], details)


def refeed_falls_with_size(runs: Sequence[RunStreams]) -> Statement:
    """(c): slope of the stage-1 refeed against ``log2(size)`` (per doubling), averaged over the speeds.

    Least-squares slope of the group means at each speed with two sizes or more; details ``stage<s>``,
    ``mean`` (refeed averaged over the stages) and ``<rpm>rpm_stage1``.
    """
    groups = _groups(runs)
    by_speed: dict[float, list[float]] = {}
    for size, rpm in groups:
        by_speed.setdefault(rpm, []).append(size)
    speeds = sorted(rpm for rpm, sz in by_speed.items() if len(sz) >= 2)
    if not speeds:
        raise MsmillInputError("runs", "fewer than two sizes at every speed", "two rock sizes or more at some speed")

    def slope(q: Quantity, at: Sequence[float]) -> Contrast:
        terms = []
        for rpm in at:
            sizes = sorted(by_speed[rpm])
            x = np.log2(sizes)
            w = (x - x.mean()) / np.sum((x - x.mean()) ** 2)
            terms += [(float(wi) / len(at), group_mean(groups[(size, rpm)], q)) for wi, size in zip(w, sizes,
                                                                                                   strict=True)]
        return combine(terms)

    details = {f"stage{s}": slope(stage_stream("refeed", s), speeds) for s in range(1, _n_stages(runs) + 1)}
    details["mean"] = slope(stage_mean("refeed"), speeds)
    for rpm in speeds:
        details[f"{rpm:g}rpm_stage1"] = slope(stage_stream("refeed", 1), [rpm])
    return Statement("refeed_falls_with_size", details["stage1"], STATEMENTS["refeed_falls_with_size"], details)


def _n_stages(runs: Sequence[RunStreams]) -> int:
    ns = {r.n_stages for r in runs}
    if len(ns) != 1:
        raise MsmillInputError("runs", f"stage counts {sorted(ns)}", "runs of one machine (one stage count)")
    return ns.pop()


@dataclass
class ConfigVerdict:
    """The three statements on one configuration's runs."""

    config: str
    statements: dict[str, Statement]
    n_runs: int
    n_excluded: int

    @property
    def agreeing(self) -> int:
        """Number of statements that agree."""
        return sum(s.agrees for s in self.statements.values())

    @property
    def steady_share(self) -> float:
        """Share of the configuration's runs that reached steady state."""
        total = self.n_runs + self.n_excluded
        return self.n_runs / total if total else math.nan

    def rank_key(self) -> tuple[int, float, int, float]:
        """(agreeing, share of steady runs, statements with the paper's sign, sum of signed z clipped to
        +-Z_CLIP): larger is better. The steady share comes first among the tie-breaks: the paper's machine
        runs steady at its operating points, so a configuration whose runs choke there is the less likely."""
        zs = [s.signed_z for s in self.statements.values()]
        right = sum(1 for z in zs if z > 0)  # NaN compares false
        clipped = sum(float(np.clip(z, -Z_CLIP, Z_CLIP)) for z in zs if not math.isnan(z))
        return self.agreeing, round(self.steady_share, 9), right, clipped


def evaluate(runs: Sequence[RunStreams], include_not_steady: bool = False) -> dict[str, ConfigVerdict]:
    """The three statements per configuration (configurations in :data:`CONFIGS` order, then others).

    Runs whose outcome is not ``steady`` are left out unless ``include_not_steady``.
    """
    if not runs:
        raise MsmillInputError("runs", "none", "run exports of at least one configuration")
    out: dict[str, ConfigVerdict] = {}
    names = sorted({r.config for r in runs}, key=lambda c: (CONFIGS.index(c) if c in CONFIGS else len(CONFIGS), c))
    for c in names:
        all_c = [r for r in runs if r.config == c]
        use = all_c if include_not_steady else [r for r in all_c if r.outcome == "steady"]
        if not use:
            continue
        st = {}
        for name, test in (("top_least_kickback", top_least_kickback), ("pass_rises_with_speed", pass_rises_with_speed),
                           ("refeed_falls_with_size", refeed_falls_with_size)):
            try:
                st[name] = test(use)
            except MsmillInputError as exc:  # too few runs yet (one speed, one size): untested, not agreeing
                st[name] = Statement(name, Contrast(math.nan, math.nan, 0), STATEMENTS[name], note=str(exc))
        out[c] = ConfigVerdict(c, st, len(use), len(all_c) - len(use))
    return out


def pick_default(verdicts: dict[str, ConfigVerdict]) -> ConfigVerdict:
    """The configuration most consistent with the observations (largest :meth:`ConfigVerdict.rank_key`)."""
    if not verdicts:
        raise MsmillInputError("verdicts", "none", "at least one evaluated configuration")
    return max(verdicts.values(), key=lambda v: v.rank_key())


def report_lines(verdicts: dict[str, ConfigVerdict], details: bool = True) -> list[str]:
    """Text report: effect and z lines, then one key=value line per configuration, then the pick."""
    lines: list[str] = []
    if details:
        for v in verdicts.values():
            lines.append(f"# {v.config}: {v.n_runs} steady runs used, {v.n_excluded} left out (not steady)")
            for st in v.statements.values():
                d = st.decision
                if st.note:
                    lines.append(f"#   {st.name}: not testable ({st.note})")
                    continue
                lines.append(f"#   {st.name}: effect={d.effect:+.4f} se={d.se:.4f} z={d.z:+.2f} "
                             f"(paper's sign {'+' if st.sign > 0 else '-'})")
                pooled = {k: c for k, c in st.details.items() if k.startswith(("stage", "mean"))}
                points = {k: c for k, c in st.details.items() if k not in pooled}
                for label, part in (("pooled", pooled), ("per point", points)):
                    if part:
                        lines.append(f"#     {label}: " + "  ".join(f"{k} {c.effect:+.3f}+-{c.se:.3f} (z {c.z:+.1f})"
                                                                     for k, c in part.items()))
    for v in verdicts.values():
        words = " ".join(f"{k}={'agree' if s.agrees else 'disagree'}" for k, s in v.statements.items())
        lines.append(f"config={v.config} {words}")
    best = pick_default(verdicts)
    lines.append(f"default={best.config} agreeing={best.agreeing}/{len(STATEMENTS)}")
    return lines


def stream_table_lines(runs: Sequence[RunStreams]) -> list[str]:
    """Markdown table of the group means: per configuration, size and speed the seeds, kickback and
    pass-through per stage, stage-1 refeed (mass fractions, mean over seeds) and the mean wall time (s)."""
    if not runs:
        raise MsmillInputError("runs", "none", "at least one run")
    n = _n_stages(runs)
    head = (["config", "size (mm)", "speed (rpm)", "seeds"] + [f"kick {s}" for s in range(1, n + 1)]
            + [f"pass {s}" for s in range(1, n + 1)] + ["refeed 1", "wall (s)"])
    lines = ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    key = {c: i for i, c in enumerate(CONFIGS)}
    cells: dict[tuple[str, float, float], list[RunStreams]] = {}
    for r in runs:
        cells.setdefault((r.config, r.size_mm, r.speed_rpm), []).append(r)
    for (c, size, rpm), rs in sorted(cells.items(), key=lambda kv: (key.get(kv[0][0], len(CONFIGS)), kv[0])):
        m = np.mean([r.streams for r in rs], axis=0)
        wall = np.nanmean([r.wall_s for r in rs]) if any(math.isfinite(r.wall_s) for r in rs) else math.nan
        row = ([c, f"{size:g}", f"{rpm:g}", str(len(rs))] + [f"{v:.2f}" for v in m[:, 0]]
               + [f"{v:.2f}" for v in m[:, 2]] + [f"{m[0, 1]:.2f}", f"{wall:.0f}"])
        lines.append("| " + " | ".join(row) + " |")
    return lines


def leave_one_seed_out(runs: Sequence[RunStreams], include_not_steady: bool = False) -> dict[int, tuple[str, int]]:
    """How sure the pick is: ``{seed: (pick, agreeing)}`` of :func:`pick_default` on the runs without that seed.

    Only seeds whose removal leaves every configuration with runs are tried.
    """
    out: dict[int, tuple[str, int]] = {}
    configs = {r.config for r in runs}
    for seed in sorted({r.seed for r in runs}):
        rest = [r for r in runs if r.seed != seed]
        if {r.config for r in rest} != configs:
            continue
        best = pick_default(evaluate(rest, include_not_steady))
        out[seed] = (best.config, best.agreeing)
    return out


def scatter_over_error(runs: Sequence[RunStreams]) -> dict[str, tuple[float, int]]:
    """Per stream, the median over (configuration, size, speed, stage) groups of two seeds or more of the
    between-seed sd over the rms of the runs' sampling errors, and the number of groups.

    About 1 when the runs' batch-means errors describe their scatter; above 1 they understate it
    (then the between-seed term sets :func:`group_mean`'s error).
    """
    cells: dict[tuple[str, float, float], list[RunStreams]] = {}
    for r in runs:
        cells.setdefault((r.config, r.size_mm, r.speed_rpm), []).append(r)
    out: dict[str, tuple[float, int]] = {}
    for stream in STREAMS:
        ratios = []
        for rs in cells.values():
            if len(rs) < 2:
                continue
            for s in range(1, rs[0].n_stages + 1):
                g = group_mean(rs, stage_stream(stream, s))
                if math.isfinite(g.sampling_rms) and g.sampling_rms > 0:
                    ratios.append(g.between_sd / g.sampling_rms)
        out[stream] = (float(np.median(ratios)) if ratios else math.nan, len(ratios))
    return out
