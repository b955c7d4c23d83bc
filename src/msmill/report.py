"""``msmill report RUN.toml``: one self-contained HTML file describing a prediction.

Contents: the run file (inputs), headline figures (P80, reduction ratio,
time to steady state, power), the product PSD (with its uncertainty band when
the result carries one), the approach to steady state (paper Fig. 14), the
per-stage breakdown (hold-up, impacts, impact energy, flinger wear indicator,
power), warnings, notes and provenance. Plots are PNGs embedded as base64
``data:`` URIs, so the file needs nothing else (no network, no scripts).
"""

from __future__ import annotations

import base64
import hashlib
import html
import platform
import warnings
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

__all__ = ["build_report", "write_report"]

_CSS = """
body{font-family:system-ui,Segoe UI,Helvetica,Arial,sans-serif;margin:2em auto;max-width:1000px;color:#222}
h1{font-size:1.6em}h2{font-size:1.2em;border-bottom:1px solid #ccc;padding-bottom:.2em;margin-top:1.6em}
table{border-collapse:collapse;margin:.5em 0}td,th{border:1px solid #ccc;padding:.25em .6em;text-align:right}
th{background:#f3f3f3}td.l,th.l{text-align:left}pre{background:#f7f7f7;padding:.8em;overflow-x:auto}
img{max-width:100%;height:auto;display:block;margin:.5em 0}.warn{color:#8a4b00}.small{font-size:.85em;color:#555}
.scroll{overflow-x:auto;max-width:100%}
"""


def _img(png: bytes, alt: str) -> str:
    return f'<img alt="{html.escape(alt)}" src="data:image/png;base64,{base64.b64encode(png).decode()}">'


def _table(rows: list[tuple[str, str]]) -> str:
    body = "".join(f'<tr><td class="l">{html.escape(k)}</td><td>{html.escape(v)}</td></tr>' for k, v in rows)
    return f"<table>{body}</table>"


def _frame(df: Any) -> str:
    """An HTML table of ``df`` (labelled columns; figures by :func:`display_number`), scrolling if wider than the page."""
    from msmill.model.result import display_number

    head = "".join(f"<th>{html.escape(str(c))}</th>" for c in df.columns)
    rows = ["<tr>" + "".join(f"<td>{html.escape(display_number(v) if isinstance(v, float) else str(v))}</td>"
                             for v in r) + "</tr>" for r in df.itertuples(index=False)]
    return f"<div class='scroll'><table><tr>{head}</tr>{''.join(rows)}</table></div>"


def _git_commit() -> str:
    from msmill.provenance import git_commit

    return git_commit(short=True) or "unknown"


def _stage_figure(result: Any, power: Any) -> Any:
    from msmill.plots.model import _figure

    fig = _figure()
    ax = fig.add_subplot()
    st = result.stages
    x = st["stage"].to_numpy()
    ax.bar(x - 0.2, st["impact_energy_kwh_t"], width=0.4, label="impact energy (kWh/t of feed)")
    ax.bar(x + 0.2, st["flinger_energy_j_per_t"] / 3.6e6, width=0.4,
           label="flinger impact energy (kWh/t of feed): wear indicator")
    ax.set_xlabel("stage (1 = top)")
    ax.set_ylabel("kWh per tonne of feed")
    ax.set_xticks(x)
    ax2 = ax.twinx()
    ax2.plot(x, st["holdup_t"] * 1000.0, "o-", color="tab:green", label="hold-up (kg)")
    ax2.set_ylabel("hold-up (kg)")
    ax2.set_ylim(bottom=0)
    h1, l1 = ax.get_legend_handles_labels()
    h2, l2 = ax2.get_legend_handles_labels()
    ax.legend(h1 + h2, l1 + l2, loc="upper right", fontsize=8)
    ax.set_title(f"per stage (power: {power.total_kw:.3g} kW)")
    return fig


def _psd_band(result: Any) -> Any:
    """``(sizes_mm, low_pct, high_pct)`` from an uncertainty band on the result, if it has one."""
    band = getattr(result, "psd_band", None)
    if band is None:
        return None
    try:
        return (band["size_mm"].to_numpy(), band["low_pct"].to_numpy(), band["high_pct"].to_numpy())
    except (KeyError, AttributeError, TypeError):
        return None


def build_report(run_file: str | Path, no_load_kw: float = 0.0) -> str:
    """Run the prediction of ``run_file`` and return the report as one HTML string.

    Parameters
    ----------
    run_file : path
        A run file (``msmill.model.runfile``).
    no_load_kw : float
        Stated no-load power (kW) for the power estimate (0: not modelled).
    """
    from msmill import __version__
    from msmill.model.power import power_estimate
    from msmill.model.result import stage_display
    from msmill.model.runfile import RunFile
    from msmill.plots.model import plot_psds, plot_timeseries, png_bytes
    from msmill.plots.validation import overlay

    path = Path(run_file)
    rf = RunFile.from_toml(path)
    text = path.read_text(encoding="utf-8")
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        mill, feed, op = rf.build()
        result = mill.run(feed, op)
    power = power_estimate(result, no_load_kw=no_load_kw)
    from msmill.plots.model import _figure

    band = _psd_band(result)
    if band is not None:
        psd_fig = overlay(result.product_psd, result.product_psd, "product PSD with uncertainty band",
                          feed=result.feed_psd, band=band)
    else:
        psd_fig = _figure()
        plot_psds(result, ax=psd_fig.add_subplot())
    ts_fig = _figure()
    plot_timeseries(result, ax=ts_fig.add_subplot())
    headline = [("feed rate (t/h)", f"{result.feed_tph:g}"), ("F80 (mm)", f"{result.f80_mm:.4g}"),
                ("P80 (mm)", f"{result.p80_mm:.4g}"), ("P50 (mm)", f"{result.p50_mm:.4g}"),
                ("reduction ratio F80/P80", f"{result.reduction_ratio:.3g}"),
                ("time to steady state (s)", f"{result.time_to_steady_state_s:.3g}"),
                ("mass held in the mill (kg)", f"{1000 * result.stages['holdup_t'].sum():.3g}"),
                ("impact energy (kWh/t)", f"{result.specific_impact_energy_kwh_t:.3g}"),
                ("impact power (kW)", f"{power.impact_kw:.3g}"),
                ("no-load power, stated (kW)", f"{power.no_load_kw:.3g}"),
                ("total power (kW)", f"{power.total_kw:.3g}"),
                ("mass-balance error", f"{result.mass_balance_error:.1e}")]
    p80_band = getattr(result, "p80_band_mm", None)
    if p80_band is not None:
        headline.insert(3, ("P80 band (mm)", f"{float(p80_band[0]):.4g} - {float(p80_band[1]):.4g}"))
    stages = result.stages.merge(power.stages[["stage", "impact_kw", "flinger_kw"]], on="stage")
    warn = sorted({f"{w.category.__name__}: {w.message}" for w in caught})
    prov = [("msmill version", __version__), ("git commit", _git_commit()),
            ("generated (UTC)", datetime.now(UTC).strftime("%Y-%m-%d %H:%M:%S")),
            ("run file", str(path.resolve())), ("run file sha256", hashlib.sha256(text.encode()).hexdigest()[:16]),
            ("solver", result.solver), ("sub-models", ", ".join(f"{k}={v}" for k, v in result.submodels.items())),
            ("python", platform.python_version())]
    parts = [
        "<!DOCTYPE html><html lang='en'><head><meta charset='utf-8'>",
        f"<title>msmill report: {html.escape(rf.title or rf.name)}</title><style>{_CSS}</style></head><body>",
        f"<h1>msmill report: {html.escape(rf.title or rf.name)}</h1>",
        "<h2>Headline</h2>", _table(headline),
        "<h2>Product size distribution</h2>", _img(png_bytes(psd_fig), "product PSD"),
        _frame(result.psd_table[["upper_mm", "feed_passing_pct", "product_passing_pct"]].set_axis(
            ["size (mm)", "feed passing (%)", "product passing (%)"], axis=1)),
        "<h2>Approach to steady state (paper Fig. 14)</h2>", _img(png_bytes(ts_fig), "time series"),
        "<h2>Per stage</h2>", _img(png_bytes(_stage_figure(result, power)), "per-stage breakdown"),
        _frame(stage_display(stages)),
        "<h2>Power and wear: assumptions</h2><ul>",
        *[f"<li>{html.escape(a)}</li>" for a in power.assumptions], "</ul>",
        "<h2>Warnings</h2>",
        ("<ul>" + "".join(f'<li class="warn">{html.escape(w)}</li>' for w in warn) + "</ul>") if warn
        else "<p>none</p>",
        "<h2>Notes</h2><ul>", *[f"<li>{html.escape(n)}</li>" for n in result.notes], "</ul>",
        "<h2>Inputs (run file)</h2>", f"<pre>{html.escape(text)}</pre>",
        "<h2>Provenance</h2>", _table(prov),
        "<p class='small'>Generated by msmill; plots embedded, no external resources.</p></body></html>",
    ]
    return "\n".join(parts)


def write_report(run_file: str | Path, out: str | Path, no_load_kw: float = 0.0) -> Path:
    """Build the report and write it to ``out`` (temp file, then rename)."""
    doc = build_report(run_file, no_load_kw=no_load_kw)
    p = Path(out)
    p.parent.mkdir(parents=True, exist_ok=True)
    tmp = p.with_name(f".{p.name}.tmp")
    tmp.write_text(doc, encoding="utf-8")
    tmp.replace(p)
    return p
