"""Event recorder: per-chunk onset buffers filled by the kernels, flushed to columns.

The kernels write one row per new contact into ``evf`` (float columns) and
``evi`` (int columns), both shaped ``(n_chunks, capacity, n_columns)``, and
keep a reference ``row * n_chunks + chunk`` in the contact's history slot so
the end fields (end time, peak overlap, dissipated energy) can be filled when
the contact ends. :meth:`EventRecorder.flush` moves finished rows to growing
column chunks and compacts the open ones (remapping the references held by
the history slots), so memory holds only open contacts plus the finished
columns.
"""

from __future__ import annotations

import numpy as np
import pandas as pd

from msmill.dem import kernels as K

FLOAT_COLUMNS = ["time_s", "radius_m", "partner_radius_m", "x_m", "y_m", "z_m", "vn_m_s",
                 "vt_m_s", "end_time_s", "peak_overlap_m", "dissipated_j"]
INT_COLUMNS = ["particle_id", "partner_kind", "partner_id"]
EVENT_COLUMNS = ["time_s", "particle_id", "partner_kind", "partner_id", "radius_m",
                 "partner_radius_m", "x_m", "y_m", "z_m", "vn_m_s", "vt_m_s", "end_time_s",
                 "peak_overlap_m", "dissipated_j"]


class EventRecorder:
    """Preallocated onset buffers plus finished-event columns.

    Parameters
    ----------
    n_chunks : int
        Number of particle chunks of the force pass (one buffer each).
    capacity : int
        Initial rows per chunk.
    """

    def __init__(self, n_chunks: int, capacity: int = 4096) -> None:
        self.n_chunks = n_chunks
        self.evf = np.zeros((n_chunks, capacity, K.N_EVF))
        self.evi = np.zeros((n_chunks, capacity, K.N_EVI), np.int64)
        self.evn = np.zeros(n_chunks, np.int64)
        self._done_f: list[np.ndarray] = []
        self._done_i: list[np.ndarray] = []
        self.lost = 0

    @property
    def capacity(self) -> int:
        """Rows per chunk."""
        return self.evf.shape[1]

    def flush(self, refs: list[np.ndarray]) -> None:
        """Move finished rows out, compact open ones and remap ``refs`` in place.

        Parameters
        ----------
        refs : list of (int64 array, int32 array)
            History-slot event references (``-1`` = none) to remap, each with
            the number of used slots per particle (unused slots are not read).
        """
        nch = self.n_chunks
        cap = self.capacity
        new_row = np.full((cap, nch), -1, np.int64)
        n_open = np.zeros(nch, np.int64)
        for c in range(nch):  # loop over a handful of chunks, not events
            rows = int(self.evn[c])
            f = self.evf[c, :rows]
            i = self.evi[c, :rows]
            closed = ~np.isnan(f[:, K.EV_END])
            if closed.any():
                self._done_f.append(f[closed].copy())
                self._done_i.append(i[closed].copy())
            op = ~closed
            k = int(op.sum())
            new_row[np.nonzero(op)[0], c] = np.arange(k)
            self.evf[c, :k] = f[op]
            self.evi[c, :k] = i[op]
            self.evn[c] = k
            n_open[c] = k
        for r, cnt in refs:
            K.remap_event_refs(r, cnt, new_row)
        if n_open.max() > cap // 4:
            self._grow(2 * cap)

    def append_only_lists(self) -> dict[str, list[np.ndarray]]:
        """The finished-event chunks (float and int columns): lists that :meth:`flush` only appends to."""
        return {"events_f": self._done_f, "events_i": self._done_i}

    def _grow(self, cap: int) -> None:
        old = self.capacity
        evf = np.zeros((self.n_chunks, cap, K.N_EVF))
        evi = np.zeros((self.n_chunks, cap, K.N_EVI), np.int64)
        evf[:, :old] = self.evf
        evi[:, :old] = self.evi
        self.evf, self.evi = evf, evi

    def frame(self, since_s: float | None = None) -> pd.DataFrame:
        """The events (finished and open) opened at or after ``since_s`` (s; None: all), sorted by onset time.

        Rows are selected chunk by chunk before they are joined: memory holds the selection, not the
        whole record (a fine-rock run records tens of millions of contacts before its window).
        """
        fs = list(self._done_f)
        is_ = list(self._done_i)
        for c in range(self.n_chunks):
            rows = int(self.evn[c])
            fs.append(self.evf[c, :rows])
            is_.append(self.evi[c, :rows])
        if since_s is not None:
            keep = [f[:, K.EV_T] >= since_s for f in fs]
            fs = [f[k] for f, k in zip(fs, keep, strict=True)]
            is_ = [i[k] for i, k in zip(is_, keep, strict=True)]
        f = np.concatenate(fs) if fs else np.zeros((0, K.N_EVF))
        i = np.concatenate(is_) if is_ else np.zeros((0, K.N_EVI), np.int64)
        del fs, is_
        data = {name: f[:, k] for k, name in enumerate(FLOAT_COLUMNS)}
        data.update({name: i[:, k] for k, name in enumerate(INT_COLUMNS)})
        data["partner_kind"] = data["partner_kind"].astype(np.int8)
        order = np.lexsort((data["particle_id"], data["time_s"]))  # by onset, ties by rock (stable)
        return pd.DataFrame({name: data[name][order] for name in EVENT_COLUMNS})
