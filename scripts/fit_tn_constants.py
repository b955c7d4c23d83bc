"""Fit the power law ``t_n = k t10**s`` (paper Eq. 12) to public t10-tn tables.

Input: tables A and B of the project's domain notes (section 3), JK drop-weight
convention (% passing parent/n against t10), copied below verbatim.
Method: for each table and each n in (2, 4, 25, 50, 75), least squares on
``ln t_n = ln k + s ln t10`` (``scipy.optimize.least_squares``): a power law with
multiplicative scatter, which weights the small fines values (t25-t75) as much
as t2. For comparison the script also fits in linear space (residuals in %,
``scipy.optimize.curve_fit``) and stores that as ``t{n}_linear``. Output: ``src/msmill/data/tn_constants.toml`` with the
fitted constants, their R^2, the input table and provenance (command, msmill
and scipy versions, UTC date). Also prints the comparison with the fits listed
in the domain notes.

Usage::

    python scripts/fit_tn_constants.py [--out src/msmill/data/tn_constants.toml]
"""

from __future__ import annotations

import argparse
import datetime as dt
import sys
from pathlib import Path

import numpy as np
import scipy
import tomli_w
from scipy.optimize import curve_fit, least_squares

import msmill

NS = (2, 4, 25, 50, 75)

# domain-notes section 3: t10, t2, t4, t25, t50, t75 (all %)
TABLES = {
    "A": [
        (10.0, 50.53, 23.33, 4.975, 3.064, 2.325),
        (30.0, 92.49, 61.58, 15.62, 9.412, 6.893),
        (50.0, 96.47, 82.86, 25.88, 14.71, 10.32),
    ],
    "B": [
        (10.0, 55.9, 27.9, 4.7, 2.7, 2.0),
        (20.0, 81.4, 49.3, 10.5, 6.7, 5.2),
        (30.0, 98.5, 65.6, 16.4, 10.7, 8.3),
    ],
}

# fits listed in the domain notes, for comparison only: n -> (k, s)
NOTES_FITS = {
    "A": {2: (19.6, 0.425), 4: (3.75, 0.803), 25: (0.469, 1.027), 50: (0.323, 0.982), 75: (0.273, 0.936)},
    "B": {2: (17.0, 0.519), 4: (4.63, 0.783), 25: (0.342, 1.140), 50: (0.150, 1.260), 75: (0.101, 1.304)},
}


def _power(t10: np.ndarray, k: float, s: float) -> np.ndarray:
    return k * t10**s


def _r2(y: np.ndarray, pred: np.ndarray) -> float:
    return 1.0 - float(np.sum((y - pred) ** 2)) / float(np.sum((y - y.mean()) ** 2))


def fit_table(rows: list[tuple[float, ...]]) -> dict[int, dict[str, float]]:
    """Log-space and linear-space least-squares ``(k, s)`` for each n of one table.

    ``r_squared`` is computed on ``ln t_n`` for the log fit and on ``t_n`` (%)
    for the linear fit.
    """
    arr = np.asarray(rows, dtype=float)
    t10 = arr[:, 0]
    lt10 = np.log(t10)
    out: dict[int, dict[str, float]] = {}
    for col, n in enumerate(NS, start=1):
        y = arr[:, col]
        ly = np.log(y)
        sol = least_squares(lambda th, ly=ly: th[0] + th[1] * lt10 - ly, x0=[0.0, 1.0])
        lk, s = sol.x
        (k_lin, s_lin), _ = curve_fit(_power, t10, y, p0=(np.exp(lk), s), maxfev=20000)
        out[n] = {
            "k": float(np.exp(lk)),
            "s": float(s),
            "r_squared": _r2(ly, lk + s * lt10),
            "k_linear": float(k_lin),
            "s_linear": float(s_lin),
            "r_squared_linear": _r2(y, _power(t10, k_lin, s_lin)),
        }
    return out


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", type=Path, default=Path("src/msmill/data/tn_constants.toml"))
    args = parser.parse_args(argv)

    doc: dict = {
        "provenance": {
            "command": "python scripts/fit_tn_constants.py" + (" " + " ".join(argv) if argv else ""),
            "msmill_version": msmill.__version__,
            "scipy_version": scipy.__version__,
            "date": dt.datetime.now(dt.UTC).strftime("%Y-%m-%dT%H:%M:%SZ"),
            "method": "scipy.optimize.least_squares on ln t_n = ln k + s ln t10, one fit per n "
            "(t{n}); t{n}_linear: scipy.optimize.curve_fit on t_n in % (comparison only)",
            "input": "domain notes section 3, public t10-tn tables A and B (JK drop-weight "
            "convention: % passing parent/n against t10)",
            "default_table": "A",
        },
        "tables": {},
    }
    print(f"{'table':>5} {'n':>3} {'k':>9} {'s':>7} {'R2(ln)':>7}   notes (k, s)")
    for name, rows in TABLES.items():
        fits = fit_table(rows)
        entry: dict = {
            "source": f"least-squares fit to t10-tn table {name} of the msmill domain notes",
            "input_t10_t2_t4_t25_t50_t75": [list(r) for r in rows],
        }
        for n in NS:
            f = fits[n]
            entry[f"t{n}"] = [round(f["k"], 6), round(f["s"], 6)]
            entry[f"t{n}_r_squared_log"] = round(f["r_squared"], 6)
            entry[f"t{n}_linear"] = [round(f["k_linear"], 6), round(f["s_linear"], 6)]
            nk, ns = NOTES_FITS[name][n]
            print(
                f"{name:>5} {n:>3} {f['k']:9.4g} {f['s']:7.4f} {f['r_squared']:7.4f}   "
                f"({nk}, {ns})   linear: ({f['k_linear']:.4g}, {f['s_linear']:.4f})"
            )
        doc["tables"][name] = entry
    args.out.parent.mkdir(parents=True, exist_ok=True)
    header = (
        "# Generated by scripts/fit_tn_constants.py: do not edit by hand.\n"
        "# t_n = k * t10**s (paper Eq. 12), entries [k, s] for n = 2, 4, 25, 50, 75.\n"
    )
    args.out.write_text(header + tomli_w.dumps(doc), encoding="utf-8")
    print(f"wrote {args.out}")
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
