"""Single-threaded native thread pools for small linear algebra (core helper).

The model's and the surrogate's matrices are small (tens to hundreds of
rows): BLAS/OpenMP threads gain nothing and, on a busy machine, spinning
threads cost up to 10x. :func:`single_threaded` limits the pools to one
thread inside a ``with`` block.

``threadpoolctl.threadpool_limits`` scans the loaded shared libraries on every
call (about 8 ms); here the scan (a ``ThreadpoolController``) is made once, on
first use, and each ``with`` block only sets and restores the thread counts
(tens of microseconds). A library loaded after that first use is not limited.
Without ``threadpoolctl`` (it comes with scikit-learn) the block does nothing.
"""

from __future__ import annotations

import contextlib
from collections.abc import Iterator
from functools import lru_cache
from typing import Any


@lru_cache(maxsize=1)
def _controller() -> Any:
    try:
        from threadpoolctl import ThreadpoolController
    except ImportError:  # pragma: no cover
        return None
    import scipy.linalg  # noqa: F401  - load scipy's own BLAS before the scan

    return ThreadpoolController()


@contextlib.contextmanager
def single_threaded(user_api: str | None = None) -> Iterator[None]:
    """Limit the native thread pools (``user_api``: ``"blas"``, ``"openmp"`` or None for all) to one thread."""
    ctl = _controller()
    if ctl is None:  # pragma: no cover
        yield
        return
    with ctl.limit(limits=1, user_api=user_api):
        yield
