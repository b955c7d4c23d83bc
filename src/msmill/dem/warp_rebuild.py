"""The neighbour-list rebuild in NVIDIA Warp, and the engine state kept on the Warp device.

Imported only with a Warp backend (:mod:`msmill.dem.backend`). :class:`DeviceEngine` holds every
array the step and the rebuild use (particles, contact-history slots, lists, event buffers) on
one Warp device and runs both there, so on CUDA the particle state stays on the GPU across steps
and rebuilds; ``Simulation`` copies it back only where the host reads it (:meth:`to_host`) and
up again after the host changed it (:meth:`to_device`).

The rebuild is a port of ``Simulation._rebuild``'s numba passes that gives the same lists in the
same order (the force pass sums a particle's contacts in list order, the integration pass its
partner shares in reverse-list order, so the order is kept, and with it the bits):

* cells: a key per particle (``kernels.bin_cells``' cell index), a stable ``radix_sort_pairs``
  of (key, index) (the counting sort's order: by cell, then by index), counts by atomics and
  ``array_scan`` for the cell starts; every ``sort_every`` rebuilds, every per-particle array,
  history slots included, is gathered into that order (``Simulation._keep``);
* half list: one thread per particle counts, then writes, its partners in the 27 cells in the
  numba sweep's order (``kernels._neighbours_rows``); ``array_scan`` gives the row starts;
* reverse list: a stable sort of (partner, entry) pairs gives each entry's reverse position in
  list order, ``array_scan`` of the partner counts the reverse starts;
* geometry candidates (``kernels._geom_rows``) on the coarse geometry grid, which the host
  builds when the cut-off changes (a few hundred primitives) and uploads;
* per-particle work flags and the force pass's particle list (``kernels.particle_kinds``,
  ``kernels.work_lists``: flags, ``array_scan``, scatter).

The tangential history needs no carrying over: it lives in the owner's slots keyed by partner
id, not in list entries, and moves with its particle in the sort; the periodic wrap shifts the
image code of its geometry keys (``kernels.wrap_positions``). Per rebuild two small reads come
back to the host: the two list lengths (to allocate them) and the force pass's particle count.
"""

from __future__ import annotations

from typing import Any

import numpy as np
import warp as wp

from msmill.dem import kernels as K
from msmill.dem.warp_kernels import (
    C_GEO,
    C_OWN,
    C_PLANE,
    C_STRIDE,
    C_WRAP,
    F64_2D,
    ZERO,
    WarpStepper,
    _weight_free,
    f64,
    geom_contact,
    image_shift,
)

C_REV = wp.constant(K.K_REV)
I32 = wp.array(dtype=wp.int32)
I64 = wp.array(dtype=wp.int64)
I32_2D = wp.array2d(dtype=wp.int32)
F64 = wp.array(dtype=wp.float64)


# --------------------------------------------------------------------------- small passes
@wp.kernel
def settle_k(kind: wp.array(dtype=wp.uint8), mass: F64, gravity: F64, frc: F64_2D, trq: F64_2D,
             shs: I64, stamp: wp.int64):
    """``frc``/``trq`` of step ``stamp``'s force pass for particles out of contact (``kernels.settle_forces``)."""
    i = wp.tid()
    if (int(kind[i]) & 8) != 0 or shs[i] == stamp:  # K_HIT, or got shares in that step
        return
    mi = mass[i]
    frc[i, 0] = mi * gravity[0]
    frc[i, 1] = mi * gravity[1]
    frc[i, 2] = mi * gravity[2]
    trq[i, 0] = ZERO
    trq[i, 1] = ZERO
    trq[i, 2] = ZERO


@wp.func
def image_code(sx: int, sy: int, sz: int):
    """Code of the image shift ``(sx, sy, sz)`` (``kernels._image_code``)."""
    return ((sx & 15) << 8) | ((sy & 15) << 4) | (sz & 15)


@wp.kernel
def wrap_k(pos: F64_2D, lo: F64, box_len: F64, periodic: wp.array(dtype=wp.int8),
           g_gid: I32_2D, g_n: I32, gspan: wp.array2d(dtype=wp.int8)):
    """Positions into the periodic box; geometry keys follow (``kernels.wrap_positions``)."""
    i = wp.tid()
    ks = wp.vec3i(0, 0, 0)
    for a in range(3):
        if periodic[a] != wp.int8(0):
            L = box_len[a]
            x = pos[i, a] - lo[a]
            if x < ZERO or x >= L:
                k = int(wp.floor(x / L))
                x = x - f64(k) * L
                if x >= L:
                    x = x - L
                    k = k + 1
                pos[i, a] = lo[a] + x
                ks[a] = k
    if ks[0] == 0 and ks[1] == 0 and ks[2] == 0:
        return
    for q in range(int(g_n[i])):
        key = int(g_gid[i, q])
        g = key // C_STRIDE
        code = key % C_STRIDE
        s = wp.vec3i(0, 0, 0)
        for a in range(3):
            s[a] = image_shift(code, a)
            if gspan[g, a] == wp.int8(0):
                s[a] = s[a] + ks[a]
            s[a] = wp.min(wp.max(s[a], -8), 7)
        g_gid[i, q] = wp.int32(g * C_STRIDE + image_code(s[0], s[1], s[2]))


@wp.kernel
def cell_k(pos: F64_2D, lo: F64, cell_len: F64, ncell: I32, key: I32, idx: I32, cc: I32_2D):
    """Cell of particle ``i`` (``kernels.bin_cells``): sort key, index, cell coordinates."""
    i = wp.tid()
    c = wp.vec3i(0, 0, 0)
    for a in range(3):
        c[a] = wp.min(wp.max(int(wp.floor((pos[i, a] - lo[a]) / cell_len[a])), 0), ncell[a] - 1)
        cc[i, a] = wp.int32(c[a])
    key[i] = wp.int32((c[2] * ncell[1] + c[1]) * ncell[0] + c[0])
    idx[i] = wp.int32(i)


@wp.kernel
def count_keys_k(key: I32, counts: I64):
    """Entries per key (cell or reverse-list partner)."""
    wp.atomic_add(counts, int(key[wp.tid()]), wp.int64(1))


@wp.kernel
def gather_k(src: wp.array2d(dtype=Any), order: I32, dst: wp.array2d(dtype=Any)):
    """Row ``i`` of ``dst`` is row ``order[i]`` of ``src``."""
    i, k = wp.tid()
    dst[i, k] = src[order[i], k]


@wp.kernel
def arange_k(a: I32):
    a[wp.tid()] = wp.int32(wp.tid())


# --------------------------------------------------------------------------- half list
@wp.func
def neighbour_cell(q: int, n: int, per: wp.int8):
    """``kernels._neighbour_cell``: ``(index, image shift, ok)`` of cell ``q`` along one axis."""
    if q < 0:
        if per == wp.int8(0) or n < 3:
            return 0, 0, False
        return q + n, -1, True
    if q >= n:
        if per == wp.int8(0) or n < 3:
            return 0, 0, False
        return q - n, 1, True
    return q, 0, True


@wp.kernel
def neighbours_k(pid: I64, pos: F64_2D, rad: F64, skin: f64, cc: I32_2D, start: I64, order: I32,
                 ncell: I32, periodic: wp.array(dtype=wp.int8), box_len: F64, nb_start: I64,
                 fill: int, nb_j: I32, nb_sh: wp.array2d(dtype=wp.int8), counts: I64):
    """Row ``i`` of the half list (``kernels._neighbours_rows``): count (``fill=0``) or write it."""
    i = wp.tid()
    xi = pos[i, 0]
    yi = pos[i, 1]
    zi = pos[i, 2]
    ri = rad[i]
    idi = pid[i]
    cnt = int(0)
    o = int(0)
    if fill != 0:
        o = int(nb_start[i])
    for oz in range(-1, 2):
        qz, sz, okz = neighbour_cell(int(cc[i, 2]) + oz, int(ncell[2]), periodic[2])
        if not okz:
            continue
        for oy in range(-1, 2):
            qy, sy, oky = neighbour_cell(int(cc[i, 1]) + oy, int(ncell[1]), periodic[1])
            if not oky:
                continue
            for ox in range(-1, 2):
                qx, sx, okx = neighbour_cell(int(cc[i, 0]) + ox, int(ncell[0]), periodic[0])
                if not okx:
                    continue
                q = (qz * int(ncell[1]) + qy) * int(ncell[0]) + qx
                offx = f64(sx) * box_len[0]
                offy = f64(sy) * box_len[1]
                offz = f64(sz) * box_len[2]
                for p in range(int(start[q]), int(start[q + 1])):
                    j = int(order[p])
                    if pid[j] <= idi:
                        continue
                    dx = pos[j, 0] + offx - xi
                    dy = pos[j, 1] + offy - yi
                    dz = pos[j, 2] + offz - zi
                    cut = ri + rad[j] + skin
                    if dx * dx + dy * dy + dz * dz < cut * cut:
                        if fill != 0:
                            nb_j[o + cnt] = wp.int32(j)
                            nb_sh[o + cnt, 0] = wp.int8(sx)
                            nb_sh[o + cnt, 1] = wp.int8(sy)
                            nb_sh[o + cnt, 2] = wp.int8(sz)
                        cnt = cnt + 1
    counts[i] = wp.int64(cnt)


@wp.kernel
def reverse_k(sorted_k: I32, rv_pos: I64):
    """Reverse position of each entry: its place among its partner's entries, in list order."""
    q = wp.tid()
    rv_pos[int(sorted_k[q])] = wp.int64(q)


# --------------------------------------------------------------------------- geometry candidates
@wp.func
def geom_candidate(g: int, x: f64, y: f64, z: f64, r: f64, skin: f64, gcur: F64_2D, grot: F64_2D,
                   gkind: I32, gbound: F64_2D):
    """``kernels._geom_candidate``: static by distance, rotating by the swept annulus."""
    m = r + skin
    if grot[g, 7] > ZERO:
        if gkind[g] == C_PLANE:
            return True
        px = x - grot[g, 0]
        py = y - grot[g, 1]
        pz = z - grot[g, 2]
        a = px * grot[g, 3] + py * grot[g, 4] + pz * grot[g, 5]
        qx = px - a * grot[g, 3]
        qy = py - a * grot[g, 4]
        qz = pz - a * grot[g, 5]
        rho = wp.sqrt(qx * qx + qy * qy + qz * qz)
        return (rho >= gbound[g, 0] - m and rho <= gbound[g, 1] + m
                and a >= gbound[g, 2] - m and a <= gbound[g, 3] + m)
    if (x < gbound[g, 0] - m or y < gbound[g, 1] - m or z < gbound[g, 2] - m
            or x > gbound[g, 3] + m or y > gbound[g, 4] + m or z > gbound[g, 5] + m):
        return False
    ok, _s, _nx, _ny, _nz, _cx, _cy, _cz = geom_contact(gkind[g], gcur, g, x, y, z, m)
    return ok


@wp.func
def image_useful(p: f64, s: int, L: f64, lo: f64, hi: f64, m: f64):
    """``kernels._image_useful``."""
    q = p + f64(s) * L
    return q >= lo - m and q <= hi + m


@wp.func
def shift_range(per: wp.int8):
    """Image shifts tried along an axis: ``-1..1`` if periodic, else ``0..0``."""
    if per != wp.int8(0):
        return 1
    return 0


@wp.kernel
def geom_rows_k(pos: F64_2D, rad: F64, skin: f64, gcur: F64_2D, grot: F64_2D, gkind: I32,
                gbound: F64_2D, gspan: wp.array2d(dtype=wp.int8), periodic: wp.array(dtype=wp.int8),
                box_len: F64, img_box: F64, glo: F64, gcl: F64, gnc: I32, grid_start: I64,
                grid_list: I32, gc_start: I64, fill: int, gc_g: I32, counts: I64):
    """Geometry candidate keys of particle ``i`` (``kernels._geom_rows``): count or write."""
    i = wp.tid()
    cnt = int(0)
    o = int(0)
    if fill != 0:
        o = int(gc_start[i])
    m = rad[i] + skin
    px = shift_range(periodic[0])
    py = shift_range(periodic[1])
    pz = shift_range(periodic[2])
    for sx in range(-px, px + 1):
        if sx != 0 and not image_useful(pos[i, 0], sx, box_len[0], img_box[0], img_box[3], m):
            continue
        for sy in range(-py, py + 1):
            if sy != 0 and not image_useful(pos[i, 1], sy, box_len[1], img_box[1], img_box[4], m):
                continue
            for sz in range(-pz, pz + 1):
                if sz != 0 and not image_useful(pos[i, 2], sz, box_len[2], img_box[2], img_box[5], m):
                    continue
                x = pos[i, 0] + f64(sx) * box_len[0]
                y = pos[i, 1] + f64(sy) * box_len[1]
                z = pos[i, 2] + f64(sz) * box_len[2]
                code = image_code(sx, sy, sz)
                cx = wp.min(wp.max(int(wp.floor((x - glo[0]) / gcl[0])), 0), int(gnc[0]) - 1)
                cy = wp.min(wp.max(int(wp.floor((y - glo[1]) / gcl[1])), 0), int(gnc[1]) - 1)
                cz = wp.min(wp.max(int(wp.floor((z - glo[2]) / gcl[2])), 0), int(gnc[2]) - 1)
                cell = (cz * int(gnc[1]) + cy) * int(gnc[0]) + cx
                for q in range(int(grid_start[cell]), int(grid_start[cell + 1])):
                    g = int(grid_list[q])
                    if ((sx != 0 and gspan[g, 0] != wp.int8(0)) or (sy != 0 and gspan[g, 1] != wp.int8(0))
                            or (sz != 0 and gspan[g, 2] != wp.int8(0))):
                        continue
                    if geom_candidate(g, x, y, z, rad[i], skin, gcur, grot, gkind, gbound):
                        if fill != 0:
                            gc_g[o + cnt] = wp.int32(g * C_STRIDE + code)
                        cnt = cnt + 1
    counts[i] = wp.int64(cnt)


# --------------------------------------------------------------------------- work flags
@wp.kernel
def kinds_k(nb_start: I64, nb_sh: wp.array2d(dtype=wp.int8), rv_start: I64, gc_start: I64,
            h_n: I32, g_n: I32, vel: F64_2D, omg: F64_2D, kind: wp.array(dtype=wp.uint8),
            owner: I32):
    """Work flags of particle ``i`` (``kernels.particle_kinds``); ``owner``: the force pass visits it."""
    i = wp.tid()
    k = int(0)
    if nb_start[i + 1] > nb_start[i] or h_n[i] > 0:
        k = k | C_OWN
    if gc_start[i + 1] > gc_start[i] or g_n[i] > 0:
        k = k | C_GEO
    if rv_start[i + 1] > rv_start[i]:
        k = k | C_REV
    for q in range(int(nb_start[i]), int(nb_start[i + 1])):
        if nb_sh[q, 0] != wp.int8(0) or nb_sh[q, 1] != wp.int8(0) or nb_sh[q, 2] != wp.int8(0):
            k = k | C_WRAP
            break
    kind[i] = wp.uint8(k)
    owner[i] = 0
    if (k & (C_OWN | C_GEO)) != 0:
        owner[i] = 1
    for a in range(3):
        if vel[i, a] == ZERO:
            vel[i, a] = ZERO
        if omg[i, a] == ZERO:
            omg[i, a] = ZERO


@wp.kernel
def own_list_k(owner: I32, incl: I32, own_idx: wp.array(dtype=wp.uint32)):
    """The force pass's particles in ascending order (``kernels.work_lists``' ``own_idx``)."""
    i = wp.tid()
    if owner[i] != 0:
        own_idx[incl[i] - 1] = wp.uint32(i)



@wp.kernel
def totals_k(nb_start: I64, gc_start: I64, n: int, out: I64):
    """The two list lengths, for one read by the host."""
    out[0] = nb_start[n]
    out[1] = gc_start[n]


# --------------------------------------------------------------------------- the device engine
#: host arrays of the step and rebuild that are not per particle: (name on the device, attribute)
_STATIC = (("gref", "_gref"), ("grot", "_grot"), ("gkind", "_gkind"), ("gmat", "_gmat"),
           ("ptab", "_ptab"), ("gravity", "_gravity"), ("lo", "_lo"), ("hi", "_hi"),
           ("periodic", "_periodic"), ("sinks", "_sinkbox"), ("box_len", "_box_len"),
           ("gbound", "_gbound"), ("gspan", "_gspan"), ("img_box", "_img_box"), ("disp", "_disp"),
           ("gcur", "_gcur"))
#: the lists, as the host keeps them: (attribute, names of its leading items on the device)
_LISTS = (("_nb", ("nb_start", "nb_j", "nb_sh", "rv_start", "rv_pos")), ("_pair", ("pc", "pf", "pt", "shs")),
          ("_gc", ("gc_start", "gc_g")))
_EVENTS = ("evf", "evi", "evn")
_DTYPES = {np.dtype(np.float64): wp.float64, np.dtype(np.int64): wp.int64,
           np.dtype(np.int32): wp.int32, np.dtype(np.uint32): wp.uint32,
           np.dtype(np.uint8): wp.uint8, np.dtype(np.int8): wp.int8}


class DeviceEngine:
    """A simulation's arrays on one Warp device, with the step and the rebuild that run there.

    ``Simulation`` makes one for a Warp backend (``_on_device``) and calls :meth:`rebuild` and
    :meth:`advance` instead of the numba passes, :meth:`to_host` before the host reads its
    arrays and marks them changed (``dev_ok = False``) when it may write them.

    Parameters
    ----------
    device : str
        Warp device, ``"cpu"`` or ``"cuda:0"``.
    """

    def __init__(self, device: str) -> None:
        self.device = device
        self.stepper = WarpStepper(device, share=False)
        self.d: dict[str, wp.array] = {}
        self.dev_ok = False  # device arrays hold the state (else the host's are newer)
        self.host_ok = True  # host arrays hold the state (else the device's are newer)
        self.lists_on_dev = False
        self.lists_on_host = True
        self._grid = None  # the host geometry grid last uploaded

    # ------------------------------------------------------------------ copies
    def _up(self, a: np.ndarray) -> wp.array:
        return wp.array(np.ascontiguousarray(a), dtype=_DTYPES[a.dtype], device=self.device)

    def to_device(self, sim: Any) -> None:
        """Upload what the host changed: particles, slots, events, tables; the lists if none are here."""
        if not self.dev_ok:
            pd = sim._pd
            self.d.update({k: self._up(v) for k, v in pd.items() if k not in ("h_rec", "g_rec")})
            self.d.update({k: self._up(getattr(sim, a)) for k, a in _STATIC})
            self.d.update({k: self._up(getattr(sim._rec, k)) for k in _EVENTS})
            self.d["diag"] = wp.zeros((sim._nch, K.N_DIAG), dtype=wp.float64, device=self.device)
            self.dev_ok = True
        if not self.lists_on_dev and not sim._need_rebuild:
            for attr, names in _LISTS:
                self.d.update({k: self._up(v) for k, v in zip(names, getattr(sim, attr), strict=False)})
            self.d["kind"] = self._up(sim._kind)
            self.d["own_idx"] = self._up(sim._work[0])
            self.lists_on_dev = True

    def to_host(self, sim: Any, lists: bool = False) -> None:
        """Download the state into the host arrays (and, with ``lists``, the lists as the host keeps them)."""
        if not self.host_ok:
            wp.synchronize_device(self.device)
            pd = sim._pd
            for k, v in pd.items():
                if k not in ("h_rec", "g_rec") and v.size:
                    v[...] = self.d[k].numpy()
            for k, a in (("disp", "_disp"), ("gcur", "_gcur")):
                getattr(sim, a)[...] = self.d[k].numpy()
            for k in _EVENTS:
                getattr(sim._rec, k)[...] = self.d[k].numpy()
            np.minimum(sim._rec.evn, sim._rec.evf.shape[1], out=sim._rec.evn)
            self.host_ok = True
        if lists and not self.lists_on_host and self.lists_on_dev:
            self._lists_to_host(sim)

    def _lists_to_host(self, sim: Any) -> None:
        """The lists into the host's tuples (``Simulation._nb``, ``_pair``, ``_gc``, ``_kind``, ``_work``)."""
        for attr, names in _LISTS:
            got = [self.d[k].numpy() for k in names]
            if attr != "_pair":  # the widest row (a hint of the numba rebuild)
                got.append(int(np.diff(got[0]).max(initial=0)))
            setattr(sim, attr, tuple(got))
        sim._kind = self.d["kind"].numpy()
        sim._work = K.work_lists(sim._kind, sim._nch)
        self.lists_on_host = True

    # ------------------------------------------------------------------ step
    def settle(self, sim: Any) -> None:
        """Settle ``frc``/``trq`` to the last step's force pass on the device (``kernels.settle_forces``)."""
        self.to_device(sim)
        d = self.d
        stamp = sim._stamp
        n = d["pos"].shape[0]
        if n and "kind" in d:
            wp.launch(settle_k, dim=n, device=self.device, inputs=[
                d["kind"], d["mass"], d["gravity"], d["frc"], d["trq"], d["shs"], stamp])
            self.host_ok = False

    def advance(self, sim: Any, dt: float, limit: int, diag: np.ndarray) -> tuple[int, int]:
        """Up to ``limit`` steps on the device; ``diag`` gets the diagnostics; ``(steps, reason)``."""
        self.to_device(sim)
        self.d["diag"].zero_()
        k, reason = self.stepper.run(self.d, sim._time, dt, limit, sim._skin, sim._stamp + 1,
                                     _weight_free(sim._gravity))
        diag[...] = self.d["diag"].numpy()
        self.host_ok = self.lists_on_host = False
        return k, reason

    # ------------------------------------------------------------------ rebuild
    def rebuild(self, sim: Any, sort: bool) -> None:
        """Wrap, bin, (``sort``: reorder), then build every list on the device, as ``Simulation._rebuild``.

        ``sim._gcur`` (the poses at the rebuild's time), the cell grid and the geometry grid are
        the host's, computed before the call.
        """
        self.to_device(sim)
        d, dev = self.d, self.device
        n = d["pos"].shape[0]
        d["gcur"] = self._up(sim._gcur)
        if sim._ggrid is not self._grid:
            d["grid_start"], d["grid_list"] = (self._up(a) for a in sim._ggrid)
            for k, a in (("glo", sim._lo), ("gcl", sim._gcl), ("gnc", sim._gnc.astype(np.int32))):
                d[k] = self._up(a)
            self._grid = sim._ggrid
        if n:
            wp.launch(wrap_k, dim=n, device=dev, inputs=[
                d["pos"], d["lo"], d["box_len"], d["periodic"], d["g_gid"], d["g_n"], d["gspan"]])
        order = self._bin(sim, n)
        if sort and n:
            self._permute(order, [k for k in sim._pd if k not in ("h_rec", "g_rec")] + ["cc"])
            wp.launch(arange_k, dim=n, device=dev, inputs=[order])
        m, _mg = self._lists(sim, n, order)
        self._reverse(n, m)
        d["pc"] = wp.zeros(m, dtype=wp.int64, device=dev)
        d["pf"] = wp.zeros((m, 3), dtype=wp.float64, device=dev)
        d["pt"] = wp.zeros((m, 3), dtype=wp.float64, device=dev)
        d["shs"] = wp.zeros(n, dtype=wp.int64, device=dev)
        self._kinds(n)
        d["disp"].zero_()
        self.host_ok = self.lists_on_host = False
        self.lists_on_dev = True

    def _bin(self, sim: Any, n: int) -> wp.array:
        """Cell keys, a stable sort by key (``order``), cell starts (``d["start"]``) and coordinates (``d["cc"]``)."""
        d, dev = self.d, self.device
        ntot = int(np.prod(sim._ncell))
        key = wp.empty(2 * n, dtype=wp.int32, device=dev)
        val = wp.empty(2 * n, dtype=wp.int32, device=dev)
        d["cc"] = wp.empty((n, 3), dtype=wp.int32, device=dev)
        counts = wp.zeros(ntot + 1, dtype=wp.int64, device=dev)
        if n:
            wp.launch(cell_k, dim=n, device=dev, inputs=[
                d["pos"], d["lo"], self._up(sim._cell_len), self._up(sim._ncell.astype(np.int32)),
                key, val, d["cc"]])
            wp.utils.radix_sort_pairs(key, val, n)
            wp.launch(count_keys_k, dim=n, device=dev, inputs=[key, counts])
        d["start"] = wp.empty(ntot + 1, dtype=wp.int64, device=dev)
        wp.utils.array_scan(counts, d["start"], inclusive=False)
        d["ncell"] = self._up(sim._ncell.astype(np.int32))
        return val[:n]

    def _permute(self, order: wp.array, names: list[str]) -> None:
        """Gather every named per-particle array into ``order`` (``Simulation._keep``)."""
        n = order.shape[0]
        for k in names:
            src = self.d[k]
            flat = src.reshape((n, src.size // n))
            out = wp.empty_like(flat)
            if flat.shape[1]:
                wp.launch(gather_k, dim=flat.shape, device=self.device, inputs=[flat, order, out])
            self.d[k] = out.reshape(src.shape)

    def _rows(self, kernel, n: int, inputs: list, fill_args: tuple, start_name: str) -> None:
        """One counting pass of a row kernel, the row starts by ``array_scan``."""
        counts = wp.zeros(n + 1, dtype=wp.int64, device=self.device)
        start = wp.empty(n + 1, dtype=wp.int64, device=self.device)
        if n:
            wp.launch(kernel, dim=n, device=self.device, inputs=[*inputs, start, 0, *fill_args, counts])
        wp.utils.array_scan(counts, start, inclusive=False)
        self.d[start_name] = start

    def _lists(self, sim: Any, n: int, order: wp.array) -> tuple[int, int]:
        """Half list and geometry candidates: count, scan, one read of the lengths, fill."""
        d, dev = self.d, self.device
        none8 = wp.empty((0, 3), dtype=wp.int8, device=dev)
        none32 = wp.empty(0, dtype=wp.int32, device=dev)
        nb_in = [d["pid"], d["pos"], d["rad"], float(sim._skin), d["cc"], d["start"], order,
                 d["ncell"], d["periodic"], d["box_len"]]
        self._rows(neighbours_k, n, nb_in, (none32, none8), "nb_start")
        geo = d["gkind"].shape[0] > 0
        gc_in = [d["pos"], d["rad"], float(sim._skin), d["gcur"], d["grot"], d["gkind"],
                 d["gbound"], d["gspan"], d["periodic"], d["box_len"], d["img_box"]]
        if geo:
            gc_in += [d["glo"], d["gcl"], d["gnc"], d["grid_start"], d["grid_list"]]
            self._rows(geom_rows_k, n, gc_in, (none32,), "gc_start")
        else:
            d["gc_start"] = wp.zeros(n + 1, dtype=wp.int64, device=dev)
        tot = wp.empty(2, dtype=wp.int64, device=dev)
        wp.launch(totals_k, dim=1, device=dev, inputs=[d["nb_start"], d["gc_start"], n, tot])
        m, mg = (int(x) for x in tot.numpy())
        d["nb_j"] = wp.empty(m, dtype=wp.int32, device=dev)
        d["nb_sh"] = wp.empty((m, 3), dtype=wp.int8, device=dev)
        d["gc_g"] = wp.empty(mg, dtype=wp.int32, device=dev)
        scratch = wp.empty(n + 1, dtype=wp.int64, device=dev)
        if n and m:
            wp.launch(neighbours_k, dim=n, device=dev, inputs=[
                *nb_in, d["nb_start"], 1, d["nb_j"], d["nb_sh"], scratch])
        if n and mg:
            wp.launch(geom_rows_k, dim=n, device=dev, inputs=[
                *gc_in, d["gc_start"], 1, d["gc_g"], scratch])
        return m, mg

    def _reverse(self, n: int, m: int) -> None:
        """Reverse list: starts by partner counts and a scan, positions by a stable sort of (partner, entry)."""
        d, dev = self.d, self.device
        counts = wp.zeros(n + 1, dtype=wp.int64, device=dev)
        d["rv_start"] = wp.empty(n + 1, dtype=wp.int64, device=dev)
        d["rv_pos"] = wp.empty(m, dtype=wp.int64, device=dev)
        if m:
            key = wp.empty(2 * m, dtype=wp.int32, device=dev)
            val = wp.empty(2 * m, dtype=wp.int32, device=dev)
            wp.copy(key, d["nb_j"], count=m)
            wp.launch(arange_k, dim=m, device=dev, inputs=[val])
            wp.utils.radix_sort_pairs(key, val, m)
            wp.launch(count_keys_k, dim=m, device=dev, inputs=[d["nb_j"], counts])
            wp.launch(reverse_k, dim=m, device=dev, inputs=[val, d["rv_pos"]])
        wp.utils.array_scan(counts, d["rv_start"], inclusive=False)

    def _kinds(self, n: int) -> None:
        """Work flags and the force pass's particles (one read: their number)."""
        d, dev = self.d, self.device
        d["kind"] = wp.empty(n, dtype=wp.uint8, device=dev)
        owner = wp.zeros(max(n, 1), dtype=wp.int32, device=dev)
        incl = wp.zeros(max(n, 1), dtype=wp.int32, device=dev)
        if n:
            wp.launch(kinds_k, dim=n, device=dev, inputs=[
                d["nb_start"], d["nb_sh"], d["rv_start"], d["gc_start"], d["h_n"], d["g_n"],
                d["vel"], d["omg"], d["kind"], owner])
            wp.utils.array_scan(owner, incl, inclusive=True)
        n_own = int(incl[max(n, 1) - 1:].numpy()[0]) if n else 0
        d["own_idx"] = wp.empty(n_own, dtype=wp.uint32, device=dev)
        if n_own:
            wp.launch(own_list_k, dim=n, device=dev, inputs=[owner, incl, d["own_idx"]])
