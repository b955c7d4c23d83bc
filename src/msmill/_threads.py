"""One BLAS/OpenMP thread around small numerical kernels.

scikit-learn's k-means (the EM initialisation of the velocity mixtures) and
the GP's small linear algebra run OpenMP/BLAS thread pools; on a loaded or
oversubscribed machine their spinning threads made a velocity fit ten times
slower (1.54 s against 0.15 s for K = 1..4 on 704 samples, measured
2026-12-01). The data are tiny, so one thread is always the faster choice.
"""

from __future__ import annotations

import contextlib
from typing import Any


def one_thread() -> Any:
    """Context manager limiting BLAS/OpenMP pools to one thread (a no-op without threadpoolctl)."""
    try:
        from threadpoolctl import threadpool_limits
    except ImportError:  # pragma: no cover
        return contextlib.nullcontext()
    return threadpool_limits(1)
