"""Wall and CPU time of validation and calibration on the SYNTHETIC example experiments.

    python benchmarks/practitioner_speed.py [--repeat 3]

Times the model-layer calls behind ``msmill validate examples/experiments/``
and ``msmill calibrate examples/experiments/`` (imports excluded, reported
separately). Last line: key=value figures (medians).
"""

from __future__ import annotations

import argparse
import statistics
import time
import warnings
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--repeat", type=int, default=3)
    args = ap.parse_args()
    t0 = time.perf_counter()
    from msmill.errors import OutOfDomainWarning
    from msmill.model.experiments import read_experiments
    from msmill.model.fitting import calibrate_surveys, impact_report
    from msmill.model.validation import SurveyModel, validate

    t_import = time.perf_counter() - t0
    warnings.simplefilter("ignore", OutOfDomainWarning)
    es = read_experiments(ROOT / "examples" / "experiments")
    val, cal, imp = [], [], []
    for _ in range(args.repeat):
        w, c = time.perf_counter(), time.process_time()
        validate(es)
        val.append((time.perf_counter() - w, time.process_time() - c))
        w, c = time.perf_counter(), time.process_time()
        for ore in es.ores():
            calibrate_surveys(SurveyModel(ore, [e for e in es.surveys if e.ore == ore]))
        cal.append((time.perf_counter() - w, time.process_time() - c))
        w, c = time.perf_counter(), time.process_time()
        for ore in es.ores("single_impact"):
            impact_report([t for t in es.impact_tests if t.ore == ore], ore)  # what msmill calibrate runs
        imp.append((time.perf_counter() - w, time.process_time() - c))
    med = {k: (statistics.median(a for a, _ in v), statistics.median(b for _, b in v))
           for k, v in (("validate", val), ("calibrate_surveys", cal), ("impact_tests", imp))}
    print(f"{len(es.surveys)} surveys, {len(es.impact_tests)} single-impact tests; imports {t_import:.2f} s")
    for k, (w, c) in med.items():
        print(f"{k}: wall {w:.2f} s, cpu {c:.2f} s (median of {args.repeat})")
    print(" ".join(f"{k}_wall_s={w:.2f} {k}_cpu_s={c:.2f}" for k, (w, c) in med.items()))


if __name__ == "__main__":
    main()
