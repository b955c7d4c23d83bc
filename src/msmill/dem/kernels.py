"""All numba kernels of the DEM engine.

Execution model (see docs/dem.md):

* :func:`advance` runs up to ``nsteps`` time steps in compiled code; each step
  updates the pose of rotating geometry, runs one force pass (one contact loop
  over the full Verlet neighbour list plus the particle's geometry candidates,
  parallel over particle chunks) and one integration pass (symplectic Euler,
  paper Eqs. 2-3). It returns early when a rebuild is due (max displacement
  since the last build, bounded by the sum over steps of the largest speed
  times dt, exceeds skin/2), a particle was flagged (sink, lost,
  non-finite) or an event buffer is half full.
* The Verlet list is a *half* list keyed by particle id: row ``i`` holds the
  partners with a larger id, so every pair is evaluated once, by its owner
  (the lower id), which accumulates its own force and stores the partner's
  share (force, torque, contact flag) per list entry; the integration pass
  gathers those shares through the reverse list (no write races, exact
  action-reaction).
* Contact history lives in the owner's per-particle slots keyed by partner
  id (particle id or geometry id), so it moves with the particle through
  sorting, insertion and deletion and the owner never changes.
* Events are written at contact onset by the owner (lower id, or the particle
  for geometry) into the buffer of the chunk that processes it; the row
  reference stored in the history slot is ``row * nchunks + chunk``; buffers
  are laid out ``(chunk, row, column)`` so threads never share cache lines.
"""

from __future__ import annotations

import numpy as np
from numba import njit, prange

from msmill.dem.threads import prefer_openmp

prefer_openmp()  # before any parallel kernel runs (see msmill.dem.threads)

# geometry kinds (mirrors geometry.py)
PLANE, BOX, CYL = 0, 1, 2

# float event columns
EV_T, EV_R, EV_PR, EV_X, EV_Y, EV_Z, EV_VN, EV_VT, EV_END, EV_PEAK, EV_DISS = range(11)
N_EVF = 11
# int event columns
EVI_PID, EVI_KIND, EVI_PARTNER = range(3)
N_EVI = 3

# per-chunk diagnostics
D_DISP2, D_OVER, D_SPEED2, D_HOVF, D_EVOVF, D_FLAGGED = range(6)
N_DIAG = 6

# per-particle work flags of the step passes (particle_kinds): owns half-list entries or
# particle history slots, is the partner of entries, has geometry candidates or slots;
# K_HIT is set by the force pass for this step when the particle's own contacts gave it a force;
# K_WRAP: some of its half-list entries are periodic images (a shift other than 0, 0, 0)
K_OWN, K_REV, K_GEO, K_HIT, K_WRAP = 1, 2, 4, 8, 16

# advance() return reasons
R_DONE, R_REBUILD, R_FLAGGED, R_EVFULL = 0, 1, 2, 3

# particle flags
F_OK, F_LOST, F_NONFINITE = 0, 1, -1  # sinks are 2 + sink index


@njit(cache=True, fastmath=False)
def chunk_bounds(n: int, nch: int, c: int) -> tuple[int, int]:
    """Half-open particle range of chunk ``c``."""
    return (c * n) // nch, ((c + 1) * n) // nch


# --------------------------------------------------------------------------- geometry
@njit(cache=True, fastmath=False, inline='always')
def _image_shift(code, a):
    """Shift (in box lengths, -8..7) along axis ``a`` of a geometry image code."""
    v = (code >> (4 * (2 - a))) & 15
    return v - 16 if v >= 8 else v


@njit(cache=True, fastmath=False, inline='always')
def _image_code(sx, sy, sz):
    """Code of the periodic image shift ``(sx, sy, sz)``; 0 for the primitive itself."""
    return ((sx & 15) << 8) | ((sy & 15) << 4) | (sz & 15)


#: geometry keys are ``g * KEY_STRIDE + image code`` (12 bits of image shifts)
KEY_STRIDE = 4096


@njit(cache=True, fastmath=False, inline='always')
def _geom_key_frame(key, x, y, z, lx, ly, lz):
    """Decode a geometry candidate key ``g * KEY_STRIDE + code``.

    Returns the primitive ``g`` and the particle position moved into the
    frame of that primitive (particle position + shift x box length), so that
    a particle near a periodic boundary meets the periodic image of a
    primitive on the other side.
    """
    g = key // KEY_STRIDE
    code = key % KEY_STRIDE
    if code == 0:
        return g, x, y, z
    return (g, x + _image_shift(code, 0) * lx, y + _image_shift(code, 1) * ly,
            z + _image_shift(code, 2) * lz)


@njit(cache=True, fastmath=False)
def update_geometry(gref, grot, gkind, t, gcur):
    """Pose of every primitive at time ``t`` (rotating ones turned by omega t)."""
    for g in range(gref.shape[0]):
        for k in range(gref.shape[1]):
            gcur[g, k] = gref[g, k]
        if grot[g, 7] <= 0.0:
            continue
        th = grot[g, 6] * t
        ux, uy, uz = grot[g, 3], grot[g, 4], grot[g, 5]
        c = np.cos(th)
        s = np.sin(th)
        oc = 1.0 - c
        q00 = c + ux * ux * oc
        q01 = ux * uy * oc - uz * s
        q02 = ux * uz * oc + uy * s
        q10 = uy * ux * oc + uz * s
        q11 = c + uy * uy * oc
        q12 = uy * uz * oc - ux * s
        q20 = uz * ux * oc - uy * s
        q21 = uz * uy * oc + ux * s
        q22 = c + uz * uz * oc
        # first field is always a point
        px = gref[g, 0] - grot[g, 0]
        py = gref[g, 1] - grot[g, 1]
        pz = gref[g, 2] - grot[g, 2]
        gcur[g, 0] = grot[g, 0] + q00 * px + q01 * py + q02 * pz
        gcur[g, 1] = grot[g, 1] + q10 * px + q11 * py + q12 * pz
        gcur[g, 2] = grot[g, 2] + q20 * px + q21 * py + q22 * pz
        nvec = 3 if gkind[g] == BOX else 1
        for m in range(nvec):
            o = 3 + 3 * m
            dx, dy, dz = gref[g, o], gref[g, o + 1], gref[g, o + 2]
            gcur[g, o] = q00 * dx + q01 * dy + q02 * dz
            gcur[g, o + 1] = q10 * dx + q11 * dy + q12 * dz
            gcur[g, o + 2] = q20 * dx + q21 * dy + q22 * dz


@njit(cache=True, fastmath=False)
def geom_contact(kind, gall, g, x, y, z, r):
    """Overlap with one primitive.

    Returns ``(ok, s, nx, ny, nz, cx, cy, cz)``: overlap ``s`` (m), unit normal
    from the particle centre towards the wall and the contact point on the
    wall surface.
    """
    if kind == PLANE:
        d = (x - gall[g, 0]) * gall[g, 3] + (y - gall[g, 1]) * gall[g, 4] + (z - gall[g, 2]) * gall[g, 5]
        if d >= r or d <= -r:
            return False, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0
        return (True, r - d, -gall[g, 3], -gall[g, 4], -gall[g, 5],
                x - d * gall[g, 3], y - d * gall[g, 4], z - d * gall[g, 5])
    if kind == BOX:
        rx = x - gall[g, 0]
        ry = y - gall[g, 1]
        rz = z - gall[g, 2]
        q0 = rx * gall[g, 3] + ry * gall[g, 4] + rz * gall[g, 5]
        q1 = rx * gall[g, 6] + ry * gall[g, 7] + rz * gall[g, 8]
        q2 = rx * gall[g, 9] + ry * gall[g, 10] + rz * gall[g, 11]
        h0, h1, h2 = gall[g, 12], gall[g, 13], gall[g, 14]
        p0 = min(max(q0, -h0), h0)
        p1 = min(max(q1, -h1), h1)
        p2 = min(max(q2, -h2), h2)
        e0 = q0 - p0
        e1 = q1 - p1
        e2 = q2 - p2
        dist2 = e0 * e0 + e1 * e1 + e2 * e2
        if dist2 > 0.0:
            if dist2 >= r * r:
                return False, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0
            dist = np.sqrt(dist2)
            l0 = -e0 / dist
            l1 = -e1 / dist
            l2 = -e2 / dist
            s = r - dist
        else:  # centre inside: push out through the nearest face
            a0 = h0 - abs(q0)
            a1 = h1 - abs(q1)
            a2 = h2 - abs(q2)
            l0 = 0.0
            l1 = 0.0
            l2 = 0.0
            if a0 <= a1 and a0 <= a2:
                sg = 1.0 if q0 >= 0 else -1.0
                l0 = -sg
                p0 = sg * h0
                s = r + a0
            elif a1 <= a2:
                sg = 1.0 if q1 >= 0 else -1.0
                l1 = -sg
                p1 = sg * h1
                s = r + a1
            else:
                sg = 1.0 if q2 >= 0 else -1.0
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
    ux, uy, uz = gall[g, 3], gall[g, 4], gall[g, 5]
    ln = gall[g, 6]
    rc = gall[g, 7]
    rx = x - gall[g, 0]
    ry = y - gall[g, 1]
    rz = z - gall[g, 2]
    a = rx * ux + ry * uy + rz * uz
    vx = rx - a * ux
    vy = ry - a * uy
    vz = rz - a * uz
    rho = np.sqrt(vx * vx + vy * vy + vz * vz)
    if gall[g, 8] > 0.5:  # inside a tube (open ends)
        if a < 0.0 or a > ln or rho <= rc - r or rho >= rc + r or rho == 0.0:
            return False, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0
        nx = vx / rho
        ny = vy / rho
        nz = vz / rho
        return (True, rho + r - rc, nx, ny, nz,
                gall[g, 0] + a * ux + rc * nx, gall[g, 1] + a * uy + rc * ny, gall[g, 2] + a * uz + rc * nz)
    # outside a solid capped cylinder
    if rho > 0.0:
        ex = vx / rho
        ey = vy / rho
        ez = vz / rho
    else:
        ex, ey, ez = 0.0, 0.0, 0.0
    if a >= 0.0 and a <= ln and rho <= rc:  # centre inside the solid
        dside = rc - rho
        if dside <= a and dside <= ln - a:
            return (True, r + dside, -ex, -ey, -ez,
                    gall[g, 0] + a * ux + rc * ex, gall[g, 1] + a * uy + rc * ey, gall[g, 2] + a * uz + rc * ez)
        if a <= ln - a:
            return True, r + a, ux, uy, uz, x - a * ux, y - a * uy, z - a * uz
        b = ln - a
        return True, r + b, -ux, -uy, -uz, x + b * ux, y + b * uy, z + b * uz
    ac = min(max(a, 0.0), ln)
    rr = min(rho, rc)
    cx = gall[g, 0] + ac * ux + rr * ex
    cy = gall[g, 1] + ac * uy + rr * ey
    cz = gall[g, 2] + ac * uz + rr * ez
    dx = cx - x
    dy = cy - y
    dz = cz - z
    d2 = dx * dx + dy * dy + dz * dz
    if d2 >= r * r or d2 == 0.0:
        return False, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0
    d = np.sqrt(d2)
    return True, r - d, dx / d, dy / d, dz / d, cx, cy, cz


# --------------------------------------------------------------------------- contact law
@njit(cache=True, fastmath=False, inline='always')
def contact_law(s, nx, ny, nz, vx, vy, vz, rstar, mstar, kfac, etah, etat, mu, strat, dt,
                sx, sy, sz):
    """Paper Eqs. 4-10 for one contact in canonical orientation.

    Inlined into the force pass: as a call it cost ~8 ns per particle-step
    in the dense benchmark gas (0.14 contacts per particle), for ~2 s more
    cold compilation.

    ``n`` points from body a to body b, ``v`` is the velocity of a relative to
    b at the contact point, ``(sx, sy, sz)`` the tangential displacement
    history. Returns the force on a, the new history and ``F_n``.
    """
    vn = vx * nx + vy * ny + vz * nz  # > 0 approaching: ds/dt
    tx = vx - vn * nx
    ty = vy - vn * ny
    tz = vz - vn * nz
    kh = kfac * np.sqrt(rstar)
    ch = 2.0 * etah * np.sqrt(mstar * kh)
    sq = np.sqrt(s)
    fel = kh * s * sq
    cn = ch * np.sqrt(sq)
    # the dashpot acts on the trapezoidal mean of v_n now and v_n' predicted for the end of the step
    # from this contact's own force, v_n' = (v_n (1 - a) - F_el dt/m*)/(1 + a), a = C dt/(2 m*),
    # i.e. F_n = (F_el + C v_n)/(1 + a): it cannot reverse the approach in one step (docs/dem.md)
    a_ = 0.5 * cn * dt / mstar
    fn = (fel + cn * vn) / (1.0 + a_)
    if fn < 0.0:
        fn = 0.0
    fx = -fn * nx
    fy = -fn * ny
    fz = -fn * nz
    stmax = mu * s * strat
    if stmax <= 0.0:
        return fx, fy, fz, 0.0, 0.0, 0.0, fn
    # keep the history in the current tangent plane (rotate, keep its length)
    sn = sx * nx + sy * ny + sz * nz
    if sn != 0.0:
        old2 = sx * sx + sy * sy + sz * sz
        sx -= sn * nx
        sy -= sn * ny
        sz -= sn * nz
        new2 = sx * sx + sy * sy + sz * sz
        if new2 > 0.0:
            sc = np.sqrt(old2 / new2)
            sx *= sc
            sy *= sc
            sz *= sc
    sx += tx * dt
    sy += ty * dt
    sz += tz * dt
    smag = np.sqrt(sx * sx + sy * sy + sz * sz)
    if smag >= stmax:
        sc = stmax / smag
        sx *= sc
        sy *= sc
        sz *= sc
        smag = stmax
        zeta = 0.0
    else:
        zeta = 1.0 - smag / stmax
    if smag > 0.0:
        fe = mu * fn * (1.0 - zeta * np.sqrt(zeta)) / smag
        fx -= fe * sx
        fy -= fe * sy
        fz -= fe * sz
    if zeta > 0.0 and fn > 0.0:
        cd = etat * np.sqrt(6.0 * mu * mstar * fn / stmax) * np.sqrt(np.sqrt(zeta))
        fx -= cd * tx
        fy -= cd * ty
        fz -= cd * tz
    return fx, fy, fz, sx, sy, sz, fn


# --------------------------------------------------------------------------- force pass
@njit(cache=True, fastmath=False, inline='always')
def _record_onset(evf, evi, evn, c, t, owner_pid, kind, partner, r, pr, cx, cy, cz, vn, vt, diag):
    row = evn[c]
    if row >= evf.shape[1]:
        diag[c, D_EVOVF] += 1.0
        return -1
    evn[c] = row + 1
    evf[c, row, EV_T] = t
    evf[c, row, EV_R] = r
    evf[c, row, EV_PR] = pr
    evf[c, row, EV_X] = cx
    evf[c, row, EV_Y] = cy
    evf[c, row, EV_Z] = cz
    evf[c, row, EV_VN] = vn
    evf[c, row, EV_VT] = vt
    evf[c, row, EV_END] = np.nan
    evf[c, row, EV_PEAK] = np.nan
    evf[c, row, EV_DISS] = np.nan
    evi[c, row, EVI_PID] = owner_pid
    evi[c, row, EVI_KIND] = kind
    evi[c, row, EVI_PARTNER] = partner
    return row * evf.shape[0] + c


@njit(cache=True, fastmath=False, inline='always')
def _close_event(evf, ref, t, peak, diss):
    nch = evf.shape[0]
    c = ref % nch
    row = ref // nch
    evf[c, row, EV_END] = t
    evf[c, row, EV_PEAK] = peak
    evf[c, row, EV_DISS] = diss



@njit(cache=True, fastmath=False, inline='always')
def _close_untouched_row(keys, n, st, ev, pk, ds, tch, i, evf, t):
    """End the contacts of particle ``i`` whose slot was not touched this step.

    Their events are closed (peak overlap, dissipated energy) and the slot is
    refilled from the last one; touched slots are reset for the next step.
    Serves particle and geometry partners alike. Called per particle from the
    force pass with the arrays as they are: measured there, the call costs no
    more than the loop written out (numba's reference counting of array
    arguments, docs/dem.md, Performance, did not show at this call site).
    """
    q = 0
    while q < n[i]:
        if tch[i, q] == 1:
            tch[i, q] = 0
            q += 1
            continue
        if ev[i, q] >= 0:
            _close_event(evf, ev[i, q], t, pk[i, q], ds[i, q])
        last = n[i] - 1
        keys[i, q] = keys[i, last]
        st[i, q, 0] = st[i, last, 0]
        st[i, q, 1] = st[i, last, 1]
        st[i, q, 2] = st[i, last, 2]
        ev[i, q] = ev[i, last]
        pk[i, q] = pk[i, last]
        ds[i, q] = ds[i, last]
        tch[i, q] = tch[i, last]
        tch[i, last] = 0
        ev[i, last] = -1
        n[i] = last

@njit(cache=True, fastmath=False, inline='always')
def _step_work(fx, fy, fz, fn, nx, ny, nz, vx, vy, vz, inv_m, inv_rot, dt):
    """Work of a contact force on the pair over one symplectic-Euler step (J).

    Uses the mid-step relative velocity ``v + dv/2``, where ``dv`` is the
    change the force itself produces (normal part through ``inv_m``, tangential
    part through ``inv_m + inv_rot``), so the sum over a binary contact equals
    the kinetic energy change exactly.
    """
    tfx = fx + fn * nx
    tfy = fy + fn * ny
    tfz = fz + fn * nz
    it = inv_m + inv_rot
    hx = vx + 0.5 * dt * (-fn * nx * inv_m + tfx * it)
    hy = vy + 0.5 * dt * (-fn * ny * inv_m + tfy * it)
    hz = vz + 0.5 * dt * (-fn * nz * inv_m + tfz * it)
    return (fx * hx + fy * hy + fz * hz) * dt


@njit(cache=True, fastmath=False)
def _force_chunk(c, t, dt, pos, vel, omg, rad, mass, invm, invi, mat, pid, frc, trq, kind, own_idx, own_start,
               nb_start, nb_j, nb_sh, rv_pos, stamp, pc, shs, pf, pt, box_len, gc_start, gc_g,
               gcur, grot, gkind, gmat, ptab, gravity,
               h_pid, h_st, h_ev, h_pk, h_ds, h_n, h_tch,
               g_gid, g_st, g_ev, g_pk, g_ds, g_n, g_tch,
               evf, evi, evn, diag):
    """Forces and torques on the particles of chunk ``c`` (see module docstring).

    Only particles with entries of their own (``kind & (K_OWN | K_GEO)``:
    half-list row, geometry candidates or open history slots) are visited;
    those in contact get ``frc`` and ``trq`` (the weight plus their own
    contacts, summed in the same order as always) and ``K_HIT``. The force on
    any other particle is its weight alone, which the integration pass takes
    without reading these arrays (see :func:`settle_forces` for ``frc`` and
    ``trq`` as outputs).
    """
    smax = h_pid.shape[1]
    sgmax = g_gid.shape[1]
    lx, ly, lz = box_len[0], box_len[1], box_len[2]
    q0, q1 = np.uint64(own_start[c]), np.uint64(own_start[c + 1])
    ovmax = 0.0
    one = np.uint64(1)
    # unsigned particle and entry indices: no negative-index wrap-around on every access;
    # only the chunk's owners (kind & (K_OWN | K_GEO), ascending, see work_lists) are visited
    for qo in range(q0, q1):
        i = np.uint64(own_idx[qo])
        ki = kind[i]
        hit = False  # the weight is read, and frc/trq written, only for a particle in contact
        fx = 0.0
        fy = 0.0
        fz = 0.0
        tx = 0.0
        ty = 0.0
        tz = 0.0
        ri = rad[i]
        xi, yi, zi = pos[i, 0], pos[i, 1], pos[i, 2]
        k0 = np.uint64(nb_start[i])
        k1 = np.uint64(nb_start[i + one]) if (ki & K_OWN) != 0 else k0
        wrap = (ki & K_WRAP) != 0
        # ---- particle-particle: half list, row i holds partners with a larger id, so
        # i is the canonical owner (force on i, history, events); the partner's
        # share is stored per entry and gathered in the integration pass
        for k in range(k0, k1):
            j = np.uint64(nb_j[k])
            rj = rad[j]
            rs = ri + rj
            if wrap:
                ox = nb_sh[k, 0] * lx
                oy = nb_sh[k, 1] * ly
                oz = nb_sh[k, 2] * lz
            else:  # no image in the row: every shift is 0, and 0 * l = +0.0
                ox = 0.0
                oy = 0.0
                oz = 0.0
            dx = pos[j, 0] - xi + ox
            dy = pos[j, 1] - yi + oy
            dz = pos[j, 2] - zi + oz
            d2 = dx * dx + dy * dy + dz * dz
            if d2 >= rs * rs or d2 == 0.0:
                continue
            if not hit:
                hit = True
                mi = mass[i]
                fx = mi * gravity[0]
                fy = mi * gravity[1]
                fz = mi * gravity[2]
            idj = pid[j]
            d = np.sqrt(d2)
            s = rs - d
            inv_d = 1.0 / d
            nx = dx * inv_d
            ny = dy * inv_d
            nz = dz * inv_d
            la = ri - 0.5 * s
            lb = rj - 0.5 * s
            # relative velocity of i w.r.t. j at the contact point
            wx = la * omg[i, 0] + lb * omg[j, 0]
            wy = la * omg[i, 1] + lb * omg[j, 1]
            wz = la * omg[i, 2] + lb * omg[j, 2]
            vx = vel[i, 0] - vel[j, 0] + (wy * nz - wz * ny)
            vy = vel[i, 1] - vel[j, 1] + (wz * nx - wx * nz)
            vz = vel[i, 2] - vel[j, 2] + (wx * ny - wy * nx)
            # history slot (written out here: an inlined helper with array arguments costs
            # numba's atomic reference counting on every entry, docs/dem.md, Performance)
            slot = -1
            new = False
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
                    h_st[i, slot, 0] = 0.0
                    h_st[i, slot, 1] = 0.0
                    h_st[i, slot, 2] = 0.0
                    h_ev[i, slot] = -1
                    h_pk[i, slot] = 0.0
                    h_ds[i, slot] = 0.0
            if slot < 0:
                diag[c, D_HOVF] += 1.0
            us = np.uint64(slot if slot >= 0 else 0)
            if slot >= 0:
                sx, sy, sz = h_st[i, us, 0], h_st[i, us, 1], h_st[i, us, 2]
            else:
                sx, sy, sz = 0.0, 0.0, 0.0
            ma = np.uint64(mat[i])
            mb = np.uint64(mat[j])
            rstar = ri * rj / rs
            mstar = 1.0 / (invm[i] + invm[j])
            cfx, cfy, cfz, sx, sy, sz, fn = contact_law(
                s, nx, ny, nz, vx, vy, vz, rstar, mstar, ptab[ma, mb, 0], ptab[ma, mb, 1],
                ptab[ma, mb, 2], ptab[ma, mb, 3], ptab[ma, mb, 4], dt, sx, sy, sz)
            fx += cfx
            fy += cfy
            fz += cfz
            cx_ = ny * cfz - nz * cfy
            cy_ = nz * cfx - nx * cfz
            cz_ = nx * cfy - ny * cfx
            tx += la * cx_
            ty += la * cy_
            tz += la * cz_
            # the partner's share, stored in its reverse-list order and stamped with this
            # step: the integration pass reads its shares contiguously and no entry
            # without contact is written
            rq = np.uint64(rv_pos[k])
            pc[rq] = stamp
            shs[j] = stamp  # j has a share this step (owners may write it concurrently: same value)
            pf[rq, 0] = cfx
            pf[rq, 1] = cfy
            pf[rq, 2] = cfz
            pt[rq, 0] = lb * cx_
            pt[rq, 1] = lb * cy_
            pt[rq, 2] = lb * cz_
            rmin = min(ri, rj)
            if s > ovmax * rmin:
                ovmax = s / rmin
            if slot >= 0:
                h_st[i, us, 0] = sx
                h_st[i, us, 1] = sy
                h_st[i, us, 2] = sz
                h_tch[i, us] = 1
                if new:
                    vn = vx * nx + vy * ny + vz * nz
                    vtx = vx - vn * nx
                    vty = vy - vn * ny
                    vtz = vz - vn * nz
                    h_ev[i, us] = _record_onset(
                        evf, evi, evn, c, t, pid[i], 0, idj, ri, rj,
                        xi + nx * la, yi + ny * la, zi + nz * la,
                        vn, np.sqrt(vtx * vtx + vty * vty + vtz * vtz), diag)
                if s > h_pk[i, us]:
                    h_pk[i, us] = s
                h_ds[i, us] -= _step_work(cfx, cfy, cfz, fn, nx, ny, nz, vx, vy, vz,
                                            invm[i] + invm[j],
                                            la * la * invi[i] + lb * lb * invi[j], dt)
        # ---- particle-geometry (a key is a primitive or one of its periodic images)
        g0 = gc_start[i] if (ki & K_GEO) != 0 else 0
        g1 = gc_start[i + one] if (ki & K_GEO) != 0 else 0
        for k in range(g0, g1):
            key = gc_g[k]
            g, xg, yg, zg = _geom_key_frame(key, xi, yi, zi, lx, ly, lz)
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
            wvx = 0.0
            wvy = 0.0
            wvz = 0.0
            if grot[g, 7] > 0.0:
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
            slot = -1
            new = False
            hn = g_n[i]
            for q in range(hn):
                if g_gid[i, q] == key:
                    slot = q
                    break
            if slot < 0:
                new = True
                if hn < sgmax:
                    slot = hn
                    g_n[i] = hn + 1
                    g_gid[i, slot] = key
                    g_st[i, slot, 0] = 0.0
                    g_st[i, slot, 1] = 0.0
                    g_st[i, slot, 2] = 0.0
                    g_ev[i, slot] = -1
                    g_pk[i, slot] = 0.0
                    g_ds[i, slot] = 0.0
            if slot < 0:
                diag[c, D_HOVF] += 1.0
            if slot >= 0:
                sx, sy, sz = g_st[i, slot, 0], g_st[i, slot, 1], g_st[i, slot, 2]
            else:
                sx, sy, sz = 0.0, 0.0, 0.0
            ma = np.uint64(mat[i])
            mb = np.uint64(gmat[g])
            cfx, cfy, cfz, sx, sy, sz, fn = contact_law(
                s, nx, ny, nz, vx, vy, vz, ri, mi, ptab[ma, mb, 0], ptab[ma, mb, 1],
                ptab[ma, mb, 2], ptab[ma, mb, 3], ptab[ma, mb, 4], dt, sx, sy, sz)
            fx += cfx
            fy += cfy
            fz += cfz
            tx += li * (ny * cfz - nz * cfy)
            ty += li * (nz * cfx - nx * cfz)
            tz += li * (nx * cfy - ny * cfx)
            if s > ovmax * ri:
                ovmax = s / ri
            if slot >= 0:
                g_st[i, slot, 0] = sx
                g_st[i, slot, 1] = sy
                g_st[i, slot, 2] = sz
                g_tch[i, slot] = 1
                if new:
                    vn = vx * nx + vy * ny + vz * nz
                    vtx = vx - vn * nx
                    vty = vy - vn * ny
                    vtz = vz - vn * nz
                    # contact point reported in the particle's frame
                    g_ev[i, slot] = _record_onset(
                        evf, evi, evn, c, t, pid[i], 1, g, ri, np.nan, cx + xi - xg, cy + yi - yg,
                        cz + zi - zg, vn,
                        np.sqrt(vtx * vtx + vty * vty + vtz * vtz), diag)
                if s > g_pk[i, slot]:
                    g_pk[i, slot] = s
                g_ds[i, slot] -= _step_work(cfx, cfy, cfz, fn, nx, ny, nz, vx, vy, vz,
                                            invm[i], li * li * invi[i], dt)
        # ---- end of contacts: the particle's slots not touched this step, while its rows are
        # in cache (a row is only read and written by its own particle, so the order of closing
        # is immaterial; as a second pass over the chunk's owners, the serial force pass took 3-5 %
        # longer, benchmarks/step_pass_pair.py)
        if (ki & K_OWN) != 0 and h_n[i] > 0:
            _close_untouched_row(h_pid, h_n, h_st, h_ev, h_pk, h_ds, h_tch, i, evf, t)
        if (ki & K_GEO) != 0 and g_n[i] > 0:
            _close_untouched_row(g_gid, g_n, g_st, g_ev, g_pk, g_ds, g_tch, i, evf, t)
        if hit:
            frc[i, 0] = fx
            frc[i, 1] = fy
            frc[i, 2] = fz
            trq[i, 0] = tx
            trq[i, 1] = ty
            trq[i, 2] = tz
            if (ki & K_HIT) == 0:
                kind[i] = ki | K_HIT
        elif (ki & K_HIT) != 0:
            kind[i] = ki & ~K_HIT
    diag[c, D_OVER] = max(diag[c, D_OVER], ovmax)


@njit(cache=True, fastmath=False, parallel=True)
def force_pass_par(t, dt, pos, vel, omg, rad, mass, invm, invi, mat, pid, frc, trq, kind, own_idx, own_start,
               nb_start, nb_j, nb_sh, rv_pos, stamp, pc, shs, pf, pt, box_len, gc_start, gc_g,
               gcur, grot, gkind, gmat, ptab, gravity,
               h_pid, h_st, h_ev, h_pk, h_ds, h_n, h_tch,
               g_gid, g_st, g_ev, g_pk, g_ds, g_n, g_tch,
               evf, evi, evn, diag):
    """Force pass, parallel over particle chunks."""
    for c in prange(diag.shape[0]):
        _force_chunk(c, t, dt, pos, vel, omg, rad, mass, invm, invi, mat, pid, frc, trq, kind, own_idx, own_start, nb_start, nb_j, nb_sh, rv_pos, stamp, pc, shs, pf, pt, box_len, gc_start, gc_g, gcur, grot, gkind, gmat, ptab, gravity, h_pid, h_st, h_ev, h_pk, h_ds, h_n, h_tch, g_gid, g_st, g_ev, g_pk, g_ds, g_n, g_tch, evf, evi, evn, diag)


@njit(cache=True, fastmath=False)
def force_pass_ser(t, dt, pos, vel, omg, rad, mass, invm, invi, mat, pid, frc, trq, kind, own_idx, own_start,
               nb_start, nb_j, nb_sh, rv_pos, stamp, pc, shs, pf, pt, box_len, gc_start, gc_g,
               gcur, grot, gkind, gmat, ptab, gravity,
               h_pid, h_st, h_ev, h_pk, h_ds, h_n, h_tch,
               g_gid, g_st, g_ev, g_pk, g_ds, g_n, g_tch,
               evf, evi, evn, diag):
    """Force pass, serial (small systems: no thread wake-up cost)."""
    for c in range(diag.shape[0]):
        _force_chunk(c, t, dt, pos, vel, omg, rad, mass, invm, invi, mat, pid, frc, trq, kind, own_idx, own_start, nb_start, nb_j, nb_sh, rv_pos, stamp, pc, shs, pf, pt, box_len, gc_start, gc_g, gcur, grot, gkind, gmat, ptab, gravity, h_pid, h_st, h_ev, h_pk, h_ds, h_n, h_tch, g_gid, g_st, g_ev, g_pk, g_ds, g_n, g_tch, evf, evi, evn, diag)


@njit(cache=True, fastmath=False, inline='always')
def _weight_free(gravity):
    """Whether every gravity component is +0.0 (then ``m g`` is +0.0 for any mass)."""
    ok = True
    for k in range(3):
        if gravity[k] != 0.0 or np.copysign(1.0, gravity[k]) < 0.0:
            ok = False
    return ok


@njit(cache=True, fastmath=False)
def _integrate_chunk(c, t_new, dt, pos, vel, omg, frc, trq, kind, act_idx, act_start, mass, gravity, rv_start,
                     stamp, pc, shs, pf, pt, invm, invi, flag, flag_t, lo, hi, periodic, sinks, diag):
    """Symplectic Euler on chunk ``c``: v += F/m dt, w += T/I dt, x += v_new dt; flags.

    Per-particle memory traffic is kept to what the particle needs: the force
    pass's ``frc``/``trq`` are read only for ``kind & K_HIT``, the partner
    shares only for particles a partner stamped this step (``shs``; the total
    is written back), any other particle feels its weight alone. The stamp
    alone is tested: it implies ``kind & K_REV``, and a test of the kind as
    well, true for ~80 % of the particles of the dense gas in no order, cost
    a mispredicted branch (the serial integration pass took 0.91 of its
    former time at phi = 0.30, ``benchmarks/step_pass_pair.py``, docs/dem.md).
    A zero force leaves ``vel``
    unchanged and a zero torque ``omg`` (bit for bit the same as adding the
    zero increment: velocities and spins are never -0.0, see
    :func:`particle_kinds`), so neither is written then.

    Two loops: the velocity and spin updates, then a branch-light one that
    moves every particle (each particle's operations are the same as in one
    loop, in the same order; its velocity is read again, from cache). In the
    first, a particle with neither its own contacts (``K_HIT``) nor a partner
    share this step takes one branch to its weight; testing the two in turn
    cost two branches in no order for most particles (serial integration
    0.68 of its time at phi = 0.30 and 0.89 in the 10 mm mill slice,
    ``benchmarks/step_pass_pair.py``). Without gravity a particle of kind 0
    (no entries, slots or candidates) feels no force, so where fewer than
    half of a chunk's particles have a nonzero kind the first loop visits
    only those (``act_idx``, see :func:`work_lists`).
    """
    n = pos.shape[0]
    nch = diag.shape[0]
    nsink = sinks.shape[0]
    i0, i1 = chunk_bounds(n, nch, c)
    vmax = 0.0
    nflag = 0
    no_weight = _weight_free(gravity)
    g0, g1, g2 = gravity[0], gravity[1], gravity[2]
    # loop constants as scalars (array reads would be repeated after every store: numba's
    # arrays may alias) and an unsigned index (no negative-index wrap-around per access)
    bx = periodic[0] == 0
    by = periodic[1] == 0
    bz = periodic[2] == 0
    lo0, lo1, lo2, hi0, hi1, hi2 = lo[0], lo[1], lo[2], hi[0], hi[1], hi[2]
    one = np.uint64(1)
    a0, a1 = np.uint64(act_start[c]), np.uint64(act_start[c + 1])
    # where most particles fly free and feel no weight (a dilute gas), the velocity loop visits
    # only the active ones (act_idx); the move loop after it visits every particle either way
    sparse = no_weight and np.uint64(2) * (a1 - a0) < np.uint64(i1 - i0)
    if sparse:  # the dense loop's updates below, written out for the active particles: one loop
        # over either index source cost 1.13x at phi = 0.30 (benchmarks/step_pass_pair.py)
        for qa in range(a0, a1):
            i = np.uint64(act_idx[qa])
            ki = kind[i]
            if (ki & K_HIT) != 0:
                f0, f1, f2 = frc[i, 0], frc[i, 1], frc[i, 2]
                t0, t1, t2 = trq[i, 0], trq[i, 1], trq[i, 2]
            else:  # no weight: a particle's own contacts are its only force
                f0 = 0.0
                f1 = 0.0
                f2 = 0.0
                t0 = 0.0
                t1 = 0.0
                t2 = 0.0
            if shs[i] == stamp:  # a partner wrote a share this step (implies K_REV)
                got = False
                for q in range(rv_start[i], rv_start[i + one]):
                    if pc[q] == stamp:  # contact owned by a partner with a smaller id, this step
                        got = True
                        f0 -= pf[q, 0]
                        f1 -= pf[q, 1]
                        f2 -= pf[q, 2]
                        t0 += pt[q, 0]
                        t1 += pt[q, 1]
                        t2 += pt[q, 2]
            else:
                got = False
            if got:
                frc[i, 0] = f0
                frc[i, 1] = f1
                frc[i, 2] = f2
                trq[i, 0] = t0
                trq[i, 1] = t1
                trq[i, 2] = t2
            if f0 != 0.0 or f1 != 0.0 or f2 != 0.0:
                im = invm[i]
                vel[i, 0] = vel[i, 0] + f0 * im * dt
                vel[i, 1] = vel[i, 1] + f1 * im * dt
                vel[i, 2] = vel[i, 2] + f2 * im * dt
            if t0 != 0.0 or t1 != 0.0 or t2 != 0.0:
                ii = invi[i]
                omg[i, 0] += t0 * ii * dt
                omg[i, 1] += t1 * ii * dt
                omg[i, 2] += t2 * ii * dt
    if not sparse:  # velocities and spins of every particle, then (below) every particle moves
        for i in range(np.uint64(i0), np.uint64(i1)):
            ki = kind[i]
            stamped = shs[i] == stamp  # a partner wrote a share this step (implies K_REV)
            # one branch, not two in no order, for the many particles with no contact this step
            if not (((ki & K_HIT) != 0) | stamped):
                if not no_weight:  # the weight alone
                    mi = mass[i]
                    f0 = mi * g0
                    f1 = mi * g1
                    f2 = mi * g2
                    if f0 != 0.0 or f1 != 0.0 or f2 != 0.0:
                        im = invm[i]
                        vel[i, 0] = vel[i, 0] + f0 * im * dt
                        vel[i, 1] = vel[i, 1] + f1 * im * dt
                        vel[i, 2] = vel[i, 2] + f2 * im * dt
            else:
                if (ki & K_HIT) != 0:
                    f0, f1, f2 = frc[i, 0], frc[i, 1], frc[i, 2]
                    t0, t1, t2 = trq[i, 0], trq[i, 1], trq[i, 2]
                else:
                    if no_weight:
                        f0 = 0.0
                        f1 = 0.0
                        f2 = 0.0
                    else:
                        mi = mass[i]
                        f0 = mi * g0
                        f1 = mi * g1
                        f2 = mi * g2
                    t0 = 0.0
                    t1 = 0.0
                    t2 = 0.0
                got = False
                if stamped:
                    for q in range(rv_start[i], rv_start[i + one]):
                        if pc[q] == stamp:  # contact owned by a partner with a smaller id, this step
                            got = True
                            f0 -= pf[q, 0]
                            f1 -= pf[q, 1]
                            f2 -= pf[q, 2]
                            t0 += pt[q, 0]
                            t1 += pt[q, 1]
                            t2 += pt[q, 2]
                if got:
                    frc[i, 0] = f0
                    frc[i, 1] = f1
                    frc[i, 2] = f2
                    trq[i, 0] = t0
                    trq[i, 1] = t1
                    trq[i, 2] = t2
                if f0 != 0.0 or f1 != 0.0 or f2 != 0.0:
                    im = invm[i]
                    vel[i, 0] = vel[i, 0] + f0 * im * dt
                    vel[i, 1] = vel[i, 1] + f1 * im * dt
                    vel[i, 2] = vel[i, 2] + f2 * im * dt
                if t0 != 0.0 or t1 != 0.0 or t2 != 0.0:
                    ii = invi[i]
                    omg[i, 0] += t0 * ii * dt
                    omg[i, 1] += t1 * ii * dt
                    omg[i, 2] += t2 * ii * dt
    for i in range(np.uint64(i0), np.uint64(i1)):  # move every particle
        v0, v1, v2 = vel[i, 0], vel[i, 1], vel[i, 2]
        x = pos[i, 0] + v0 * dt
        y = pos[i, 1] + v1 * dt
        z = pos[i, 2] + v2 * dt
        pos[i, 0] = x
        pos[i, 1] = y
        pos[i, 2] = z
        sp = v0 * v0 + v1 * v1 + v2 * v2
        if sp > vmax:
            vmax = sp
        # every flag is F_OK when a pass starts (a flagged particle ends the call, R_FLAGGED,
        # and is removed before the next), so flags are written here, never read
        if not (np.isfinite(x + y + z) and np.isfinite(sp)):
            flag[i] = F_NONFINITE
            flag_t[i] = t_new
            nflag += 1
            continue
        sunk = False
        for k in range(nsink):
            if (x >= sinks[k, 0] and x <= sinks[k, 3] and y >= sinks[k, 1]
                    and y <= sinks[k, 4] and z >= sinks[k, 2] and z <= sinks[k, 5]):
                flag[i] = 2 + k
                flag_t[i] = t_new
                nflag += 1
                sunk = True
                break
        if sunk:
            continue
        if ((bx and (x < lo0 or x > hi0)) or (by and (y < lo1 or y > hi1))
                or (bz and (z < lo2 or z > hi2))):
            flag[i] = F_LOST
            flag_t[i] = t_new
            nflag += 1
    diag[c, D_DISP2] = vmax  # this step's max speed^2 (D_SPEED2 keeps the max of the call)
    diag[c, D_SPEED2] = max(diag[c, D_SPEED2], vmax)
    diag[c, D_FLAGGED] += nflag


@njit(cache=True, fastmath=False)
def work_lists(kind, nch):
    """Per-chunk lists of the particles the step passes visit, for the kinds just computed.

    Returns ``(own_idx, own_start, act_idx, act_start)``: chunk ``c``'s
    particles (:func:`chunk_bounds`) with ``kind & (K_OWN | K_GEO)`` (the
    force pass) are ``own_idx[own_start[c]:own_start[c + 1]]``, those of
    nonzero kind (the velocity updates of a weight-free integration) are
    ``act_idx[act_start[c]:act_start[c + 1]]``, each in ascending order. The
    passes then neither test nor touch the others (most particles of a
    dilute gas).
    """
    n = kind.shape[0]
    no = 0
    na = 0
    for i in range(n):
        if (kind[i] & (K_OWN | K_GEO)) != 0:
            no += 1
        if kind[i] != 0:
            na += 1
    own_idx = np.empty(no, np.uint32)
    act_idx = np.empty(na, np.uint32)
    own_start = np.zeros(nch + 1, np.int64)
    act_start = np.zeros(nch + 1, np.int64)
    no = 0
    na = 0
    for c in range(nch):
        i0, i1 = chunk_bounds(n, nch, c)
        for i in range(i0, i1):
            if (kind[i] & (K_OWN | K_GEO)) != 0:
                own_idx[no] = i
                no += 1
            if kind[i] != 0:
                act_idx[na] = i
                na += 1
        own_start[c + 1] = no
        act_start[c + 1] = na
    return own_idx, own_start, act_idx, act_start


@njit(cache=True, fastmath=False)
def particle_kinds(nb_start, nb_sh, rv_start, gc_start, h_n, g_n, vel, omg):
    """Per-particle work flags of the step passes for the list just built.

    ``K_OWN``: the particle owns half-list entries or particle history slots
    and ``K_GEO`` geometry candidates or slots, so the force pass visits it;
    ``K_REV``: it is the partner of half-list entries, so the integration
    pass gathers shares; ``K_WRAP``: some of its entries are periodic images,
    so the force pass reads their shifts (for the others the shift term is
    +0.0, which it adds without reading them).
    Also turns -0.0 velocity and spin components into +0.0 (what adding a
    zero increment does), so that skipping a zero increment is exact.
    """
    n = nb_start.shape[0] - 1
    kind = np.zeros(n, np.uint8)
    for i in range(n):
        k = 0
        if nb_start[i + 1] > nb_start[i] or h_n[i] > 0:
            k |= K_OWN
        if gc_start[i + 1] > gc_start[i] or g_n[i] > 0:
            k |= K_GEO
        if rv_start[i + 1] > rv_start[i]:
            k |= K_REV
        for q in range(nb_start[i], nb_start[i + 1]):
            if nb_sh[q, 0] != 0 or nb_sh[q, 1] != 0 or nb_sh[q, 2] != 0:
                k |= K_WRAP
                break
        kind[i] = k
        for a in range(3):
            if vel[i, a] == 0.0:
                vel[i, a] = 0.0
            if omg[i, a] == 0.0:
                omg[i, a] = 0.0
    return kind


@njit(cache=True, fastmath=False)
def settle_forces(kind, mass, gravity, frc, trq, shs, stamp):
    """Make ``frc``/``trq`` those of the force pass of step ``stamp`` for every particle.

    The step passes write them only for particles in contact; any other
    particle had its weight and no torque. Call before the kinds or the
    partner shares of that step are replaced.
    """
    for i in range(kind.shape[0]):
        ki = kind[i]
        if (ki & K_HIT) != 0:
            continue
        if shs[i] == stamp:  # shares of partners were added in that step's integration
            continue
        mi = mass[i]
        frc[i, 0] = mi * gravity[0]
        frc[i, 1] = mi * gravity[1]
        frc[i, 2] = mi * gravity[2]
        trq[i, 0] = 0.0
        trq[i, 1] = 0.0
        trq[i, 2] = 0.0


@njit(cache=True, fastmath=False, parallel=True)
def integrate_par(t_new, dt, pos, vel, omg, frc, trq, kind, act_idx, act_start, mass, gravity, rv_start, stamp, pc, shs, pf, pt, invm, invi, flag, flag_t, lo, hi, periodic, sinks, diag):
    """Integration pass, parallel over chunks."""
    for c in prange(diag.shape[0]):
        _integrate_chunk(c, t_new, dt, pos, vel, omg, frc, trq, kind, act_idx, act_start, mass, gravity, rv_start, stamp, pc, shs, pf, pt, invm, invi, flag, flag_t, lo, hi, periodic, sinks, diag)


@njit(cache=True, fastmath=False)
def integrate_ser(t_new, dt, pos, vel, omg, frc, trq, kind, act_idx, act_start, mass, gravity, rv_start, stamp, pc, shs, pf, pt, invm, invi, flag, flag_t, lo, hi, periodic, sinks, diag):
    """Integration pass, serial."""
    for c in range(diag.shape[0]):
        _integrate_chunk(c, t_new, dt, pos, vel, omg, frc, trq, kind, act_idx, act_start, mass, gravity, rv_start, stamp, pc, shs, pf, pt, invm, invi, flag, flag_t, lo, hi, periodic, sinks, diag)


@njit(cache=True, fastmath=False)
def advance(t0, dt, nsteps, skin, disp, pos, vel, omg, rad, mass, invm, invi, mat, pid, frc, trq, kind,
            own_idx, own_start, act_idx, act_start, flag, flag_t, nb_start, nb_j, nb_sh, rv_start, rv_pos, stamp0, pc, shs, pf, pt, box_len, gc_start,
            gc_g, gref, gcur, grot, gkind, gmat, ptab, gravity, lo, hi, periodic, sinks,
            h_pid, h_st, h_ev, h_pk, h_ds, h_n, h_tch,
            g_gid, g_st, g_ev, g_pk, g_ds, g_n, g_tch, evf, evi, evn, diag, parallel):
    """Run up to ``nsteps`` steps from time ``t0``; return (steps done, reason).

    ``parallel`` selects the threaded passes (worth it from a few thousand
    particles; below that the thread wake-up per pass dominates). Step
    ``stamp0 + step`` stamps the partner shares it writes to ``pc``, and in
    ``shs`` the partners that got one (step numbers are unique over the run,
    so neither array needs clearing).
    """
    half_skin = 0.5 * skin
    ev_limit = evf.shape[1] // 2
    for step in range(nsteps):
        t = t0 + step * dt
        update_geometry(gref, grot, gkind, t, gcur)
        stamp = stamp0 + step
        if parallel:
            force_pass_par(t, dt, pos, vel, omg, rad, mass, invm, invi, mat, pid, frc, trq, kind,
                own_idx, own_start, nb_start, nb_j, nb_sh, rv_pos, stamp, pc, shs, pf, pt, box_len, gc_start, gc_g, gcur, grot, gkind, gmat,
                ptab, gravity, h_pid, h_st, h_ev, h_pk, h_ds, h_n, h_tch,
                g_gid, g_st, g_ev, g_pk, g_ds, g_n, g_tch, evf, evi, evn, diag)
            integrate_par(t0 + (step + 1) * dt, dt, pos, vel, omg, frc, trq, kind, act_idx, act_start, mass, gravity, rv_start, stamp, pc, shs, pf, pt, invm, invi, flag,
                flag_t, lo, hi, periodic, sinks, diag)
        else:
            force_pass_ser(t, dt, pos, vel, omg, rad, mass, invm, invi, mat, pid, frc, trq, kind,
                own_idx, own_start, nb_start, nb_j, nb_sh, rv_pos, stamp, pc, shs, pf, pt, box_len, gc_start, gc_g, gcur, grot, gkind, gmat,
                ptab, gravity, h_pid, h_st, h_ev, h_pk, h_ds, h_n, h_tch,
                g_gid, g_st, g_ev, g_pk, g_ds, g_n, g_tch, evf, evi, evn, diag)
            integrate_ser(t0 + (step + 1) * dt, dt, pos, vel, omg, frc, trq, kind, act_idx, act_start, mass, gravity, rv_start, stamp, pc, shs, pf, pt, invm, invi, flag,
                flag_t, lo, hi, periodic, sinks, diag)
        vmax2 = 0.0
        nflag = 0.0
        for c in range(diag.shape[0]):
            vmax2 = max(vmax2, diag[c, D_DISP2])
            nflag += diag[c, D_FLAGGED]
        # bound on the largest displacement since the last build: sum of max speed x dt
        disp[0] += np.sqrt(vmax2) * dt
        if nflag > 0:
            return step + 1, R_FLAGGED
        if disp[0] > half_skin:
            return step + 1, R_REBUILD
        for c in range(evn.shape[0]):
            if evn[c] > ev_limit:
                return step + 1, R_EVFULL
    return nsteps, R_DONE


# --------------------------------------------------------------------------- neighbour search
@njit(cache=True, fastmath=False)
def wrap_positions(pos, lo, box_len, periodic, g_gid, g_n, gspan):
    """Map positions into the periodic box along periodic axes.

    A particle moved by ``-k`` box lengths keeps its geometry contacts: the
    image shift in each history key grows by ``k`` along the axes its
    primitive does not span (see :func:`_geom_key_frame`), so the key still
    names the same image; a spanning primitive is met unshifted anyway.
    """
    for i in range(pos.shape[0]):
        kx = 0
        ky = 0
        kz = 0
        for a in range(3):
            if periodic[a] != 0:
                L = box_len[a]
                x = pos[i, a] - lo[a]
                if x < 0.0 or x >= L:
                    k = int(np.floor(x / L))
                    x -= k * L
                    if x >= L:
                        x -= L
                        k += 1
                    pos[i, a] = lo[a] + x
                    if a == 0:
                        kx = k
                    elif a == 1:
                        ky = k
                    else:
                        kz = k
        if kx != 0 or ky != 0 or kz != 0:
            for q in range(g_n[i]):
                key = g_gid[i, q]
                g = key // KEY_STRIDE
                code = key % KEY_STRIDE
                sx = _image_shift(code, 0) + (kx if gspan[g, 0] == 0 else 0)
                sy = _image_shift(code, 1) + (ky if gspan[g, 1] == 0 else 0)
                sz = _image_shift(code, 2) + (kz if gspan[g, 2] == 0 else 0)
                sx = min(max(sx, -8), 7)
                sy = min(max(sy, -8), 7)
                sz = min(max(sz, -8), 7)
                g_gid[i, q] = g * KEY_STRIDE + _image_code(sx, sy, sz)


@njit(cache=True, fastmath=False)
def bin_cells(pos, lo, cell_len, ncell):
    """Counting sort of particles into cells.

    Returns (cell of each, cell start, order, cell coordinates of each (n, 3)):
    the coordinates spare the neighbour sweep three integer divisions per
    particle.
    """
    n = pos.shape[0]
    nx, ny, nz = ncell[0], ncell[1], ncell[2]
    ntot = nx * ny * nz
    cell = np.empty(n, np.int64)
    cc = np.empty((n, 3), np.int32)
    for i in range(n):
        cx = int(np.floor((pos[i, 0] - lo[0]) / cell_len[0]))
        cy = int(np.floor((pos[i, 1] - lo[1]) / cell_len[1]))
        cz = int(np.floor((pos[i, 2] - lo[2]) / cell_len[2]))
        cx = min(max(cx, 0), nx - 1)
        cy = min(max(cy, 0), ny - 1)
        cz = min(max(cz, 0), nz - 1)
        cell[i] = (cz * ny + cy) * nx + cx
        cc[i, 0] = cx
        cc[i, 1] = cy
        cc[i, 2] = cz
    start = np.zeros(ntot + 1, np.int64)
    for i in range(n):
        start[cell[i] + 1] += 1
    for k in range(ntot):
        start[k + 1] += start[k]
    fill = start[:-1].copy()
    order = np.empty(n, np.int64)
    for i in range(n):
        order[fill[cell[i]]] = i
        fill[cell[i]] += 1
    return cell, start, order, cc


@njit(cache=True, fastmath=False, inline='always')
def _neighbour_cell(q, n, periodic_axis):
    """Cell index ``q`` along one axis wrapped into ``[0, n)``: ``(index, image shift, ok)``.

    The shift is -1, 0 or 1 periodic lengths; ``ok`` is False beyond a
    non-periodic boundary (and for periodic axes of fewer than 3 cells, where
    a wrapped cell would repeat a neighbour).
    """
    if q < 0:
        if periodic_axis == 0 or n < 3:
            return 0, 0, False
        return q + n, -1, True
    if q >= n:
        if periodic_axis == 0 or n < 3:
            return 0, 0, False
        return q - n, 1, True
    return q, 0, True


#: row blocks of the threaded rebuild sweeps (one call of the row function each)
SWEEP_BLOCKS = 64


@njit(cache=True, fastmath=False, inline='always')
def _candidates(i, p0, p1, sx, sy, sz, idi, xi, yi, zi, ri, skin, cxyzr, cpid, order, box_len, pad_j,
                pad_sh, cnt):
    """Add the candidates ``p0 <= p < p1`` (cell order) within the cut-off to row ``i``."""
    maxn = pad_j.shape[1]
    # the image offsets once per run (read in the loop they are reloaded after every store)
    ox = sx * box_len[0]
    oy = sy * box_len[1]
    oz = sz * box_len[2]
    for p in range(np.uint64(p0), np.uint64(p1)):  # unsigned: no wrap-around per access
        if cpid[p] <= idi:
            continue
        dx = cxyzr[p, 0] + ox - xi
        dy = cxyzr[p, 1] + oy - yi
        dz = cxyzr[p, 2] + oz - zi
        cut = ri + cxyzr[p, 3] + skin
        if dx * dx + dy * dy + dz * dz < cut * cut:
            if cnt < maxn:
                pad_j[i, cnt] = order[p]
                pad_sh[i, cnt, 0] = sx
                pad_sh[i, cnt, 1] = sy
                pad_sh[i, cnt, 2] = sz
            cnt += 1
    return cnt


@njit(cache=True, fastmath=False)
def _neighbours_rows(i0, i1, pid, pos, rad, skin, cell, start, order, cxyzr, cpid, ncell, periodic,
                     box_len, pad_j, pad_sh, counts):
    """Half-list candidates of particles ``i0 <= i < i1`` into their padded rows.

    Candidates are read from ``cxyzr`` (x, y, z, r) and ``cpid``, copies of
    the particle data in cell order, so a cell's particles are contiguous.
    A loop over a block of rows, not an inlined per-particle helper: numba
    wraps every entry of an inlined helper with array arguments in atomic
    reference counting (~100 ns per particle here, docs/dem.md, Performance).
    """
    nx, ny, nz = ncell[0], ncell[1], ncell[2]
    perx, pery, perz = periodic[0], periodic[1], periodic[2]
    for i in range(np.uint64(i0), np.uint64(i1)):
        cx = np.int64(cell[i, 0])
        cy = np.int64(cell[i, 1])
        cz = np.int64(cell[i, 2])
        xi, yi, zi = pos[i, 0], pos[i, 1], pos[i, 2]
        ri = rad[i]
        idi = pid[i]
        cnt = 0
        for oz in range(-1, 2):
            qz, sz, ok = _neighbour_cell(cz + oz, nz, perz)
            if not ok:
                continue
            for oy in range(-1, 2):
                qy, sy, ok = _neighbour_cell(cy + oy, ny, pery)
                if not ok:
                    continue
                row = (qz * ny + qy) * nx
                if 0 < cx < nx - 1:
                    # the three cells along x are contiguous in cell order and unshifted:
                    # one run of candidates, visited in the same order as cell by cell
                    cnt = _candidates(i, start[np.uint64(row + cx - 1)], start[np.uint64(row + cx + 2)],
                                      0, sy, sz, idi,
                                      xi, yi, zi, ri, skin, cxyzr, cpid, order, box_len, pad_j,
                                      pad_sh, cnt)
                    continue
                for ox in range(-1, 2):
                    qx, sx, ok = _neighbour_cell(cx + ox, nx, perx)
                    if not ok:
                        continue
                    q = np.uint64(row + qx)
                    cnt = _candidates(i, start[q], start[q + np.uint64(1)], sx, sy, sz, idi, xi, yi, zi, ri,
                                      skin, cxyzr, cpid, order, box_len, pad_j, pad_sh, cnt)
        counts[i] = cnt


@njit(cache=True, fastmath=False, parallel=True)
def _neighbours_pass_par(pid, pos, rad, skin, cell, start, order, cxyzr, cpid, ncell, periodic, box_len,
                         pad_j, pad_sh, counts):
    n = pos.shape[0]
    for c in prange(SWEEP_BLOCKS):
        i0, i1 = chunk_bounds(n, SWEEP_BLOCKS, c)
        _neighbours_rows(i0, i1, pid, pos, rad, skin, cell, start, order, cxyzr, cpid, ncell, periodic,
                         box_len, pad_j, pad_sh, counts)


@njit(cache=True, fastmath=False)
def _neighbours_pass_ser(pid, pos, rad, skin, cell, start, order, cxyzr, cpid, ncell, periodic, box_len,
                         pad_j, pad_sh, counts):
    _neighbours_rows(0, pos.shape[0], pid, pos, rad, skin, cell, start, order, cxyzr, cpid, ncell, periodic,
                     box_len, pad_j, pad_sh, counts)


@njit(cache=True, fastmath=False)
def _widest_row(counts):
    """Largest entry count of padded rows (0 for none)."""
    top = 0
    for i in range(counts.shape[0]):
        top = max(top, counts[i])
    return top


@njit(cache=True, fastmath=False)
def _row_starts(counts):
    """CSR row starts for rows of ``counts`` entries each."""
    n = counts.shape[0]
    start = np.zeros(n + 1, np.int64)
    for i in range(n):
        start[i + 1] = start[i] + counts[i]
    return start


@njit(cache=True, fastmath=False)
def build_neighbours(pid, pos, rad, skin, cell, start, order, ncell, periodic, box_len, parallel,
                     maxn_hint):
    """Half Verlet list (partners with a larger id) in CSR form plus its reverse.

    ``cell`` holds each particle's cell coordinates (n, 3), ``start`` and
    ``order`` the cell lists (see :func:`bin_cells`).

    One cell sweep fills padded rows of width ``maxn_hint`` (widened and
    redone if a row overflows), then rows are packed. Returns ``(start,
    partner index, periodic shift, reverse start, reverse entry)``: entries
    ``rv_start[j] <= q < rv_start[j+1]`` are the reverse positions of the
    entries whose partner is ``j`` and ``rv_pos[k]`` is entry ``k``'s (entries
    of a partner in list order).
    """
    n = pos.shape[0]
    counts = np.zeros(n, np.int64)
    maxn = max(maxn_hint, 1)
    cxyzr = np.empty((n, 4))
    cpid = np.empty(n, np.int64)
    for p in range(n):
        j = order[p]
        cxyzr[p, 0] = pos[j, 0]
        cxyzr[p, 1] = pos[j, 1]
        cxyzr[p, 2] = pos[j, 2]
        cxyzr[p, 3] = rad[j]
        cpid[p] = pid[j]
    while True:
        pad_j = np.empty((n, maxn), np.int32)
        pad_sh = np.empty((n, maxn, 3), np.int8)
        if parallel:
            _neighbours_pass_par(pid, pos, rad, skin, cell, start, order, cxyzr, cpid, ncell, periodic,
                                 box_len, pad_j, pad_sh, counts)
        else:
            _neighbours_pass_ser(pid, pos, rad, skin, cell, start, order, cxyzr, cpid, ncell, periodic,
                                 box_len, pad_j, pad_sh, counts)
        top = _widest_row(counts)
        if top <= maxn:
            break
        maxn = top + top // 4 + 4
    nb_start = _row_starts(counts)
    nb_j = np.empty(nb_start[n], np.int32)
    nb_sh = np.empty((nb_start[n], 3), np.int8)
    for i in range(n):
        o = nb_start[i]
        for q in range(counts[i]):
            nb_j[o + q] = pad_j[i, q]
            nb_sh[o + q, 0] = pad_sh[i, q, 0]
            nb_sh[o + q, 1] = pad_sh[i, q, 1]
            nb_sh[o + q, 2] = pad_sh[i, q, 2]
    m = nb_start[n]
    rv_start = np.zeros(n + 1, np.int64)
    for k in range(m):
        rv_start[nb_j[k] + 1] += 1
    for i in range(n):
        rv_start[i + 1] += rv_start[i]
    fill = rv_start[:-1].copy()
    rv_pos = np.empty(m, np.int64)
    for k in range(m):
        j = nb_j[k]
        rv_pos[k] = fill[j]
        fill[j] += 1
    return nb_start, nb_j, nb_sh, rv_start, rv_pos, top


@njit(cache=True, fastmath=False, inline='always')
def _geom_candidate(g, x, y, z, r, skin, gcur, grot, gkind, gbound):
    m = r + skin
    if grot[g, 7] > 0.0:
        if gkind[g] == PLANE:
            return True
        px = x - grot[g, 0]
        py = y - grot[g, 1]
        pz = z - grot[g, 2]
        a = px * grot[g, 3] + py * grot[g, 4] + pz * grot[g, 5]
        qx = px - a * grot[g, 3]
        qy = py - a * grot[g, 4]
        qz = pz - a * grot[g, 5]
        rho = np.sqrt(qx * qx + qy * qy + qz * qz)
        return (rho >= gbound[g, 0] - m and rho <= gbound[g, 1] + m
                and a >= gbound[g, 2] - m and a <= gbound[g, 3] + m)
    if (x < gbound[g, 0] - m or y < gbound[g, 1] - m or z < gbound[g, 2] - m
            or x > gbound[g, 3] + m or y > gbound[g, 4] + m or z > gbound[g, 5] + m):
        return False
    ok = geom_contact(gkind[g], gcur, g, x, y, z, m)[0]
    return ok


@njit(cache=True, fastmath=False, inline='always')
def _image_useful(p, s, L, lo, hi, m):
    """Whether position ``p`` shifted by ``s`` periods ``L`` comes within ``m`` of ``[lo, hi]``."""
    q = p + s * L
    return q >= lo - m and q <= hi + m


@njit(cache=True, fastmath=False)
def _geom_rows(i0, i1, pos, rad, skin, gcur, grot, gkind, gbound, gspan, periodic, box_len, img_box, glo,
               gcl, gnc, grid_start, grid_list, pad, counts):
    """Candidates of particles ``i0 <= i < i1``: keys ``g * KEY_STRIDE + code`` of primitives and images.

    Along a periodic axis the particle is also tested shifted by one box
    length either way against every primitive that does not span that axis
    (``gspan``), i.e. against the primitive's periodic images; a shift is
    only tried if the shifted position comes within ``r + skin`` of
    ``img_box`` (lo 0:3, hi 3:6), the bounding box of those primitives.
    Keys go to row ``i`` of ``pad`` as far as it reaches; ``counts[i]`` gets
    their number. A loop over a block of rows (see :func:`_neighbours_rows`).
    """
    for i in range(i0, i1):
        cnt = 0
        width = pad.shape[1]
        m = rad[i] + skin
        px = 1 if periodic[0] != 0 else 0
        py = 1 if periodic[1] != 0 else 0
        pz = 1 if periodic[2] != 0 else 0
        for sx in range(-px, px + 1):
            if sx != 0 and not _image_useful(pos[i, 0], sx, box_len[0], img_box[0], img_box[3], m):
                continue
            for sy in range(-py, py + 1):
                if sy != 0 and not _image_useful(pos[i, 1], sy, box_len[1], img_box[1], img_box[4], m):
                    continue
                for sz in range(-pz, pz + 1):
                    if sz != 0 and not _image_useful(pos[i, 2], sz, box_len[2], img_box[2], img_box[5], m):
                        continue
                    x = pos[i, 0] + sx * box_len[0]
                    y = pos[i, 1] + sy * box_len[1]
                    z = pos[i, 2] + sz * box_len[2]
                    code = _image_code(sx, sy, sz)
                    cx = min(max(int(np.floor((x - glo[0]) / gcl[0])), 0), gnc[0] - 1)
                    cy = min(max(int(np.floor((y - glo[1]) / gcl[1])), 0), gnc[1] - 1)
                    cz = min(max(int(np.floor((z - glo[2]) / gcl[2])), 0), gnc[2] - 1)
                    cell = (cz * gnc[1] + cy) * gnc[0] + cx
                    for q in range(grid_start[cell], grid_start[cell + 1]):
                        g = grid_list[q]
                        # a spanning primitive is met unshifted only (it is its own image)
                        if ((sx != 0 and gspan[g, 0] != 0) or (sy != 0 and gspan[g, 1] != 0)
                                or (sz != 0 and gspan[g, 2] != 0)):
                            continue
                        if _geom_candidate(g, x, y, z, rad[i], skin, gcur, grot, gkind, gbound):
                            if cnt < width:
                                pad[i, cnt] = g * KEY_STRIDE + code
                            cnt += 1
        counts[i] = cnt


@njit(cache=True, fastmath=False, parallel=True)
def _geom_pass_par(pos, rad, skin, gcur, grot, gkind, gbound, gspan, periodic, box_len, img_box, glo, gcl,
                   gnc, grid_start, grid_list, pad, counts):
    n = pos.shape[0]
    for c in prange(SWEEP_BLOCKS):
        i0, i1 = chunk_bounds(n, SWEEP_BLOCKS, c)
        _geom_rows(i0, i1, pos, rad, skin, gcur, grot, gkind, gbound, gspan, periodic, box_len, img_box, glo,
                   gcl, gnc, grid_start, grid_list, pad, counts)


@njit(cache=True, fastmath=False)
def _geom_pass_ser(pos, rad, skin, gcur, grot, gkind, gbound, gspan, periodic, box_len, img_box, glo, gcl,
                   gnc, grid_start, grid_list, pad, counts):
    _geom_rows(0, pos.shape[0], pos, rad, skin, gcur, grot, gkind, gbound, gspan, periodic, box_len, img_box,
               glo, gcl, gnc, grid_start, grid_list, pad, counts)


@njit(cache=True, fastmath=False)
def build_geom_candidates(pos, rad, skin, gcur, grot, gkind, gbound, gspan, periodic, box_len, img_box, glo,
                          gcl, gnc, grid_start, grid_list, parallel, maxg_hint):
    """Per-particle candidate primitives (CSR): static by distance, rotating by swept annulus.

    Only the primitives listed in the particle's cell of the coarse geometry
    grid (:func:`build_geom_grid`) are tested; entries are keys
    ``g * KEY_STRIDE + image code`` (see :func:`_geom_key_frame`). One sweep
    fills padded rows of width ``maxg_hint`` (widened and redone if a row
    overflows). Returns ``(start, keys, widest row)``. Without primitives
    (a periodic gas) every row is empty and nothing is swept.
    """
    n = pos.shape[0]
    if gkind.shape[0] == 0:
        return np.zeros(n + 1, np.int64), np.empty(0, np.int32), 0
    counts = np.zeros(n, np.int64)
    maxg = max(maxg_hint, 1)
    while True:
        pad = np.empty((n, maxg), np.int32)
        if parallel:
            _geom_pass_par(pos, rad, skin, gcur, grot, gkind, gbound, gspan, periodic, box_len, img_box, glo,
                           gcl, gnc, grid_start, grid_list, pad, counts)
        else:
            _geom_pass_ser(pos, rad, skin, gcur, grot, gkind, gbound, gspan, periodic, box_len, img_box, glo,
                           gcl, gnc, grid_start, grid_list, pad, counts)
        top = _widest_row(counts)
        if top <= maxg:
            break
        maxg = top + top // 4 + 4
    gc_start = _row_starts(counts)
    gc_g = np.empty(gc_start[n], np.int32)
    for i in range(n):
        o = gc_start[i]
        for q in range(counts[i]):
            gc_g[o + q] = pad[i, q]
    return gc_start, gc_g, top


@njit(cache=True, fastmath=False)
def _geom_aabb(g, gcur, grot, gkind, gbound):
    """Axis-aligned box holding a primitive at any rotation angle (planes: infinite)."""
    lo = np.empty(3)
    hi = np.empty(3)
    if gkind[g] == PLANE:
        for k in range(3):
            lo[k] = -np.inf
            hi[k] = np.inf
    elif grot[g, 7] > 0.0:
        rmax = gbound[g, 1]
        for k in range(3):
            u = grot[g, 3 + k]
            a0 = grot[g, k] + gbound[g, 2] * u
            a1 = grot[g, k] + gbound[g, 3] * u
            ext = rmax * np.sqrt(max(0.0, 1.0 - u * u))
            lo[k] = min(a0, a1) - ext
            hi[k] = max(a0, a1) + ext
    else:
        for k in range(3):
            lo[k] = gbound[g, k]
            hi[k] = gbound[g, 3 + k]
    return lo, hi


@njit(cache=True, fastmath=False)
def _grid_pass(gcur, grot, gkind, gbound, glo, gcl, gnc, margin, grid_start, grid_list, fill):
    ncell = gnc[0] * gnc[1] * gnc[2]
    half_diag = 0.5 * np.sqrt(gcl[0] ** 2 + gcl[1] ** 2 + gcl[2] ** 2)
    for g in range(gkind.shape[0]):
        if gkind[g] == PLANE and grot[g, 7] <= 0.0:
            for c in range(ncell):
                cx = c % gnc[0]
                cy = (c // gnc[0]) % gnc[1]
                cz = c // (gnc[0] * gnc[1])
                px = glo[0] + (cx + 0.5) * gcl[0] - gcur[g, 0]
                py = glo[1] + (cy + 0.5) * gcl[1] - gcur[g, 1]
                pz = glo[2] + (cz + 0.5) * gcl[2] - gcur[g, 2]
                d = px * gcur[g, 3] + py * gcur[g, 4] + pz * gcur[g, 5]
                if abs(d) <= half_diag + margin:
                    if fill:
                        grid_list[grid_start[c + 1]] = g
                    grid_start[c + 1] += 1
            continue
        lo, hi = _geom_aabb(g, gcur, grot, gkind, gbound)
        i0 = np.empty(3, np.int64)
        i1 = np.empty(3, np.int64)
        for k in range(3):
            a = (lo[k] - margin - glo[k]) / gcl[k]
            b = (hi[k] + margin - glo[k]) / gcl[k]
            a = min(max(a, 0.0), gnc[k] - 1.0)
            b = min(max(b, 0.0), gnc[k] - 1.0)
            i0[k] = int(np.floor(a))
            i1[k] = int(np.floor(b))
        for cz in range(i0[2], i1[2] + 1):
            for cy in range(i0[1], i1[1] + 1):
                for cx in range(i0[0], i1[0] + 1):
                    c = (cz * gnc[1] + cy) * gnc[0] + cx
                    if fill:
                        grid_list[grid_start[c + 1]] = g
                    grid_start[c + 1] += 1


@njit(cache=True, fastmath=False)
def build_geom_grid(gcur, grot, gkind, gbound, glo, gcl, gnc, margin):
    """Coarse grid of primitives: cell ``c`` lists every primitive within ``margin`` of it."""
    ncell = gnc[0] * gnc[1] * gnc[2]
    counts = np.zeros(ncell + 1, np.int64)
    dummy = np.zeros(0, np.int32)
    _grid_pass(gcur, grot, gkind, gbound, glo, gcl, gnc, margin, counts, dummy, False)
    grid_start = np.zeros(ncell + 1, np.int64)
    for c in range(ncell):
        grid_start[c + 1] = grid_start[c] + counts[c + 1]
    grid_list = np.empty(grid_start[ncell], np.int32)
    cursor = grid_start.copy()
    # second pass writes at cursor[c + 1 - 1]: shift so that cursor[c + 1] starts at c's offset
    shifted = np.empty(ncell + 1, np.int64)
    shifted[1:] = cursor[:-1]
    shifted[0] = 0
    _grid_pass(gcur, grot, gkind, gbound, glo, gcl, gnc, margin, shifted, grid_list, True)
    return grid_start, grid_list


# --------------------------------------------------------------------------- diagnostics
@njit(cache=True, fastmath=False)
def contact_potential_energy(pos, rad, pid, mat, nb_start, nb_j, nb_sh, box_len, ptab,
                             gc_start, gc_g, gcur, gkind, gmat):
    """Elastic energy stored in normal contacts, sum of 2/5 K_H s^{5/2} (J)."""
    e = 0.0
    for i in range(pos.shape[0]):
        for k in range(nb_start[i], nb_start[i + 1]):
            j = nb_j[k]
            if pid[j] < pid[i]:
                continue
            dx = pos[j, 0] - pos[i, 0] + nb_sh[k, 0] * box_len[0]
            dy = pos[j, 1] - pos[i, 1] + nb_sh[k, 1] * box_len[1]
            dz = pos[j, 2] - pos[i, 2] + nb_sh[k, 2] * box_len[2]
            s = rad[i] + rad[j] - np.sqrt(dx * dx + dy * dy + dz * dz)
            if s > 0:
                rstar = rad[i] * rad[j] / (rad[i] + rad[j])
                e += 0.4 * ptab[mat[i], mat[j], 0] * np.sqrt(rstar) * s**2.5
        for k in range(gc_start[i], gc_start[i + 1]):
            g, xg, yg, zg = _geom_key_frame(gc_g[k], pos[i, 0], pos[i, 1], pos[i, 2], box_len[0],
                                            box_len[1], box_len[2])
            ok, s, _nx, _ny, _nz, _cx, _cy, _cz = geom_contact(gkind[g], gcur, g, xg, yg, zg, rad[i])
            if ok:
                e += 0.4 * ptab[mat[i], gmat[g], 0] * np.sqrt(rad[i]) * s**2.5
    return e


@njit(cache=True, fastmath=False, inline='always')
def _min_image_d2(dx, dy, dz, box_len, periodic):
    """Squared length of the shortest periodic image of ``(dx, dy, dz)``."""
    if periodic[0] != 0:
        dx -= box_len[0] * np.round(dx / box_len[0])
    if periodic[1] != 0:
        dy -= box_len[1] * np.round(dy / box_len[1])
    if periodic[2] != 0:
        dz -= box_len[2] * np.round(dz / box_len[2])
    return dx * dx + dy * dy + dz * dz


@njit(cache=True, fastmath=False)
def place_without_overlap(cand, radii, ex_pos, ex_rad, box_len, periodic):
    """Pick, for each new particle, the first candidate position free of overlap.

    ``cand`` has shape (n_new, n_try, 3). Distances are taken to the nearest
    periodic image along periodic axes. Returns the accepted positions and a
    boolean mask (False when every try overlapped).
    """
    nnew, ntry = cand.shape[0], cand.shape[1]
    out = np.empty((nnew, 3))
    okm = np.zeros(nnew, np.bool_)
    nex = ex_pos.shape[0]
    for p in range(nnew):
        r = radii[p]
        for tr in range(ntry):
            x, y, z = cand[p, tr, 0], cand[p, tr, 1], cand[p, tr, 2]
            free = True
            for j in range(nex):
                rr = ex_rad[j] + r
                if _min_image_d2(ex_pos[j, 0] - x, ex_pos[j, 1] - y, ex_pos[j, 2] - z, box_len,
                                 periodic) < rr * rr:
                    free = False
                    break
            if free:
                for q in range(p):
                    if not okm[q]:
                        continue
                    rr = radii[q] + r
                    if _min_image_d2(out[q, 0] - x, out[q, 1] - y, out[q, 2] - z, box_len,
                                     periodic) < rr * rr:
                        free = False
                        break
            if free:
                out[p, 0] = x
                out[p, 1] = y
                out[p, 2] = z
                okm[p] = True
                break
    return out, okm


@njit(cache=True, fastmath=False)
def geometry_overlap(pos, rad, gcur, gkind, box_len, periodic):
    """Largest overlap (m) of each sphere with any primitive at its current pose (0 if clear).

    Periodic axes are searched one box length either way (a sphere near the
    boundary meets a primitive's periodic image). A plane counts every point
    on its far side as overlapping (``r - d`` with the signed distance ``d``),
    so a sphere outside the casing is never taken as clear.
    """
    n = pos.shape[0]
    out = np.zeros(n)
    sx = 1 if periodic[0] != 0 else 0
    sy = 1 if periodic[1] != 0 else 0
    sz = 1 if periodic[2] != 0 else 0
    for i in range(n):
        r = rad[i]
        best = 0.0
        for g in range(gkind.shape[0]):
            for ix in range(-sx, sx + 1):
                for iy in range(-sy, sy + 1):
                    for iz in range(-sz, sz + 1):
                        x = pos[i, 0] + ix * box_len[0]
                        y = pos[i, 1] + iy * box_len[1]
                        z = pos[i, 2] + iz * box_len[2]
                        if gkind[g] == PLANE:
                            d = ((x - gcur[g, 0]) * gcur[g, 3] + (y - gcur[g, 1]) * gcur[g, 4]
                                 + (z - gcur[g, 2]) * gcur[g, 5])
                            s = r - d
                        else:
                            ok, s, _nx, _ny, _nz, _cx, _cy, _cz = geom_contact(gkind[g], gcur, g, x, y, z, r)
                            if not ok:
                                s = 0.0
                        if s > best:
                            best = s
        out[i] = best
    return out


@njit(cache=True, fastmath=False)
def permute_slot_records(perm, cnt, words):
    """Gather slot records by ``perm``, copying only the used slots of each particle.

    ``words`` is the records' raw view, shape (particles, slots, words per
    record). Returns a new array of that shape; unused slots hold undefined
    values (every reader bounds its access by ``cnt``; a slot is initialised
    when it is taken).
    """
    n = perm.shape[0]
    out = np.empty((n, words.shape[1], words.shape[2]), words.dtype)
    nw = words.shape[2]
    for i in range(n):
        o = perm[i]
        for q in range(cnt[o]):
            for w in range(nw):
                out[i, q, w] = words[o, q, w]
    return out


@njit(cache=True, fastmath=False)
def remap_event_refs(ev, cnt, new_row):
    """Remap the used slots' event references after a flush (``new_row[row, chunk]``, -1: moved out)."""
    nch = new_row.shape[1]
    for i in range(ev.shape[0]):
        for q in range(cnt[i]):
            v = ev[i, q]
            if v >= 0:
                row = new_row[v // nch, v % nch]
                ev[i, q] = row * nch + v % nch if row >= 0 else -1
