"""Mutation check: plant plausible physics bugs one at a time and see which the tests miss.

Run on demand (not in CI; CPU-heavy: about 25 min of one core, 60-70 min wall on a
loaded shared machine)::

    nice -n 5 python scripts/mutation_check.py               # every mutant
    nice -n 5 python scripts/mutation_check.py --only dem    # names containing "dem"
    python scripts/mutation_check.py --list                  # the list, no runs

Each mutant is ``(name, file, original snippet, mutated snippet, tests)``: the
script copies ``src/``, ``tests/``, ``examples/``, ``scripts/`` and ``pyproject.toml`` of the checkout it
lives in (including uncommitted edits) into a scratch directory, checks that
the unmutated tests pass there (the baseline), then for every mutant replaces
the snippet (which must occur exactly once: a stale definition is reported, not
skipped silently), runs the mutant's test subset with ``PYTHONPATH`` pointing at
the scratch ``src`` and restores the file. A mutant is *killed* when pytest
reports failing tests (exit code 1), *survived* when the subset passes, and an
*error* for any other outcome (collection error, stale snippet, time-out of the
whole subset). Mutants of numba-compiled files get their own ``NUMBA_CACHE_DIR``
so they never overwrite the compiled unmutated kernels. The per-test limits of
``tests/conftest.py`` are multiplied by ``--timeout-scale`` (default 5, through
``MSMILL_TIMEOUT_SCALE``): on a loaded machine a 10 s test can take 90 s of wall
time, and a time-out would otherwise count as a kill, or fail the baseline.
Property tests run under the hypothesis profile ``mutation`` of
``tests/conftest.py`` (no shrinking of counterexamples: minutes per failing
property test otherwise).

The last line is ``key=value`` (``killed=.. survived=.. errors=..``); the exit
status is 0 only if every mutant was killed. When a snippet changes in the
code, update the mutant's ``original`` (and ``mutated``) here.
"""

from __future__ import annotations

import argparse
import os
import re
import shutil
import subprocess
import sys
import tempfile
import time
from dataclasses import dataclass
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
NUMBA_FILES = ("src/msmill/dem/kernels.py", "src/msmill/dem/contact.py")

# test subsets (paths relative to the checkout)
BREAKAGE = ["tests/test_breakage.py", "tests/test_damage.py", "tests/model/test_damage_submodels.py"]
MODEL = ["tests/model/test_physics.py", "tests/model/test_mass_balance.py",
         "tests/model/test_poisson_series.py", "tests/model/test_damage_submodels.py",
         "tests/model/test_velocity_quadrature.py", "tests/model/test_count_solvers.py",
         "tests/model/test_montecarlo_counts.py"]
PSD = ["tests/test_psd.py", "tests/test_distributions.py", "tests/test_count_families.py"]
STATS = ["tests/dem/test_mill_stats.py"]
CONTACT = ["tests/dem/test_chung_ooi.py", "tests/dem/test_contact_torques.py"]
TN_CAP_CLI = ["tests/test_cli_core.py::test_breakage_table_caps_tn_at_100"]


@dataclass(frozen=True)
class Mutant:
    """One planted bug: replace ``original`` by ``mutated`` in ``file``, run ``tests``."""

    name: str
    file: str
    original: str
    mutated: str
    tests: tuple[str, ...]


def m(name: str, file: str, original: str, mutated: str, tests: list[str]) -> Mutant:
    return Mutant(name, file, original, mutated, tuple(dict.fromkeys(tests)))


BK = "src/msmill/breakage.py"
SUB = "src/msmill/model/submodels.py"
EV = "src/msmill/model/expected_value.py"
MC = "src/msmill/model/montecarlo.py"
ST = "src/msmill/dem/mill/stats.py"
KE = "src/msmill/dem/kernels.py"

MUTANTS: list[Mutant] = [
    # ---- the two bugs that escaped the suite before issue 19
    m("model-damage-returns-increment", SUB,
      "return np.minimum(1.0 - (1.0 - d) * (1.0 - dd), np.nextafter(1.0, 0.0))",
      "return np.minimum(dd, np.nextafter(1.0, 0.0))", [*MODEL, "tests/test_damage.py"]),
    m("dem-slip-factor-linear", KE,
      "fe = mu * fn * (1.0 - zeta * np.sqrt(zeta)) / smag",
      "fe = mu * fn * (1.0 - zeta) / smag", CONTACT),
    # ---- breakage law, t_n family, appearance, damage
    m("breakage-eq11-drops-damage", BK,
      "x = bb * e * size / (lref * (1.0 - d))", "x = bb * e * size / lref", BREAKAGE + MODEL),
    m("breakage-t10-squared", BK, "return _ret(a * p)", "return _ret(a * p * p)",
      [*BREAKAGE, "tests/test_cli_core.py::test_breakage_table"]),
    m("breakage-tn-cap-dropped", BK,
      "return _ret(np.minimum(kk * t**ss, 100.0))", "return _ret(kk * t**ss)", BREAKAGE),
    m("breakage-tnconstants-cap-dropped", BK,
      "return np.minimum(np.asarray(self.k) * t ** np.asarray(self.s), 100.0)",
      "return np.asarray(self.k) * t ** np.asarray(self.s)", BREAKAGE + TN_CAP_CLI),
    m("appearance-tail-slope-wrong-segment", BK,
      "tail_slope = np.maximum((y[..., 1] - y[..., 0]) / h[0], 0.0)",
      "tail_slope = np.maximum((y[..., 1] - y[..., 0]) / h[1], 0.0)", BREAKAGE),
    m("appearance-hermite-slope-swapped", BK,
      "+ (t3 - t2) * hk * d1", "+ (t3 - t2) * hk * d0", BREAKAGE),
    m("damage-exponent-halved", BK,
      "** (2.0 * g / 5.0)\n", "** (g / 5.0)\n", BREAKAGE),
    m("survivor-ratio-without-survivor-energy", BK,
      "    r = e / (e + em)\n", "    r = e / (e + 2.0 * em)\n", BREAKAGE),
    m("mean-fracture-energy-drops-damage", BK,
      "return _ret(lref * (1.0 - d) / (bb * size))", "return _ret(lref / (bb * size))", BREAKAGE),
    m("accumulate-damage-adds", BK,
      "return _ret(1.0 - (1.0 - a) * (1.0 - b))", "return _ret(np.minimum(a + b, 1.0))", BREAKAGE),
    m("specific-energy-drops-half", SUB,
      "return 0.5 * v * v * KWH_T_PER_J_KG", "return v * v * KWH_T_PER_J_KG", MODEL),
    # ---- PSD and KL utilities
    m("psd-passing-linear-interpolation", "src/msmill/psd.py",
      "out = np.interp(np.log(s), logx, p, left=0.0, right=100.0)",
      "out = np.interp(s, np.exp(logx), p, left=0.0, right=100.0)", PSD),
    m("psd-rebin-reads-lower-edges", "src/msmill/psd.py",
      "cum = np.interp(np.log(grid.edges_mm[1:]), logx, p, left=0.0, right=100.0)",
      "cum = np.interp(np.log(grid.edges_mm[:-1]), logx, p, left=0.0, right=100.0)", PSD),
    m("psd-ks-mean-not-max", "src/msmill/psd.py",
      "return float(np.clip(d.max() / 100.0, 0.0, 1.0))",
      "return float(np.clip(d.mean() / 100.0, 0.0, 1.0))", PSD),
    m("kl-divergence-reversed-log", "src/msmill/distributions.py",
      "np.log(p[m] / np.maximum(q[m], 1e-300))", "np.log(np.maximum(q[m], 1e-300) / p[m])", PSD),
    m("poisson-fit-median", "src/msmill/distributions.py",
      "        lam = self.mean_count_\n", "        lam = float(np.median(self.support_))\n", PSD + STATS),
    # ---- expected-value solver
    m("ev-poisson-exponent-drops-identity", EV,
      "Z[:, :nd, :nd] = lam_ic * (survive[i] - np.eye(nd)[None])",
      "Z[:, :nd, :nd] = lam_ic * survive[i]", MODEL),
    m("ev-poisson-phi-drops-lambda", EV,
      "full[1, active] = wic * lam_ic * X[:, nd:, :nd]", "full[1, active] = wic * X[:, nd:, :nd]", MODEL),
    m("ev-count-series-phi-uses-pmf", EV,
      "phi[:r] += q[:r, j, None, None] * power[:r]", "phi[:r] += p[:r, j, None, None] * power[:r]", MODEL),
    m("ev-band-sweep-refeed-ignores-staying-fraction", EV,
      'u = x[:, 1:, i] * (stay[:, :, i, None] if impacted == "refeed" else 1.0)', "u = x[:, 1:, i]",
      ["tests/model/test_batched_solver.py"]),
    m("ev-batched-survivor-upper-class-dropped", EV,
      "(row + np.minimum(lo + 1, nd - 1))", "(row + lo)", ["tests/model/test_batched_solver.py"]),
    m("ev-quadrature-drops-sqrt2", EV,
      "v = mix.means_m_s[..., None] + np.sqrt(2.0) * mix.sigmas_m_s[..., None] * x",
      "v = mix.means_m_s[..., None] + mix.sigmas_m_s[..., None] * x", MODEL),
    m("ev-damage-split-rounds-down", EV,
      "    frac = pos - lo\n", "    frac = 0.0 * (pos - lo)\n", MODEL),
    m("ev-threshold-ignored", EV,
      "broke_thr = d_new >= th", "broke_thr = d_new > 1.0", MODEL),
    # ---- Monte Carlo solver
    m("mc-one-extra-secondary", MC, "sel = k > j", "sel = k >= j", MODEL),
    m("mc-threshold-ignored", MC, "broke |= d_new >= th", "broke |= d_new > 1.0", MODEL),
    # ---- DEM statistics
    m("stats-characteristic-time-doubled", ST,
      "    tau = machine.stage_spacing_m / speed\n", "    tau = 2.0 * machine.stage_spacing_m / speed\n",
      STATS),
    m("stats-slow-secondaries-counted", ST,
      "(vn >= s_.min_secondary_speed_m_s)", "(vn > 0.0)", STATS),
    m("stats-hit-window-too-long", ST,
      'nxt["hit"] = nxt["t_hit"] <= nxt["t_to"] + 1e-12',
      'nxt["hit"] = nxt["t_hit"] <= nxt["t_to"] + 0.011', STATS),
    m("stats-kickback-passthrough-swapped", ST,
      '[m["stage_to"] < m["stage_from"], m["stage_to"] == m["stage_from"]], [0, 1], default=2)',
      '[m["stage_to"] > m["stage_from"], m["stage_to"] == m["stage_from"]], [0, 1], default=2)', STATS),
    m("stats-region-of-lower-edge", ST,
      'region=np.clip(np.searchsorted(edges_y, snaps["y_m"].to_numpy(), side="right") - 1,',
      'region=np.clip(np.searchsorted(edges_y, snaps["y_m"].to_numpy(), side="right"),', STATS),
    m("stats-region-weights-by-area", ST,
      'vol=4.0 / 3.0 * np.pi * snaps["radius_m"].to_numpy() ** 3)',
      'vol=4.0 / 3.0 * np.pi * snaps["radius_m"].to_numpy() ** 2)', STATS),
    # ---- DEM contact laws
    m("dem-hertz-linear", KE, "fel = kh * s * sq", "fel = kh * s", CONTACT),
    m("dem-damping-overlap-exponent", KE, "cn = ch * np.sqrt(sq)", "cn = ch * sq", CONTACT),
    m("dem-mindlin-ratio-halved", "src/msmill/dem/contact.py",
      "tab[a, b, P_STRATIO] = estar / (4.0 * gstar)", "tab[a, b, P_STRATIO] = estar / (2.0 * gstar)",
      CONTACT),
    m("dem-no-tangential-damping", KE,
      "cd = etat * np.sqrt(6.0 * mu * mstar * fn / stmax) * np.sqrt(np.sqrt(zeta))",
      "cd = 0.0 * etat * np.sqrt(6.0 * mu * mstar * fn / stmax)", CONTACT),
    m("dem-pair-torque-sign", KE, "            tx += la * cx_\n            ty += la * cy_\n",
      "            tx -= la * cx_\n            ty -= la * cy_\n", CONTACT),
    m("dem-wall-lever-full-radius", KE, "            li = ri - s\n", "            li = ri + s\n", CONTACT),
]


def _copy_checkout(dst: Path) -> None:
    for part in ("src", "tests", "examples", "scripts"):  # tests read the examples and some scripts
        shutil.copytree(ROOT / part, dst / part, ignore=shutil.ignore_patterns(
            "__pycache__", "*.nbi", "*.nbc", ".hypothesis", ".pytest_cache"))
    shutil.copy2(ROOT / "pyproject.toml", dst / "pyproject.toml")


def _run_pytest(work: Path, tests: tuple[str, ...], cache_dir: Path, timeout_s: float,
                timeout_scale: float) -> tuple[int, str, float]:
    env = dict(os.environ, PYTHONPATH=str(work / "src"), NUMBA_CACHE_DIR=str(cache_dir),
               NUMBA_NUM_THREADS="1", OMP_NUM_THREADS="1", PYTHONDONTWRITEBYTECODE="1",
               MSMILL_TIMEOUT_SCALE=str(timeout_scale))
    cmd = [sys.executable, "-m", "pytest", "-q", "-rf", "-p", "no:cacheprovider", "-o", "addopts=",
           "--hypothesis-profile=mutation", *tests]
    t0 = time.perf_counter()
    try:
        proc = subprocess.run(cmd, cwd=work, env=env, capture_output=True, text=True, timeout=timeout_s)
    except subprocess.TimeoutExpired:
        return -1, "subset timed out", time.perf_counter() - t0
    lines = proc.stdout.strip().splitlines() or [""]
    if proc.returncode != 0:
        for line in lines:
            if line.startswith(("FAILED", "ERROR")):
                print(f"    {line[:160]}", flush=True)
    return proc.returncode, lines[-1], time.perf_counter() - t0


def _n_failed(summary: str) -> int:
    hit = re.search(r"(\d+) failed", summary)
    return int(hit.group(1)) if hit else 0


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--only", default="", help="run the mutants whose name contains this text")
    ap.add_argument("--list", action="store_true", help="list the mutants and exit")
    ap.add_argument("--timeout", type=float, default=1800.0,
                    help="limit per mutant's test subset (s); a broken operator can make the solver-agreement "
                         "tests march to max_steps (17 min for ev-count-series-phi-uses-pmf under load)")
    ap.add_argument("--baseline-timeout", type=float, default=2700.0,
                    help="limit of the baseline run of every subset used (s)")
    ap.add_argument("--timeout-scale", type=float, default=5.0,
                    help="factor on the per-test limits of tests/conftest.py (MSMILL_TIMEOUT_SCALE): "
                         "a test timing out on a loaded machine must not count as a kill")
    ap.add_argument("--keep", action="store_true", help="keep the scratch directory")
    args = ap.parse_args(argv)
    mutants = [x for x in MUTANTS if args.only in x.name]
    if args.list:
        for x in mutants:
            print(f"{x.name:42s} {x.file:38s} {' '.join(x.tests)}")
        return 0
    scratch = Path(tempfile.mkdtemp(prefix="msmill-mutants-"))
    work = scratch / "checkout"
    _copy_checkout(work)
    shared_cache = scratch / "numba-cache"
    print(f"scratch copy: {work}")
    # baseline: every subset used must pass unmutated
    subsets = sorted({t for x in mutants for t in x.tests})
    rc, tail, secs = _run_pytest(work, tuple(subsets), shared_cache, args.baseline_timeout, args.timeout_scale)
    print(f"baseline: rc={rc} ({secs:.0f} s) {tail}")
    if rc != 0:
        print("baseline fails: fix the tests first")
        if not args.keep:
            shutil.rmtree(scratch, ignore_errors=True)
        return 2
    rows = []
    for x in mutants:
        path = work / x.file
        text = path.read_text()
        n = text.count(x.original)
        if n != 1:
            rows.append((x, "error", f"snippet found {n} times (stale definition)", 0, 0.0))
            continue
        stat = path.stat()
        cache = scratch / f"numba-{x.name}" if x.file in NUMBA_FILES else shared_cache
        try:
            path.write_text(text.replace(x.original, x.mutated))
            rc, tail, secs = _run_pytest(work, x.tests, cache, args.timeout, args.timeout_scale)
        finally:
            path.write_text(text)
            os.utime(path, ns=(stat.st_atime_ns, stat.st_mtime_ns))  # keep the shared cache valid
            if cache != shared_cache:
                shutil.rmtree(cache, ignore_errors=True)
        status = {0: "SURVIVED", 1: "killed"}.get(rc, "error")
        rows.append((x, status, tail, _n_failed(tail), secs))
        print(f"{x.name:42s} {status:8s} failed={_n_failed(tail):3d} {secs:6.0f} s  {tail}", flush=True)
    print()
    print("| mutant | file | result | failing tests | time (s) |")
    print("|---|---|---|---|---|")
    for x, status, _tail, nf, secs in rows:
        print(f"| {x.name} | {x.file.removeprefix('src/msmill/')} | {status} | {nf} | {secs:.0f} |")
    killed = sum(r[1] == "killed" for r in rows)
    survived = sum(r[1] == "SURVIVED" for r in rows)
    errors = sum(r[1] == "error" for r in rows)
    for x, status, tail, _nf, _s in rows:
        if status != "killed":
            print(f"{status}: {x.name}: {tail}")
    if not args.keep:
        shutil.rmtree(scratch, ignore_errors=True)
    print(f"mutants={len(rows)} killed={killed} survived={survived} errors={errors}")
    return 0 if killed == len(rows) else 1


if __name__ == "__main__":
    sys.exit(main())
