"""The DEM time step in NVIDIA Warp: one kernel source for Warp's CPU device and CUDA.

Imported only when a Warp backend is chosen (``Simulation(backend="warp-cpu" | "cuda")``,
:mod:`msmill.dem.backend`): ``import msmill.dem`` never loads Warp.

:func:`WarpStepper.advance` has the signature and the contract of
:func:`msmill.dem.kernels.advance`: it runs up to ``nsteps`` steps on the
engine's own arrays (half Verlet list and its reverse, geometry candidates,
history slots, event buffers, diagnostics) and returns ``(steps, reason)``.
The kernels below are a line-by-line port of the numba step passes
(``kernels._force_chunk``, ``kernels._integrate_chunk``,
``kernels.update_geometry``) with one thread per particle instead of one per
chunk: an owner writes its own force, history slots and events and its
partners' shares (no write races: a reverse-list position belongs to one
entry), the integration pass gathers the shares. The contact-law constants
come from the same pair table (:func:`msmill.dem.contact.pair_table`); the
force formula is written twice, here and in ``kernels.contact_law``
(``tests/dem/test_warp_backend.py`` checks that the two agree).

:meth:`WarpStepper.run` steps on arrays already on the device: with a Warp backend the
state and the neighbour rebuild stay there (:mod:`msmill.dem.warp_rebuild`); :meth:`advance`
(numba rebuilds, arrays copied in and out per call) is the previous data path.

Floating point: the module is compiled without FMA contraction (``fuse_fp``)
and without fast math, like the numba kernels (``fastmath=False``).
"""

from __future__ import annotations

import math

import numpy as np
import warp as wp

from msmill.dem import kernels as K
from msmill.dem.backend import warp_status

wp.config.log_level = wp.LOG_WARNING  # no greeting on stdout
wp.set_module_options({"fuse_fp": False, "fast_math": False, "enable_backward": False})

f64 = wp.float64
ZERO = wp.constant(wp.float64(0.0))
ONE = wp.constant(wp.float64(1.0))
HALF = wp.constant(wp.float64(0.5))

C_OWN = wp.constant(K.K_OWN)
C_GEO = wp.constant(K.K_GEO)
C_HIT = wp.constant(K.K_HIT)
C_WRAP = wp.constant(K.K_WRAP)
C_BOX = wp.constant(K.BOX)
C_PLANE = wp.constant(K.PLANE)
C_STRIDE = wp.constant(K.KEY_STRIDE)
C_D_OVER = wp.constant(K.D_OVER)
C_D_SPEED2 = wp.constant(K.D_SPEED2)
C_D_HOVF = wp.constant(K.D_HOVF)
C_D_EVOVF = wp.constant(K.D_EVOVF)
C_F_LOST = wp.constant(K.F_LOST)
C_F_NONFINITE = wp.constant(K.F_NONFINITE)
C_R_REBUILD = wp.constant(K.R_REBUILD)
C_R_FLAGGED = wp.constant(K.R_FLAGGED)
C_R_EVFULL = wp.constant(K.R_EVFULL)

F64_2D = wp.array2d(dtype=wp.float64)
F64_3D = wp.array3d(dtype=wp.float64)


# --------------------------------------------------------------------------- contact law
@wp.func
def contact_law(s: f64, nx: f64, ny: f64, nz: f64, vx: f64, vy: f64, vz: f64, rstar: f64,
                mstar: f64, kfac: f64, etah: f64, etat: f64, mu: f64, strat: f64, dt: f64,
                sx0: f64, sy0: f64, sz0: f64):
    """Paper Eqs. 4-10 for one contact: the same operations as ``kernels.contact_law``.

    Returns the force on body a (7 values: force, new tangential history, ``F_n``).
    """
    vn = vx * nx + vy * ny + vz * nz
    tx = vx - vn * nx
    ty = vy - vn * ny
    tz = vz - vn * nz
    kh = kfac * wp.sqrt(rstar)
    ch = f64(2.0) * etah * wp.sqrt(mstar * kh)
    sq = wp.sqrt(s)
    fel = kh * s * sq
    cn = ch * wp.sqrt(sq)
    a_ = HALF * cn * dt / mstar
    fn = (fel + cn * vn) / (ONE + a_)
    if fn < ZERO:
        fn = f64(0.0)
    fx = -fn * nx
    fy = -fn * ny
    fz = -fn * nz
    stmax = mu * s * strat
    if stmax <= ZERO:
        return fx, fy, fz, ZERO, ZERO, ZERO, fn
    sx = sx0
    sy = sy0
    sz = sz0
    sn = sx * nx + sy * ny + sz * nz
    if sn != ZERO:
        old2 = sx * sx + sy * sy + sz * sz
        sx = sx - sn * nx
        sy = sy - sn * ny
        sz = sz - sn * nz
        new2 = sx * sx + sy * sy + sz * sz
        if new2 > ZERO:
            sc = wp.sqrt(old2 / new2)
            sx = sx * sc
            sy = sy * sc
            sz = sz * sc
    sx = sx + tx * dt
    sy = sy + ty * dt
    sz = sz + tz * dt
    smag = wp.sqrt(sx * sx + sy * sy + sz * sz)
    zeta = f64(0.0)
    if smag >= stmax:
        sc2 = stmax / smag
        sx = sx * sc2
        sy = sy * sc2
        sz = sz * sc2
        smag = stmax
    else:
        zeta = ONE - smag / stmax
    if smag > ZERO:
        fe = mu * fn * (ONE - zeta * wp.sqrt(zeta)) / smag
        fx = fx - fe * sx
        fy = fy - fe * sy
        fz = fz - fe * sz
    if zeta > ZERO and fn > ZERO:
        cd = etat * wp.sqrt(f64(6.0) * mu * mstar * fn / stmax) * wp.sqrt(wp.sqrt(zeta))
        fx = fx - cd * tx
        fy = fy - cd * ty
        fz = fz - cd * tz
    return fx, fy, fz, sx, sy, sz, fn


@wp.func
def step_work(fx: f64, fy: f64, fz: f64, fn: f64, nx: f64, ny: f64, nz: f64, vx: f64, vy: f64,
              vz: f64, inv_m: f64, inv_rot: f64, dt: f64):
    """Work of a contact force over one step (J), as ``kernels._step_work``."""
    tfx = fx + fn * nx
    tfy = fy + fn * ny
    tfz = fz + fn * nz
    it = inv_m + inv_rot
    hx = vx + HALF * dt * (-fn * nx * inv_m + tfx * it)
    hy = vy + HALF * dt * (-fn * ny * inv_m + tfy * it)
    hz = vz + HALF * dt * (-fn * nz * inv_m + tfz * it)
    return (fx * hx + fy * hy + fz * hz) * dt


# --------------------------------------------------------------------------- geometry
@wp.func
def image_shift(code: int, a: int):
    """Shift (box lengths) along axis ``a`` of a geometry image code (``kernels._image_shift``)."""
    v = (code >> (4 * (2 - a))) & 15
    if v >= 8:
        v = v - 16
    return v


@wp.func
def geom_contact(kind: int, gall: F64_2D, g: int, x: f64, y: f64, z: f64, r: f64):
    """Overlap with one primitive, as ``kernels.geom_contact``: ``(ok, s, n, contact point)``."""
    if kind == C_PLANE:
        d = (x - gall[g, 0]) * gall[g, 3] + (y - gall[g, 1]) * gall[g, 4] + (z - gall[g, 2]) * gall[g, 5]
        if d >= r or d <= -r:
            return False, ZERO, ZERO, ZERO, ZERO, ZERO, ZERO, ZERO
        return (True, r - d, -gall[g, 3], -gall[g, 4], -gall[g, 5],
                x - d * gall[g, 3], y - d * gall[g, 4], z - d * gall[g, 5])
    if kind == C_BOX:
        rx = x - gall[g, 0]
        ry = y - gall[g, 1]
        rz = z - gall[g, 2]
        q0 = rx * gall[g, 3] + ry * gall[g, 4] + rz * gall[g, 5]
        q1 = rx * gall[g, 6] + ry * gall[g, 7] + rz * gall[g, 8]
        q2 = rx * gall[g, 9] + ry * gall[g, 10] + rz * gall[g, 11]
        h0 = gall[g, 12]
        h1 = gall[g, 13]
        h2 = gall[g, 14]
        p0 = wp.min(wp.max(q0, -h0), h0)
        p1 = wp.min(wp.max(q1, -h1), h1)
        p2 = wp.min(wp.max(q2, -h2), h2)
        e0 = q0 - p0
        e1 = q1 - p1
        e2 = q2 - p2
        dist2 = e0 * e0 + e1 * e1 + e2 * e2
        l0 = f64(0.0)
        l1 = f64(0.0)
        l2 = f64(0.0)
        s = f64(0.0)
        if dist2 > ZERO:
            if dist2 >= r * r:
                return False, ZERO, ZERO, ZERO, ZERO, ZERO, ZERO, ZERO
            dist = wp.sqrt(dist2)
            l0 = -e0 / dist
            l1 = -e1 / dist
            l2 = -e2 / dist
            s = r - dist
        else:  # centre inside: push out through the nearest face
            a0 = h0 - wp.abs(q0)
            a1 = h1 - wp.abs(q1)
            a2 = h2 - wp.abs(q2)
            if a0 <= a1 and a0 <= a2:
                sg = ONE
                if q0 < ZERO:
                    sg = -ONE
                l0 = -sg
                p0 = sg * h0
                s = r + a0
            elif a1 <= a2:
                sg = ONE
                if q1 < ZERO:
                    sg = -ONE
                l1 = -sg
                p1 = sg * h1
                s = r + a1
            else:
                sg = ONE
                if q2 < ZERO:
                    sg = -ONE
                l2 = -sg
                p2 = sg * h2
                s = r + a2
        nx = l0 * gall[g, 3] + l1 * gall[g, 6] + l2 * gall[g, 9]
        ny = l0 * gall[g, 4] + l1 * gall[g, 7] + l2 * gall[g, 10]
        nz = l0 * gall[g, 5] + l1 * gall[g, 8] + l2 * gall[g, 11]
        cx = gall[g, 0] + p0 * gall[g, 3] + p1 * gall[g, 6] + p2 * gall[g, 9]
        cy = gall[g, 1] + p0 * gall[g, 4] + p1 * gall[g, 7] + p2 * gall[g, 10]
        cz = gall[g, 2] + p0 * gall[g, 5] + p1 * gall[g, 8] + p2 * gall[g, 11]
        return True, s, nx, ny, nz, cx, cy, cz
    # cylinder
    ux = gall[g, 3]
    uy = gall[g, 4]
    uz = gall[g, 5]
    ln = gall[g, 6]
    rc = gall[g, 7]
    rx = x - gall[g, 0]
    ry = y - gall[g, 1]
    rz = z - gall[g, 2]
    a = rx * ux + ry * uy + rz * uz
    vx = rx - a * ux
    vy = ry - a * uy
    vz = rz - a * uz
    rho = wp.sqrt(vx * vx + vy * vy + vz * vz)
    if gall[g, 8] > HALF:  # inside a tube (open ends)
        if a < ZERO or a > ln or rho <= rc - r or rho >= rc + r or rho == ZERO:
            return False, ZERO, ZERO, ZERO, ZERO, ZERO, ZERO, ZERO
        nx = vx / rho
        ny = vy / rho
        nz = vz / rho
        return (True, rho + r - rc, nx, ny, nz,
                gall[g, 0] + a * ux + rc * nx, gall[g, 1] + a * uy + rc * ny,
                gall[g, 2] + a * uz + rc * nz)
    ex = f64(0.0)
    ey = f64(0.0)
    ez = f64(0.0)
    if rho > ZERO:
        ex = vx / rho
        ey = vy / rho
        ez = vz / rho
    if a >= ZERO and a <= ln and rho <= rc:  # centre inside the solid
        dside = rc - rho
        if dside <= a and dside <= ln - a:
            return (True, r + dside, -ex, -ey, -ez,
                    gall[g, 0] + a * ux + rc * ex, gall[g, 1] + a * uy + rc * ey,
                    gall[g, 2] + a * uz + rc * ez)
        if a <= ln - a:
            return True, r + a, ux, uy, uz, x - a * ux, y - a * uy, z - a * uz
        b = ln - a
        return True, r + b, -ux, -uy, -uz, x + b * ux, y + b * uy, z + b * uz
    ac = wp.min(wp.max(a, ZERO), ln)
    rr = wp.min(rho, rc)
    cx = gall[g, 0] + ac * ux + rr * ex
    cy = gall[g, 1] + ac * uy + rr * ey
    cz = gall[g, 2] + ac * uz + rr * ez
    dx = cx - x
    dy = cy - y
    dz = cz - z
    d2 = dx * dx + dy * dy + dz * dz
    if d2 >= r * r or d2 == ZERO:
        return False, ZERO, ZERO, ZERO, ZERO, ZERO, ZERO, ZERO
    d = wp.sqrt(d2)
    return True, r - d, dx / d, dy / d, dz / d, cx, cy, cz


@wp.kernel
def update_geometry_k(ctl: wp.array(dtype=wp.int32), gref: F64_2D, grot: F64_2D,
                      gkind: wp.array(dtype=wp.int32), t: f64, gcur: F64_2D):
    """Pose of primitive ``g`` at time ``t`` (``kernels.update_geometry``)."""
    g = wp.tid()
    if ctl[0] >= 0:
        return
    for k in range(gref.shape[1]):
        gcur[g, k] = gref[g, k]
    if grot[g, 7] <= ZERO:
        return
    th = grot[g, 6] * t
    ux = grot[g, 3]
    uy = grot[g, 4]
    uz = grot[g, 5]
    c = wp.cos(th)
    s = wp.sin(th)
    oc = ONE - c
    q00 = c + ux * ux * oc
    q01 = ux * uy * oc - uz * s
    q02 = ux * uz * oc + uy * s
    q10 = uy * ux * oc + uz * s
    q11 = c + uy * uy * oc
    q12 = uy * uz * oc - ux * s
    q20 = uz * ux * oc - uy * s
    q21 = uz * uy * oc + ux * s
    q22 = c + uz * uz * oc
    px = gref[g, 0] - grot[g, 0]
    py = gref[g, 1] - grot[g, 1]
    pz = gref[g, 2] - grot[g, 2]
    gcur[g, 0] = grot[g, 0] + q00 * px + q01 * py + q02 * pz
    gcur[g, 1] = grot[g, 1] + q10 * px + q11 * py + q12 * pz
    gcur[g, 2] = grot[g, 2] + q20 * px + q21 * py + q22 * pz
    nvec = 1
    if gkind[g] == C_BOX:
        nvec = 3
    for m in range(nvec):
        o = 3 + 3 * m
        dx = gref[g, o]
        dy = gref[g, o + 1]
        dz = gref[g, o + 2]
        gcur[g, o] = q00 * dx + q01 * dy + q02 * dz
        gcur[g, o + 1] = q10 * dx + q11 * dy + q12 * dz
        gcur[g, o + 2] = q20 * dx + q21 * dy + q22 * dz


# --------------------------------------------------------------------------- events
@wp.func
def chunk_of(i: int, n: int, nch: int):
    """Chunk ``c`` of particle ``i`` (``kernels.chunk_bounds``: ``[c n // nch, (c + 1) n // nch)``)."""
    c = (i * nch) // n
    while c > 0 and (c * n) // nch > i:
        c = c - 1
    while c < nch - 1 and ((c + 1) * n) // nch <= i:
        c = c + 1
    return c


@wp.func
def record_onset(evf: F64_3D, evi: wp.array3d(dtype=wp.int64), evn: wp.array(dtype=wp.int64),
                 c: int, t: f64, owner_pid: wp.int64, kind: int, partner: wp.int64, r: f64, pr: f64,
                 cx: f64, cy: f64, cz: f64, vn: f64, vt: f64, diag: F64_2D):
    """One event row at contact onset in chunk ``c``'s buffer; its reference (``kernels._record_onset``)."""
    row = wp.atomic_add(evn, c, wp.int64(1))
    if row >= wp.int64(evf.shape[1]):
        wp.atomic_add(diag, c, C_D_EVOVF, ONE)
        return wp.int64(-1)
    rw = int(row)
    nan = wp.nan
    evf[c, rw, 0] = t
    evf[c, rw, 1] = r
    evf[c, rw, 2] = pr
    evf[c, rw, 3] = cx
    evf[c, rw, 4] = cy
    evf[c, rw, 5] = cz
    evf[c, rw, 6] = vn
    evf[c, rw, 7] = vt
    evf[c, rw, 8] = f64(nan)
    evf[c, rw, 9] = f64(nan)
    evf[c, rw, 10] = f64(nan)
    evi[c, rw, 0] = owner_pid
    evi[c, rw, 1] = wp.int64(kind)
    evi[c, rw, 2] = partner
    return row * wp.int64(evf.shape[0]) + wp.int64(c)


@wp.func
def close_event(evf: F64_3D, ref: wp.int64, t: f64, peak: f64, diss: f64):
    nch = wp.int64(evf.shape[0])
    c = int(ref % nch)
    row = int(ref / nch)
    evf[c, row, 8] = t
    evf[c, row, 9] = peak
    evf[c, row, 10] = diss


@wp.func
def close_untouched_h(keys: wp.array2d(dtype=wp.int64), n: wp.array(dtype=wp.int32), st: F64_3D,
                      ev: wp.array2d(dtype=wp.int64), pk: F64_2D, ds: F64_2D,
                      tch: wp.array2d(dtype=wp.uint8), i: int, evf: F64_3D, t: f64):
    """End particle ``i``'s particle contacts untouched this step (``kernels._close_untouched_row``)."""
    q = int(0)
    while q < n[i]:
        if tch[i, q] == wp.uint8(1):
            tch[i, q] = wp.uint8(0)
            q = q + 1
            continue
        if ev[i, q] >= wp.int64(0):
            close_event(evf, ev[i, q], t, pk[i, q], ds[i, q])
        last = n[i] - 1
        keys[i, q] = keys[i, last]
        st[i, q, 0] = st[i, last, 0]
        st[i, q, 1] = st[i, last, 1]
        st[i, q, 2] = st[i, last, 2]
        ev[i, q] = ev[i, last]
        pk[i, q] = pk[i, last]
        ds[i, q] = ds[i, last]
        tch[i, q] = tch[i, last]
        tch[i, last] = wp.uint8(0)
        ev[i, last] = wp.int64(-1)
        n[i] = last


@wp.func
def close_untouched_g(keys: wp.array2d(dtype=wp.int32), n: wp.array(dtype=wp.int32), st: F64_3D,
                      ev: wp.array2d(dtype=wp.int64), pk: F64_2D, ds: F64_2D,
                      tch: wp.array2d(dtype=wp.uint8), i: int, evf: F64_3D, t: f64):
    """The same for the geometry contacts (keys are int32)."""
    q = int(0)
    while q < n[i]:
        if tch[i, q] == wp.uint8(1):
            tch[i, q] = wp.uint8(0)
            q = q + 1
            continue
        if ev[i, q] >= wp.int64(0):
            close_event(evf, ev[i, q], t, pk[i, q], ds[i, q])
        last = n[i] - 1
        keys[i, q] = keys[i, last]
        st[i, q, 0] = st[i, last, 0]
        st[i, q, 1] = st[i, last, 1]
        st[i, q, 2] = st[i, last, 2]
        ev[i, q] = ev[i, last]
        pk[i, q] = pk[i, last]
        ds[i, q] = ds[i, last]
        tch[i, q] = tch[i, last]
        tch[i, last] = wp.uint8(0)
        ev[i, last] = wp.int64(-1)
        n[i] = last


# --------------------------------------------------------------------------- force pass
@wp.kernel
def force_k(ctl: wp.array(dtype=wp.int32), t: f64, dt: f64, nch: int,
            pos: F64_2D, vel: F64_2D, omg: F64_2D, rad: wp.array(dtype=f64),
            mass: wp.array(dtype=f64), invm: wp.array(dtype=f64), invi: wp.array(dtype=f64),
            mat: wp.array(dtype=wp.int32), pid: wp.array(dtype=wp.int64), frc: F64_2D, trq: F64_2D,
            kind: wp.array(dtype=wp.uint8), own_idx: wp.array(dtype=wp.uint32),
            nb_start: wp.array(dtype=wp.int64), nb_j: wp.array(dtype=wp.int32),
            nb_sh: wp.array2d(dtype=wp.int8), rv_pos: wp.array(dtype=wp.int64), stamp: wp.int64,
            pc: wp.array(dtype=wp.int64), shs: wp.array(dtype=wp.int64), pf: F64_2D, pt: F64_2D,
            box_len: wp.array(dtype=f64), gc_start: wp.array(dtype=wp.int64),
            gc_g: wp.array(dtype=wp.int32), gcur: F64_2D, grot: F64_2D,
            gkind: wp.array(dtype=wp.int32), gmat: wp.array(dtype=wp.int32), ptab: F64_3D,
            gravity: wp.array(dtype=f64),
            h_pid: wp.array2d(dtype=wp.int64), h_st: F64_3D, h_ev: wp.array2d(dtype=wp.int64),
            h_pk: F64_2D, h_ds: F64_2D, h_n: wp.array(dtype=wp.int32),
            h_tch: wp.array2d(dtype=wp.uint8),
            g_gid: wp.array2d(dtype=wp.int32), g_st: F64_3D, g_ev: wp.array2d(dtype=wp.int64),
            g_pk: F64_2D, g_ds: F64_2D, g_n: wp.array(dtype=wp.int32),
            g_tch: wp.array2d(dtype=wp.uint8),
            evf: F64_3D, evi: wp.array3d(dtype=wp.int64), evn: wp.array(dtype=wp.int64),
            diag: F64_2D):
    """Forces, torques, history and events of one owner particle (``kernels._force_chunk``)."""
    qo = wp.tid()
    if ctl[0] >= 0:
        return
    n = pos.shape[0]
    i = int(own_idx[qo])
    c = chunk_of(i, n, nch)
    smax = h_pid.shape[1]
    sgmax = g_gid.shape[1]
    lx = box_len[0]
    ly = box_len[1]
    lz = box_len[2]
    ovmax = f64(0.0)
    ki = int(kind[i])
    hit = bool(False)
    fx = f64(0.0)
    fy = f64(0.0)
    fz = f64(0.0)
    tx = f64(0.0)
    ty = f64(0.0)
    tz = f64(0.0)
    ri = rad[i]
    xi = pos[i, 0]
    yi = pos[i, 1]
    zi = pos[i, 2]
    k0 = int(nb_start[i])
    k1 = k0
    if (ki & C_OWN) != 0:
        k1 = int(nb_start[i + 1])
    wrap = (ki & C_WRAP) != 0
    # ---- particle-particle: i owns the pairs of its half-list row
    for k in range(k0, k1):
        j = int(nb_j[k])
        rj = rad[j]
        rs = ri + rj
        ox = f64(0.0)
        oy = f64(0.0)
        oz = f64(0.0)
        if wrap:
            ox = f64(nb_sh[k, 0]) * lx
            oy = f64(nb_sh[k, 1]) * ly
            oz = f64(nb_sh[k, 2]) * lz
        dx = pos[j, 0] - xi + ox
        dy = pos[j, 1] - yi + oy
        dz = pos[j, 2] - zi + oz
        d2 = dx * dx + dy * dy + dz * dz
        if d2 >= rs * rs or d2 == ZERO:
            continue
        if not hit:
            hit = True
            mi0 = mass[i]
            fx = mi0 * gravity[0]
            fy = mi0 * gravity[1]
            fz = mi0 * gravity[2]
        idj = pid[j]
        d = wp.sqrt(d2)
        s = rs - d
        inv_d = ONE / d
        nx = dx * inv_d
        ny = dy * inv_d
        nz = dz * inv_d
        la = ri - HALF * s
        lb = rj - HALF * s
        wx = la * omg[i, 0] + lb * omg[j, 0]
        wy = la * omg[i, 1] + lb * omg[j, 1]
        wz = la * omg[i, 2] + lb * omg[j, 2]
        vx = vel[i, 0] - vel[j, 0] + (wy * nz - wz * ny)
        vy = vel[i, 1] - vel[j, 1] + (wz * nx - wx * nz)
        vz = vel[i, 2] - vel[j, 2] + (wx * ny - wy * nx)
        slot = int(-1)
        new = bool(False)
        hn = h_n[i]
        for q in range(hn):
            if h_pid[i, q] == idj:
                slot = q
                break
        if slot < 0:
            new = True
            if hn < smax:
                slot = hn
                h_n[i] = hn + 1
                h_pid[i, slot] = idj
                h_st[i, slot, 0] = ZERO
                h_st[i, slot, 1] = ZERO
                h_st[i, slot, 2] = ZERO
                h_ev[i, slot] = wp.int64(-1)
                h_pk[i, slot] = ZERO
                h_ds[i, slot] = ZERO
        sx = f64(0.0)
        sy = f64(0.0)
        sz = f64(0.0)
        if slot < 0:
            wp.atomic_add(diag, c, C_D_HOVF, ONE)
        else:
            sx = h_st[i, slot, 0]
            sy = h_st[i, slot, 1]
            sz = h_st[i, slot, 2]
        ma = mat[i]
        mb = mat[j]
        rstar = ri * rj / rs
        mstar = ONE / (invm[i] + invm[j])
        cfx, cfy, cfz, nsx, nsy, nsz, fn = contact_law(
            s, nx, ny, nz, vx, vy, vz, rstar, mstar, ptab[ma, mb, 0], ptab[ma, mb, 1],
            ptab[ma, mb, 2], ptab[ma, mb, 3], ptab[ma, mb, 4], dt, sx, sy, sz)
        fx = fx + cfx
        fy = fy + cfy
        fz = fz + cfz
        cx_ = ny * cfz - nz * cfy
        cy_ = nz * cfx - nx * cfz
        cz_ = nx * cfy - ny * cfx
        tx = tx + la * cx_
        ty = ty + la * cy_
        tz = tz + la * cz_
        rq = int(rv_pos[k])
        pc[rq] = stamp
        shs[j] = stamp
        pf[rq, 0] = cfx
        pf[rq, 1] = cfy
        pf[rq, 2] = cfz
        pt[rq, 0] = lb * cx_
        pt[rq, 1] = lb * cy_
        pt[rq, 2] = lb * cz_
        rmin = wp.min(ri, rj)
        if s > ovmax * rmin:
            ovmax = s / rmin
        if slot >= 0:
            h_st[i, slot, 0] = nsx
            h_st[i, slot, 1] = nsy
            h_st[i, slot, 2] = nsz
            h_tch[i, slot] = wp.uint8(1)
            if new:
                vn = vx * nx + vy * ny + vz * nz
                vtx = vx - vn * nx
                vty = vy - vn * ny
                vtz = vz - vn * nz
                h_ev[i, slot] = record_onset(
                    evf, evi, evn, c, t, pid[i], 0, idj, ri, rj,
                    xi + nx * la, yi + ny * la, zi + nz * la,
                    vn, wp.sqrt(vtx * vtx + vty * vty + vtz * vtz), diag)
            if s > h_pk[i, slot]:
                h_pk[i, slot] = s
            h_ds[i, slot] = h_ds[i, slot] - step_work(
                cfx, cfy, cfz, fn, nx, ny, nz, vx, vy, vz, invm[i] + invm[j],
                la * la * invi[i] + lb * lb * invi[j], dt)
    # ---- particle-geometry (a key is a primitive or one of its periodic images)
    g0 = int(0)
    g1 = int(0)
    if (ki & C_GEO) != 0:
        g0 = int(gc_start[i])
        g1 = int(gc_start[i + 1])
    for k in range(g0, g1):
        key = int(gc_g[k])
        g = key // C_STRIDE
        code = key % C_STRIDE
        xg = xi
        yg = yi
        zg = zi
        if code != 0:
            xg = xi + f64(image_shift(code, 0)) * lx
            yg = yi + f64(image_shift(code, 1)) * ly
            zg = zi + f64(image_shift(code, 2)) * lz
        ok, s, nx, ny, nz, cx, cy, cz = geom_contact(gkind[g], gcur, g, xg, yg, zg, ri)
        if not ok:
            continue
        mi = mass[i]
        if not hit:
            hit = True
            fx = mi * gravity[0]
            fy = mi * gravity[1]
            fz = mi * gravity[2]
        li = ri - s
        wvx = f64(0.0)
        wvy = f64(0.0)
        wvz = f64(0.0)
        if grot[g, 7] > ZERO:
            om = grot[g, 6]
            ax = om * grot[g, 3]
            ay = om * grot[g, 4]
            az = om * grot[g, 5]
            px = cx - grot[g, 0]
            py = cy - grot[g, 1]
            pz = cz - grot[g, 2]
            wvx = ay * pz - az * py
            wvy = az * px - ax * pz
            wvz = ax * py - ay * px
        vx = vel[i, 0] + li * (omg[i, 1] * nz - omg[i, 2] * ny) - wvx
        vy = vel[i, 1] + li * (omg[i, 2] * nx - omg[i, 0] * nz) - wvy
        vz = vel[i, 2] + li * (omg[i, 0] * ny - omg[i, 1] * nx) - wvz
        slot = int(-1)
        new = bool(False)
        hn = g_n[i]
        for q in range(hn):
            if int(g_gid[i, q]) == key:
                slot = q
                break
        if slot < 0:
            new = True
            if hn < sgmax:
                slot = hn
                g_n[i] = hn + 1
                g_gid[i, slot] = wp.int32(key)
                g_st[i, slot, 0] = ZERO
                g_st[i, slot, 1] = ZERO
                g_st[i, slot, 2] = ZERO
                g_ev[i, slot] = wp.int64(-1)
                g_pk[i, slot] = ZERO
                g_ds[i, slot] = ZERO
        sx = f64(0.0)
        sy = f64(0.0)
        sz = f64(0.0)
        if slot < 0:
            wp.atomic_add(diag, c, C_D_HOVF, ONE)
        else:
            sx = g_st[i, slot, 0]
            sy = g_st[i, slot, 1]
            sz = g_st[i, slot, 2]
        ma = mat[i]
        mb = gmat[g]
        cfx, cfy, cfz, nsx, nsy, nsz, fn = contact_law(
            s, nx, ny, nz, vx, vy, vz, ri, mi, ptab[ma, mb, 0], ptab[ma, mb, 1],
            ptab[ma, mb, 2], ptab[ma, mb, 3], ptab[ma, mb, 4], dt, sx, sy, sz)
        fx = fx + cfx
        fy = fy + cfy
        fz = fz + cfz
        tx = tx + li * (ny * cfz - nz * cfy)
        ty = ty + li * (nz * cfx - nx * cfz)
        tz = tz + li * (nx * cfy - ny * cfx)
        if s > ovmax * ri:
            ovmax = s / ri
        if slot >= 0:
            g_st[i, slot, 0] = nsx
            g_st[i, slot, 1] = nsy
            g_st[i, slot, 2] = nsz
            g_tch[i, slot] = wp.uint8(1)
            if new:
                vn = vx * nx + vy * ny + vz * nz
                vtx = vx - vn * nx
                vty = vy - vn * ny
                vtz = vz - vn * nz
                g_ev[i, slot] = record_onset(
                    evf, evi, evn, c, t, pid[i], 1, wp.int64(g), ri, f64(wp.nan),
                    cx + xi - xg, cy + yi - yg, cz + zi - zg, vn,
                    wp.sqrt(vtx * vtx + vty * vty + vtz * vtz), diag)
            if s > g_pk[i, slot]:
                g_pk[i, slot] = s
            g_ds[i, slot] = g_ds[i, slot] - step_work(
                cfx, cfy, cfz, fn, nx, ny, nz, vx, vy, vz, invm[i], li * li * invi[i], dt)
    # ---- end of contacts: the particle's slots not touched this step
    if (ki & C_OWN) != 0 and h_n[i] > 0:
        close_untouched_h(h_pid, h_n, h_st, h_ev, h_pk, h_ds, h_tch, i, evf, t)
    if (ki & C_GEO) != 0 and g_n[i] > 0:
        close_untouched_g(g_gid, g_n, g_st, g_ev, g_pk, g_ds, g_tch, i, evf, t)
    if hit:
        frc[i, 0] = fx
        frc[i, 1] = fy
        frc[i, 2] = fz
        trq[i, 0] = tx
        trq[i, 1] = ty
        trq[i, 2] = tz
        if (ki & C_HIT) == 0:
            kind[i] = wp.uint8(ki | C_HIT)
    elif (ki & C_HIT) != 0:
        kind[i] = wp.uint8(ki & ~C_HIT)
    if ovmax > diag[c, C_D_OVER]:
        wp.atomic_max(diag, c, C_D_OVER, ovmax)


# --------------------------------------------------------------------------- integration
@wp.kernel
def integrate_k(ctl: wp.array(dtype=wp.int32), t_new: f64, dt: f64, no_weight: int, nch: int,
                pos: F64_2D, vel: F64_2D, omg: F64_2D, frc: F64_2D, trq: F64_2D,
                kind: wp.array(dtype=wp.uint8), mass: wp.array(dtype=f64),
                gravity: wp.array(dtype=f64), rv_start: wp.array(dtype=wp.int64), stamp: wp.int64,
                pc: wp.array(dtype=wp.int64), shs: wp.array(dtype=wp.int64), pf: F64_2D,
                pt: F64_2D, invm: wp.array(dtype=f64), invi: wp.array(dtype=f64),
                flag: wp.array(dtype=wp.int32), flag_t: wp.array(dtype=f64),
                lo: wp.array(dtype=f64), hi: wp.array(dtype=f64),
                periodic: wp.array(dtype=wp.int8), sinks: F64_2D, diag: F64_2D,
                red_f: wp.array(dtype=f64), red_i: wp.array(dtype=wp.int32)):
    """Symplectic Euler for particle ``i``, then sinks and flags (``kernels._integrate_chunk``)."""
    i = wp.tid()
    if ctl[0] >= 0:
        return
    ki = int(kind[i])
    stamped = shs[i] == stamp
    hitk = (ki & C_HIT) != 0
    if not (hitk or stamped):
        if no_weight == 0:
            mi = mass[i]
            f0 = mi * gravity[0]
            f1 = mi * gravity[1]
            f2 = mi * gravity[2]
            if f0 != ZERO or f1 != ZERO or f2 != ZERO:
                im = invm[i]
                vel[i, 0] = vel[i, 0] + f0 * im * dt
                vel[i, 1] = vel[i, 1] + f1 * im * dt
                vel[i, 2] = vel[i, 2] + f2 * im * dt
    else:
        f0 = f64(0.0)
        f1 = f64(0.0)
        f2 = f64(0.0)
        t0 = f64(0.0)
        t1 = f64(0.0)
        t2 = f64(0.0)
        if hitk:
            f0 = frc[i, 0]
            f1 = frc[i, 1]
            f2 = frc[i, 2]
            t0 = trq[i, 0]
            t1 = trq[i, 1]
            t2 = trq[i, 2]
        elif no_weight == 0:
            mi = mass[i]
            f0 = mi * gravity[0]
            f1 = mi * gravity[1]
            f2 = mi * gravity[2]
        got = bool(False)
        if stamped:
            for q in range(int(rv_start[i]), int(rv_start[i + 1])):
                if pc[q] == stamp:
                    got = True
                    f0 = f0 - pf[q, 0]
                    f1 = f1 - pf[q, 1]
                    f2 = f2 - pf[q, 2]
                    t0 = t0 + pt[q, 0]
                    t1 = t1 + pt[q, 1]
                    t2 = t2 + pt[q, 2]
        if got:
            frc[i, 0] = f0
            frc[i, 1] = f1
            frc[i, 2] = f2
            trq[i, 0] = t0
            trq[i, 1] = t1
            trq[i, 2] = t2
        if f0 != ZERO or f1 != ZERO or f2 != ZERO:
            im = invm[i]
            vel[i, 0] = vel[i, 0] + f0 * im * dt
            vel[i, 1] = vel[i, 1] + f1 * im * dt
            vel[i, 2] = vel[i, 2] + f2 * im * dt
        if t0 != ZERO or t1 != ZERO or t2 != ZERO:
            ii = invi[i]
            omg[i, 0] = omg[i, 0] + t0 * ii * dt
            omg[i, 1] = omg[i, 1] + t1 * ii * dt
            omg[i, 2] = omg[i, 2] + t2 * ii * dt
    # move
    v0 = vel[i, 0]
    v1 = vel[i, 1]
    v2 = vel[i, 2]
    x = pos[i, 0] + v0 * dt
    y = pos[i, 1] + v1 * dt
    z = pos[i, 2] + v2 * dt
    pos[i, 0] = x
    pos[i, 1] = y
    pos[i, 2] = z
    sp = v0 * v0 + v1 * v1 + v2 * v2
    if sp > red_f[0]:  # a plain read first: few atomics
        wp.atomic_max(red_f, 0, sp)
    c = chunk_of(i, pos.shape[0], nch)
    if sp > diag[c, C_D_SPEED2]:
        wp.atomic_max(diag, c, C_D_SPEED2, sp)
    if not (wp.isfinite(x + y + z) and wp.isfinite(sp)):
        flag[i] = C_F_NONFINITE
        flag_t[i] = t_new
        wp.atomic_add(red_i, 0, 1)
        return
    for k in range(sinks.shape[0]):
        if (x >= sinks[k, 0] and x <= sinks[k, 3] and y >= sinks[k, 1]
                and y <= sinks[k, 4] and z >= sinks[k, 2] and z <= sinks[k, 5]):
            flag[i] = 2 + k
            flag_t[i] = t_new
            wp.atomic_add(red_i, 0, 1)
            return
    if ((periodic[0] == wp.int8(0) and (x < lo[0] or x > hi[0]))
            or (periodic[1] == wp.int8(0) and (y < lo[1] or y > hi[1]))
            or (periodic[2] == wp.int8(0) and (z < lo[2] or z > hi[2]))):
        flag[i] = C_F_LOST
        flag_t[i] = t_new
        wp.atomic_add(red_i, 0, 1)


@wp.kernel
def control_k(ctl: wp.array(dtype=wp.int32), dt: f64, half_skin: f64, ev_limit: wp.int64,
              disp: wp.array(dtype=f64), evn: wp.array(dtype=wp.int64),
              red_f: wp.array(dtype=f64), red_i: wp.array(dtype=wp.int32)):
    """End of a step (one thread): displacement bound, the reason to stop (``kernels.advance``)."""
    if ctl[0] >= 0:
        return
    disp[0] = disp[0] + wp.sqrt(red_f[0]) * dt
    ctl[1] = ctl[1] + 1
    if red_i[0] > 0:
        ctl[0] = C_R_FLAGGED
    elif disp[0] > half_skin:
        ctl[0] = C_R_REBUILD
    else:
        for c in range(evn.shape[0]):
            if evn[c] > ev_limit:
                ctl[0] = C_R_EVFULL
    red_f[0] = ZERO
    red_i[0] = 0


# --------------------------------------------------------------------------- driver
#: argument names of :func:`msmill.dem.kernels.advance`, in order
ADVANCE_ARGS = (
    "t0", "dt", "nsteps", "skin", "disp", "pos", "vel", "omg", "rad", "mass", "invm", "invi", "mat",
    "pid", "frc", "trq", "kind", "own_idx", "own_start", "act_idx", "act_start", "flag", "flag_t",
    "nb_start", "nb_j", "nb_sh", "rv_start", "rv_pos", "stamp0", "pc", "shs", "pf", "pt",
    "box_len", "gc_start", "gc_g", "gref", "gcur", "grot", "gkind", "gmat", "ptab", "gravity", "lo",
    "hi", "periodic", "sinks", "h_pid", "h_st", "h_ev", "h_pk", "h_ds", "h_n", "h_tch", "g_gid",
    "g_st", "g_ev", "g_pk", "g_ds", "g_n", "g_tch", "evf", "evi", "evn", "diag", "parallel")
_SCALARS = {"t0", "dt", "nsteps", "skin", "stamp0", "parallel"}
#: arrays the step writes (copied back from a CUDA device after a call)
_WRITTEN = {"disp", "pos", "vel", "omg", "frc", "trq", "kind", "flag", "flag_t", "pc", "shs", "pf",
            "pt", "gcur", "h_pid", "h_st", "h_ev", "h_pk", "h_ds", "h_n", "h_tch", "g_gid", "g_st",
            "g_ev", "g_pk", "g_ds", "g_n", "g_tch", "evf", "evi", "evn", "diag"}
_DTYPES = {np.dtype(np.float64): wp.float64, np.dtype(np.int64): wp.int64,
           np.dtype(np.int32): wp.int32, np.dtype(np.uint32): wp.uint32,
           np.dtype(np.uint8): wp.uint8, np.dtype(np.int8): wp.int8}
#: steps launched between two reads of the stop flag on a CUDA device (CPU: every step)
CUDA_STEPS_PER_CHECK = 16


def _weight_free(gravity: np.ndarray) -> bool:
    """Every gravity component is +0.0 (as ``kernels._weight_free``)."""
    return all(g == 0.0 and math.copysign(1.0, g) > 0.0 for g in gravity)


class WarpStepper:
    """Runs the engine's step loop with the Warp kernels on one Warp device.

    Parameters
    ----------
    device : str
        ``"cpu"`` (Warp's LLVM-compiled CPU kernels) or ``"cuda"`` / ``"cuda:N"``.
    share : bool, optional
        Work on views of the engine's arrays (default on the CPU device) instead of copies made
        at each call and written back after it (a GPU's way; ``False`` on the CPU tests it there).
    steps_per_check : int, optional
        Steps launched between two reads of the stop flag (default: 1 when sharing, else
        :data:`CUDA_STEPS_PER_CHECK`); steps launched after a stop do nothing.
    """

    def __init__(self, device: str, *, share: bool | None = None,
                 steps_per_check: int | None = None) -> None:
        self.device = device
        self._share = (device == "cpu") if share is None else bool(share)
        if self._share and device != "cpu":
            raise ValueError("share=True needs Warp's CPU device")
        self._every = steps_per_check or (1 if self._share else CUDA_STEPS_PER_CHECK)
        self.compile_s = self._load()

    def _load(self) -> float:
        """Compile (or load from Warp's kernel cache, ~/.cache/warp) the module; seconds taken."""
        import time

        warp_status()  # initialises Warp quietly
        tic = time.perf_counter()
        wp.load_module(device=self.device)
        return time.perf_counter() - tic

    def _array(self, a: np.ndarray):
        """A Warp view (CPU device: the same memory) or device copy of a numpy array."""
        dtype = _DTYPES[a.dtype]
        if self._share:
            return wp.array(a, dtype=dtype, device="cpu", copy=False)
        return wp.array(np.ascontiguousarray(a), dtype=dtype, device=self.device)

    def advance(self, *args):
        """Same arguments and result as :func:`msmill.dem.kernels.advance` (``parallel`` is ignored)."""
        a = dict(zip(ADVANCE_ARGS, args, strict=True))
        if int(a["nsteps"]) <= 0:
            return 0, K.R_DONE
        arr = {k: self._array(v) for k, v in a.items() if k not in _SCALARS}
        steps, reason = self.run(arr, float(a["t0"]), float(a["dt"]), int(a["nsteps"]),
                                 float(a["skin"]), int(a["stamp0"]), _weight_free(a["gravity"]))
        self._copy_back(a, arr)
        return steps, reason

    def run(self, arr: dict, t0: float, dt: float, nsteps: int, skin: float, stamp0: int,
            no_weight: bool) -> tuple[int, int]:
        """Up to ``nsteps`` steps on Warp arrays already on the device; ``(steps, reason)``.

        Parameters
        ----------
        arr : dict of str to warp.array
            The array arguments of :func:`msmill.dem.kernels.advance`, by name, on ``self.device``.
        t0, dt, skin : float
            Time of the first step (s), the step (s) and the Verlet skin (m).
        nsteps, stamp0 : int
            Most steps to run; stamp of the first (``kernels.advance``).
        no_weight : bool
            Every gravity component is +0.0 (``kernels._weight_free``).
        """
        if nsteps <= 0:
            return 0, K.R_DONE
        dev = self.device
        ctl = wp.array(np.array([-1, 0], np.int32), dtype=wp.int32, device=dev)
        red_f = wp.zeros(1, dtype=wp.float64, device=dev)
        red_i = wp.zeros(1, dtype=wp.int32, device=dev)
        n = arr["pos"].shape[0]
        nch = arr["diag"].shape[0]
        ng = arr["gref"].shape[0]
        n_own = arr["own_idx"].shape[0]
        geom = wp.launch(update_geometry_k, dim=max(ng, 1), device=dev, record_cmd=True,
                         inputs=[ctl, arr["gref"], arr["grot"], arr["gkind"], 0.0, arr["gcur"]])
        force = wp.launch(force_k, dim=max(n_own, 1), device=dev, record_cmd=True, inputs=[
            ctl, 0.0, dt, nch, *(arr[k] for k in (
                "pos", "vel", "omg", "rad", "mass", "invm", "invi", "mat", "pid", "frc", "trq",
                "kind", "own_idx", "nb_start", "nb_j", "nb_sh", "rv_pos")), 0,
            *(arr[k] for k in (
                "pc", "shs", "pf", "pt", "box_len", "gc_start", "gc_g", "gcur", "grot", "gkind",
                "gmat", "ptab", "gravity", "h_pid", "h_st", "h_ev", "h_pk", "h_ds", "h_n", "h_tch",
                "g_gid", "g_st", "g_ev", "g_pk", "g_ds", "g_n", "g_tch", "evf", "evi", "evn",
                "diag"))])
        integ = wp.launch(integrate_k, dim=max(n, 1), device=dev, record_cmd=True, inputs=[
            ctl, 0.0, dt, int(no_weight), nch,
            *(arr[k] for k in ("pos", "vel", "omg", "frc", "trq", "kind", "mass", "gravity",
                               "rv_start")), 0,
            *(arr[k] for k in ("pc", "shs", "pf", "pt", "invm", "invi", "flag", "flag_t", "lo",
                               "hi", "periodic", "sinks", "diag")), red_f, red_i])
        control = wp.launch(control_k, dim=1, device=dev, record_cmd=True, inputs=[
            ctl, dt, 0.5 * skin, arr["evf"].shape[1] // 2, arr["disp"], arr["evn"],
            red_f, red_i])
        every = self._every
        for step in range(nsteps):
            t = t0 + step * dt
            stamp = stamp0 + step
            if ng > 0:
                geom.set_param_at_index(4, t)
                geom.launch()
            if n_own > 0:
                force.set_param_at_index(1, t)
                force.set_param_at_index(21, stamp)
                force.launch()
            if n > 0:
                integ.set_param_at_index(1, t0 + (step + 1) * dt)
                integ.set_param_at_index(14, stamp)
                integ.launch()
            control.launch()
            if ((step + 1) % every == 0 or step == nsteps - 1) and ctl.numpy()[0] >= 0:
                break
        state = ctl.numpy()
        steps = int(state[1])
        return steps, (int(state[0]) if state[0] >= 0 else K.R_DONE)

    def _copy_back(self, a: dict, arr: dict) -> None:
        """Bring the arrays the step wrote back from a CUDA device (on the CPU they are shared); clamp ``evn``."""
        if not self._share:
            wp.synchronize_device(self.device)
            for k in _WRITTEN:
                if a[k].size:
                    a[k][...] = arr[k].numpy()
        # rows past a chunk's capacity were counted, not written (kernels._record_onset)
        np.minimum(a["evn"], a["evf"].shape[1], out=a["evn"])
