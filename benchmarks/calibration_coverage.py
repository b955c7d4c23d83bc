"""Are calibration standard errors honest? z-scores of L_ref over noise seeds (SYNTHETIC surveys).

    python benchmarks/calibration_coverage.py [--seeds 10] [--objective ssq]

Makes the UG2 surveys of the example design (``msmill.model.synthetic.EXAMPLE_POINTS``, those of
``scripts/make_example_experiments.py``: 5 operating points, 9 surveys, true ``L_ref`` = 20 mm) with noise sigma = 0.05
on the retained masses for each seed, calibrates ``L_ref`` and reports
``z = (L_fit - 20) / s.e.`` for the jackknife and the Jacobian s.e.
An honest s.e. gives mean(z) ~ 0 and sd(z) ~ 1. Last line: key=value.
"""

from __future__ import annotations

import argparse
import warnings

import numpy as np


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--seeds", type=int, default=10)
    ap.add_argument("--objective", default="ssq")
    args = ap.parse_args()
    from msmill.errors import OutOfDomainWarning
    from msmill.model.fitting import calibrate_surveys
    from msmill.model.synthetic import EXAMPLE_FEEDS, EXAMPLE_POINTS, EXAMPLE_SIGMA, model_surveys
    from msmill.model.validation import SurveyModel

    warnings.simplefilter("ignore", OutOfDomainWarning)
    specs = [(f"p{j}-{fk}", EXAMPLE_FEEDS[fk], tph, {"speed_rpm": rpm, "gate_deg": gate})
             for j, (tph, rpm, gate, feeds) in enumerate(EXAMPLE_POINTS["UG2"]) for fk in feeds]
    zj, zc = [], []
    for seed in range(args.seeds):
        sv = model_surveys("UG2", specs, {"l_ref_mm": 20.0}, EXAMPLE_SIGMA, np.random.default_rng(1000 + seed))
        cal = calibrate_surveys(SurveyModel("UG2", sv), objective=args.objective)
        L = cal.params["l_ref_mm"]
        zj.append((L - 20.0) / cal.std_errors["l_ref_mm"])
        zc.append((L - 20.0) / cal.jacobian_std_errors["l_ref_mm"])
        print(f"seed {seed}: L_ref {L:.3f} mm, jackknife s.e. {cal.std_errors['l_ref_mm']:.3f}, "
              f"Jacobian s.e. {cal.jacobian_std_errors['l_ref_mm']:.3f}")
    zj, zc = np.array(zj), np.array(zc)
    print(f"z (jackknife): mean {zj.mean():.2f}, sd {zj.std(ddof=1):.2f}; "
          f"z (Jacobian): mean {np.nanmean(zc):.2f}, sd {np.nanstd(zc, ddof=1):.2f}")
    print(f"seeds={args.seeds} z_jackknife_mean={zj.mean():.3f} z_jackknife_sd={zj.std(ddof=1):.3f} "
          f"z_jacobian_mean={np.nanmean(zc):.3f} z_jacobian_sd={np.nanstd(zc, ddof=1):.3f}")


if __name__ == "__main__":
    main()
