"""The numpy twins of the compiled kernels: the reference each compiled kernel is tested against, and what
runs where the kernels are not built (a pure-Python install) or numpy is asked for (RELIEF_RAY_KERNEL=numpy).

Every twin takes the arguments of its compiled kernel (`_compiled.pyx`, the same name), writes the same
outputs and returns the same value, with the same float32 / float64 operations in the same order, so that
the two give the same numbers bit for bit (tests/backend/kernels).  The physics they share with the rest of
the project comes from the core: the interface coefficients from `core.fresnel.interface_coefficients_f32`
(Born & Wolf 1.5.20-21, 1.5.27, total internal reflection included), the Stokes frame rotation's
(cos 2psi, sin 2psi) from `core.stokes.double_angle_cd`.  Input arrays are the compiled kernels': float32
directions, origins, weights and Mueller rows, int64 indices, uint8 flags.
"""
from __future__ import annotations

import functools

import numpy as np

from relief_bsdf.core.fresnel import interface_coefficients_f32
from relief_bsdf.core.stokes import double_angle_cd

F32 = np.float32


def _quiet(fn):
    """Run a twin without numpy's floating-point warnings: the compiled kernel gives the same infinities and
    NaNs (a ray along a tile side, a zero normal) silently, and its callers handle them."""
    @functools.wraps(fn)
    def run(*args, **kwargs):
        with np.errstate(all="ignore"):
            return fn(*args, **kwargs)
    return run


# ----------------------------------------------------------------------------- binning


@_quiet
def bin_cells(cell, w, M, sum_w, sum_w2, sum_M, group=None, keys=None, w_keys=None, compact=None, path_ids=None,
              n_paths=0):
    """Add each exit i with cell[i] >= 0 to its cell in the order of i: sum_w += w, sum_w2 += w^2 (float64),
    sum_M[c, e] += float64(M[e, i] * w) (the float32 product); exits flagged compact are expanded first
    (`expand_compact`).  With group: the binned exits' keys group * cells + cell (group of the path
    path_ids[i] mod n_paths when path_ids is given) and float32 weights into keys, w_keys; returns how many
    (0 without group).
    Sums that start at zero take numpy's bincount (which adds in input order from zero, the same sums);
    others `np.add.at` (unbuffered, in order)."""
    n, nc = cell.shape[0], sum_w.shape[0]
    sel = np.flatnonzero(cell >= 0)
    full = sel.size == n
    c = (cell if full else cell[sel]).astype(np.intp, copy=False)
    wf = w if full else w[sel]
    wd = wf.astype(np.float64)
    zero = not (sum_w.any() or sum_w2.any() or (sum_M is not None and sum_M.any()))
    rows = None
    if M is not None:
        Mw = M if full else M[:, sel]
        rows = [Mw[e] for e in range(16)]
        flag = None if compact is None else (compact if full else compact[sel]) != 0
        if flag is not None and flag.any():          # compact records: their 16 entries from rows 0-7
            rows = [np.where(flag, x, r) for x, r in zip(_factored(*rows[:8]), rows)]
    if zero:                                         # bincount adds in input order from zero
        sum_w += np.bincount(c, weights=wd, minlength=nc)
        sum_w2 += np.bincount(c, weights=wd * wd, minlength=nc)
        if rows is not None:
            for e in range(16):
                sum_M[:, e] += np.bincount(c, weights=rows[e] * wf, minlength=nc)
    else:
        np.add.at(sum_w, c, wd)
        np.add.at(sum_w2, c, wd * wd)
        if rows is not None:
            np.add.at(sum_M, c, np.stack([(r * wf).astype(np.float64) for r in rows], axis=1))
    if group is None:
        return 0
    if path_ids is not None:
        pid = path_ids[sel]
        pid = np.where(pid >= n_paths, pid - n_paths, pid)
        g = np.asarray(group)[pid]
    else:
        g = np.asarray(group)[sel]
    j = sel.size
    keys[:j] = (g.astype(np.int64) * nc + c).astype(np.int32)
    w_keys[:j] = wf
    return j


@_quiet
def add_at(keys, w, out):
    """out[keys[i]] += float64(w[i]) in the order of i."""
    np.add.at(out, np.asarray(keys, np.int64), np.asarray(w).astype(np.float64))


@_quiet
def direction_parts(k, az, kx, ky):
    """az = min(|k_z|, 1) (NaN kept), and the components k_x, k_y of directions k (n, 3), contiguous."""
    np.minimum(np.abs(k[:, 2]), F32(1), out=az)
    kx[:] = k[:, 0]
    ky[:] = k[:, 1]


@_quiet
def cells_of_angles(x, y, t_scale, t_off, p_scale, p_off, ring_lut, az_lut, n_az, side, side_cells, out):
    """The cell of each exit from its polar angle x and azimuth y (radians, float32): scale, offset,
    max 0 (NaN -> 0), clipped to the look-up tables, truncated, looked up; plus side * side_cells, or -1
    where either look-up is negative (outside the table)."""
    rmax, amax = F32(ring_lut.shape[0] - 1), F32(az_lut.shape[0] - 1)
    xv = x * F32(t_scale)
    xv += F32(t_off)
    xv = np.where(xv > 0, xv, F32(0))
    xv = np.where(xv > rmax, rmax, xv)
    yv = y * F32(p_scale)
    yv += F32(p_off)
    yv = np.where(yv > 0, yv, F32(0))
    yv = np.where(yv > amax, amax, yv)
    ib = ring_lut[xv.astype(np.int32)]
    ia = az_lut[yv.astype(np.int32)]
    c = ib * np.int32(n_az) + ia + side.astype(np.int32) * np.int32(side_cells)
    out[:] = np.where((ib | ia) < 0, np.int32(-1), c)


@_quiet
def cells_of_directions(k, t_scale, t_off, p_scale, p_off, ring_lut, az_lut, n_az, side, side_cells, margin, out,
                        exact):
    """The cells of directions k (n, 3) from numpy's float32 arccos min(|k_z|, 1) and arctan2(k_y, k_x)
    (`direction_parts`, `cells_of_angles`): the reference.  The compiled kernel gives these cells without
    the two functions wherever they cannot change the cell and lists the other directions in exact (out -2)
    for the caller to finish with numpy's angles; here every cell is numpy's and none is listed (returns 0):
    after the caller's finish both give the same cells (tests/backend/kernels)."""
    n = k.shape[0]
    x, kx, ky = np.empty(n, F32), np.empty(n, F32), np.empty(n, F32)
    direction_parts(k, x, kx, ky)
    np.arccos(x, out=x)
    np.arctan2(ky, kx, out=ky)
    cells_of_angles(x, ky, t_scale, t_off, p_scale, p_off, ring_lut, az_lut, n_az, side, side_cells, out)
    return 0



@_quiet
def cells_of_edges(k, te_sin2, last_ring, lut_t, scale_t, pe_rel, lut_p, scale_p, pe0, margin_deg, side, side_cells,
                   out, exact):
    """The cells of directions k (n, 3) on searched edges from numpy's sin^2 theta search and float32 arctan2
    (`builder.CellIndex` for edges that are not uniform: `_theta_bins`' and `_phi_bins`' searches): the
    reference (the look-up tables only speed the compiled search up); none listed in exact (returns 0)."""
    S, A = te_sin2.size - 1, pe_rel.size - 1
    kz = k[:, 2]
    sin2 = np.maximum(F32(0), 1 - kz * kz).astype(np.float64)
    ib = np.searchsorted(te_sin2, sin2, side="right") - 1
    ib[sin2 >= te_sin2[-1]] = last_ring
    phi = np.mod(np.degrees(np.arctan2(k[:, 1], k[:, 0]).astype(np.float64)) - pe0, 360.0)
    ia = np.searchsorted(pe_rel, phi, side="right") - 1
    cell = (ib * A + ia).astype(np.int32)
    bad = (ib < 0) | (ib >= S) | (ia < 0) | (ia >= A)
    cell += side.astype(np.int32) * np.int32(side_cells)
    cell[bad] = -1
    out[...] = cell
    return 0

@_quiet
def near_direction(dirs, d0, d1, d2, cos_min, out):
    """Indices (into out, in order; their number returned) of the directions whose float32 dot product
    (x d0 + y d1) + z d2 with (d0, d1, d2) exceeds cos_min."""
    c = dirs[:, 0] * F32(d0)
    c += dirs[:, 1] * F32(d1)
    c += dirs[:, 2] * F32(d2)
    idx = np.flatnonzero(c > F32(cos_min))
    out[:idx.size] = idx
    return idx.size


@_quiet
def near_two_directions(dirs, a0, a1, a2, b0, b1, b2, cos_min, out_a, out_b):
    """`near_direction` for the two directions a and b: (count a, count b)."""
    return near_direction(dirs, a0, a1, a2, cos_min, out_a), near_direction(dirs, b0, b1, b2, cos_min, out_b)


# ----------------------------------------------------------------------------- Stokes frames, exit records


def _double_angle(c, d):
    """(cos 2psi, sin 2psi) of the rotation given c, d (`core.stokes.double_angle_cd`, float32)."""
    return double_angle_cd(np.array(c, F32), np.array(d, F32))


def _factored(a, b, cc, dd, c2, s2, E, S) -> list:
    """The 16 entries (row-major: entry 4 i + j is column j's Stokes component i) of Rot_exit (M Rot / p) from a
    first interaction's factors (a, b, cc, dd, c2, s2) and the exit rotation (E, S) = (cos 2psi', sin 2psi')
    (`methods.ray.transport.exit_columns_of_factors`'s operations)."""
    x1, x2, y1, y2 = a * c2, -(cc * s2), a * s2, cc * c2
    z = np.zeros_like(a)
    return [a, b * c2, b * s2, z,
            E * b, E * x1 + S * x2, E * y1 + S * y2, S * dd,
            -(b * S), x2 * E - x1 * S, y2 * E - y1 * S, dd * E,
            z, dd * s2, -(dd * c2), cc]


@_quiet
def expand_compact(M, compact, idx=None):
    """In place: the exits held compactly (compact 1: the 6 factors and (E, S) in rows 0-7) of M (16, n)
    written whole (`_factored`), their flags cleared; idx given: those exits only."""
    sel = np.flatnonzero(compact) if idx is None else np.asarray(idx)[compact[idx] != 0]
    if not sel.size:
        return
    r = M[:8, sel]
    M[:, sel] = np.stack(_factored(*r))
    compact[sel] = 0


@_quiet
def exit_columns(F, A, s, k, idx, out, along_z_xy2, compact=None):
    """out (4, K, m) <- the Stokes columns of the rays idx (rows 0..m-1 when None) in the exit frame s' = z x k
    of their directions k (m, 3): rotated by c = s_y k_x - s_x k_y, d = s_z; from the factors F (6, n) of a
    first interaction or, F None, from the columns A (4, K, n).  compact given: records from factors are
    written compactly (factors and (E, S), flag 1), from columns whole (flag 0).  Returns the number of
    rows along z (k_x^2 + k_y^2 < along_z_xy2), left to the caller."""
    if F is None and A is None:
        raise ValueError("exit_columns: neither factors nor columns")
    pick = (lambda a: a) if idx is None else (lambda a: np.take(a, idx, axis=-1))
    kx, ky = k[:, 0], k[:, 1]
    h = kx * kx
    h += ky * ky
    along = int(np.count_nonzero(h < F32(along_z_xy2)))
    si = s if idx is None else np.take(s, idx, axis=0)
    c = si[:, 1] * kx - si[:, 0] * ky
    d = np.array(si[:, 2], F32)
    E, S = _double_angle(c, d)
    if F is not None:
        f = [pick(F[r]) for r in range(6)]
        if compact is not None:
            out[0, 0], out[0, 1], out[0, 2], out[0, 3] = f[0], f[1], f[2], f[3]
            out[1, 0], out[1, 1], out[1, 2], out[1, 3] = f[4], f[5], E, S
            compact[:] = 1
            return along
        for e, v in enumerate(_factored(*f, E, S)):
            out[e >> 2, e & 3] = v
        return along
    if compact is not None:
        compact[:] = 0
    a = pick(A)
    out[0] = a[0]
    out[1] = E * a[1] + S * a[2]
    out[2] = a[2] * E - a[1] * S
    out[3] = a[3]
    return along


# ----------------------------------------------------------------------------- facet events


@_quiet
def facet_event(nfx, nfy, nfz, kx, ky, kz, s, ci, n1, n2, A, s_new, scratch, c2, s2, R, T, pR, F_r=None, F_t=None):
    """The polarised event at the facets hit, per ray (real indices n1 -> n2): the facet's basis
    s_new = n x k / |n x k| (the old s where |n x k| < 1e-6: normal incidence), the rotation onto it
    (c2, s2), the interface coefficients R, T (4, n) (`core.fresnel.interface_coefficients_f32`), the columns
    A (4, K, n) rotated in place (A None: the identity, not rotated) and pR = clip((M_R A)_00, 0, 1).
    F_r, F_t (6, n) given (A None: a first interaction keeping both branches): their factors
    R / max(pR, 1e-30), T / max(1 - pR, 1e-30), c2, s2 instead of R, T, c2, s2 (left unwritten)."""
    n = ci.shape[0]
    if n == 0:
        return
    sx, sy, sz = s[:, 0], s[:, 1], s[:, 2]
    u0 = nfy * kz
    u0 -= nfz * ky
    u1 = nfz * kx
    u1 -= nfx * kz
    u2 = nfx * ky
    u2 -= nfy * kx
    c = sx * u0
    c += sy * u1
    c += sz * u2
    d = sx * nfx
    d += sy * nfy
    d += sz * nfz
    sn = u0 * u0
    sn += u1 * u1
    sn += u2 * u2
    np.sqrt(sn, out=sn)
    deg = sn < F32(1e-6)                          # normal incidence on the facet: the basis kept
    if deg.any():
        u0, u1, u2 = (np.where(deg, si, ui) for si, ui in zip((sx, sy, sz), (u0, u1, u2)))
        c = np.where(deg, F32(1), c)
        d = np.where(deg, F32(0), d)
        sn = np.where(deg, F32(1), sn)
    for r, ui in enumerate((u0, u1, u2)):
        np.divide(ui, sn, out=scratch[r])
        s_new[:, r] = scratch[r]
    E, S = _double_angle(c, d)
    Rv, Tv = interface_coefficients_f32(np.asarray(ci), np.asarray(n1), np.asarray(n2))
    if F_r is not None:
        p = np.clip(Rv[0], 0, 1).astype(F32, copy=False)
        pR[:] = p
        inv_r = F32(1) / np.maximum(p, F32(1e-30))
        inv_t = F32(1) / np.maximum(F32(1) - p, F32(1e-30))
        for r in range(4):
            np.multiply(Rv[r], inv_r, out=F_r[r])
            np.multiply(Tv[r], inv_t, out=F_t[r])
        F_r[4], F_r[5], F_t[4], F_t[5] = E, S, E, S
        return
    c2[:], s2[:] = E, S
    for r in range(4):
        R[r] = Rv[r]
        T[r] = Tv[r]
    if A is None:
        pR[:] = np.clip(Rv[0], 0, 1)
        return
    a1 = E * A[1]                                   # the columns' rows 1, 2 rotated: E a1 + S a2, a2 E - a1 S
    a1 += S * A[2]
    a2 = A[2] * E
    a2 -= A[1] * S
    A[1], A[2] = a1, a2
    pR[:] = np.clip(R[0] + R[1] * A[1, 0], 0, 1)


@_quiet
def facet_geometry(ng, k, below, eta_up, eta_dn, n_above, n_below, out, tir, leak):
    """The facets hit, per ray, from Embree's normals ng (n, 3): out (12, n) rows kx, ky, kz, the unit normal
    on the incident side (ng / |ng| with the sign of ng_z, negated below the surface), cos i = |k . n_up|,
    cos t (Snell, 0 past the critical angle), eta = n1 / n2, k . n_up and the indices n1, n2; tir (cos t
    == 0, i.e. sin^2 t >= 1) and leak (k . n_up > 0 is not `below`) as 0 / 1."""
    if k.shape[0] == 0:
        return
    b = below != 0
    gx, gy, gz = ng[:, 0], ng[:, 1], ng[:, 2]
    kx, ky, kz = k[:, 0], k[:, 1], k[:, 2]
    inv = gx * gx
    inv += gy * gy
    inv += gz * gz
    inv = np.copysign(F32(1) / np.sqrt(inv), gz)
    dot = kx * gx
    dot += ky * gy
    dot += kz * gz
    dot *= inv
    sg = np.where(b, -inv, inv)
    ci = np.abs(dot)
    eta = np.where(b, F32(eta_up), F32(eta_dn))
    sin2t = (F32(1) - ci * ci) * (eta * eta)
    ct = F32(1) - sin2t
    ct = np.where(ct < 0, F32(0), ct)
    ct = np.sqrt(ct)
    for r, v in enumerate((kx, ky, kz, gx * sg, gy * sg, gz * sg, ci, ct, eta, dot,
                           np.where(b, F32(n_below), F32(n_above)), np.where(b, F32(n_above), F32(n_below)))):
        out[r] = v
    tir[:] = ct == 0
    leak[:] = (dot > 0) != b


# ----------------------------------------------------------------------------- geometry of a batch


def _fmin_select(a, b):
    """a where b is NaN or a < b, else b (`np.fmin` for ordered values, NaN in b ignored)."""
    return np.where(np.isnan(b) | (a < b), a, b)


def _slab(o, k, hx, hy, zh, zc):
    """(tx, ty, tz): ((copysign(h, k) - o) + c) / k per component, h = (hx, hy, zh), c = (0, 0, zc)."""
    return tuple(((np.copysign(F32(h), k[:, j]) - o[:, j]) + F32(c)) / k[:, j]
                 for j, (h, c) in enumerate(((hx, 0), (hy, 0), (zh, zc))))


@_quiet
def slab_distances(o, k, hx, hy, zh, zc, T, t_lat, tfar):
    """Distances along k from o to the tile's sides and the slab's faces: T (3, n) rows tx, ty, tz,
    t_lat = fmin(tx, ty), tfar = max(fmin(t_lat, tz), 0)."""
    if k.shape[0] == 0:
        return
    tx, ty, tz = _slab(o, k, hx, hy, zh, zc)
    T[0], T[1], T[2] = tx, ty, tz
    tl = _fmin_select(tx, ty)
    t_lat[:] = tl
    tf = _fmin_select(tl, tz)
    tfar[:] = np.where(tf < 0, F32(0), tf)


@_quiet
def slab_far(o, k, hx, hy, zh, zc, tfar, lat_first):
    """`slab_distances`' tfar and whether a tile side comes first (t_lat < tz), the distances not kept."""
    if k.shape[0] == 0:
        return
    tx, ty, tz = _slab(o, k, hx, hy, zh, zc)
    tl = _fmin_select(tx, ty)
    lat_first[:] = tl < tz
    tf = _fmin_select(tl, tz)
    tfar[:] = np.where(tf < 0, F32(0), tf)


@_quiet
def classify_misses(hit, lat_first, k, below, above_code, below_code, leak_code, exit_idx, exit_state, wrap_idx):
    """The rays that hit nothing, in order, sorted into those that leave through a slab face (indices, and
    states: above_code going up, below_code going down, leak_code going away from the side the ray was on)
    and those that reached a tile side first (wrap_idx); returns (exits, wraps)."""
    miss = hit == 0
    lat = lat_first != 0
    wi = np.flatnonzero(miss & lat)
    ei = np.flatnonzero(miss & ~lat)
    up = k[ei, 2] > 0
    st = np.where(up == (below[ei] != 0), np.int8(leak_code), np.where(up, np.int8(above_code), np.int8(below_code)))
    exit_idx[:ei.size], exit_state[:ei.size], wrap_idx[:wi.size] = ei, st, wi
    return ei.size, wi.size


@_quiet
def beam_origins(ix, iy, jit, sx, hx, sy, hy, z, o):
    """Origins of a chunk's rays in their strata: ((ix + jit_0) sx - hx, (iy + jit_1) sy - hy, z), computed in
    float64 and rounded to float32."""
    o[:, 0] = (ix + jit[:, 0]) * float(sx) - float(hx)
    o[:, 1] = (iy + jit[:, 1]) * float(sy) - float(hy)
    o[:, 2] = F32(z)


def _subtile(px, py, hx, hy, half_x, half_y, scale_x, scale_y, mirrored, gx, gy):
    """The sub-tile ix + iy gx of points (px, py): u = p + h, folded (half - |u - half|) on a mirror-extended
    tile, truncated u * scale clipped to the grid (float32 and int32 operations)."""
    ux, uy = px + F32(hx), py + F32(hy)
    if mirrored:
        ux = F32(half_x) - np.abs(ux - F32(half_x))
        uy = F32(half_y) - np.abs(uy - F32(half_y))
    ix = np.clip((ux * F32(scale_x)).astype(np.int32), 0, gx - 1)
    iy = np.clip((uy * F32(scale_y)).astype(np.int32), 0, gy - 1)
    return (ix + iy * np.int32(gx)).astype(np.int32)


@_quiet
def subtile_index(p, hx, hy, half_x, half_y, scale_x, scale_y, mirrored, gx, gy, out):
    """Sub-tile iy * gx + ix of each point p (n, >= 2) (`_subtile`)."""
    out[:] = _subtile(p[:, 0], p[:, 1], hx, hy, half_x, half_y, scale_x, scale_y, mirrored, gx, gy)


# ----------------------------------------------------------------------------- gathers, new rays


@_quiet
def gather_records(idx, k, w, nb, ids, k_out, w_out, nb_out, ids_out):
    """Rows idx of the rays' direction, weight, bounce count and id into an exit record's slot."""
    np.take(k, idx, axis=0, out=k_out, mode="clip")     # "clip": no bounds-check buffer (indices in range)
    np.take(w, idx, out=w_out, mode="clip")
    np.take(nb, idx, out=nb_out, mode="clip")
    np.take(ids, idx, out=ids_out, mode="clip")


@_quiet
def gather_rays(idx, o, k, below, w, nb, ids, o_out, k_out, below_out, w_out, nb_out, ids_out):
    """Rows idx of a batch's origins, directions, side, weight, bounce count and id."""
    for a, out in ((o, o_out), (k, k_out)):
        np.take(a, idx, axis=0, out=out, mode="clip")
    for a, out in ((below, below_out), (w, w_out), (nb, nb_out), (ids, ids_out)):
        np.take(a, idx, out=out, mode="clip")


@_quiet
def split_rays(kx, ky, kz, nfx, nfy, nfz, eta, ci, ct, th, o, eps, p, o_r, k_r, o_t, k_t, grid=None, ids=None,
               group=None):
    """Both branches of the rays' first interaction: the hit point p = k th + o (kept when p is given), the
    reflected direction 2 ci nf + k and origin p + eps nf, the refracted direction v / |v|,
    v = eta k + (eta ci - ct) nf, and origin p - eps nf; grid given: the sub-tile of each hit point into
    group[ids]."""
    eps = F32(eps)
    pts = [kc * th + o[:, j] for j, kc in enumerate((kx, ky, kz))]
    if p is not None:
        for j in range(3):
            p[:, j] = pts[j]
    if grid is not None:
        group[ids] = _subtile(pts[0], pts[1], *grid)
    b = F32(2) * ci
    bt = eta * ci - ct
    v = [eta * kc + bt * nc for kc, nc in zip((kx, ky, kz), (nfx, nfy, nfz))]
    nr = np.sqrt((v[0] * v[0] + v[1] * v[1]) + v[2] * v[2])
    for j, (kc, nc) in enumerate(zip((kx, ky, kz), (nfx, nfy, nfz))):
        k_r[:, j] = b * nc + kc
        o_r[:, j] = pts[j] + eps * nc
        k_t[:, j] = v[j] / nr
        o_t[:, j] = pts[j] - eps * nc


@_quiet
def split_weights(w, pR, below, ids, nb, n0, w_r, w_t, below_t, ids_t, nb_next):
    """The scalars of both branches of the rays' first interaction: w pR, w (1 - pR), not below, ids + n0,
    nb + 1; returns how many rays transmit something (pR < 1)."""
    np.multiply(w, pR, out=w_r)
    np.multiply(w, F32(1) - pR, out=w_t)
    below_t[:] = below == 0
    np.add(ids, n0, out=ids_t)
    np.add(nb, np.int16(1), out=nb_next)
    return int(np.count_nonzero(pR < 1))
