# cython: language_level=3, boundscheck=False, wraparound=False, cdivision=True, initializedcheck=False
"""Compiled kernels of the ray engine (package doc): C loops over rays, the GIL released.

Every kernel repeats the float32 / float64 operations of the numpy code it replaces, in the same
order (its docstring names that code), so that the results are bit for bit the same; the module is
compiled with -ffp-contract=off (no fused multiply-add).
"""

from libc.math cimport INFINITY, isfinite, sqrtf
from libc.float cimport FLT_MAX

cdef extern from *:
    void prefetch_write "__builtin_prefetch"(const void *addr, int rw, int locality) nogil

cdef enum:
    PREFETCH_AHEAD = 16       # exits ahead: the sums of a cell come from memory (a table's sums exceed L2)


def bin_cells(const int[::1] cell, const float[::1] w, const float[:, :] M,
              double[::1] sum_w, double[::1] sum_w2, double[:, ::1] sum_M):
    """Add each exit i with cell[i] >= 0 to its cell: sum_w[c] += w, sum_w2[c] += w^2 (float64) and, when M
    (16, n) is given, sum_M[c, e] += M[e, i] w (the float32 product, summed in float64).

    One pass over the exits in their order: the sums of `np.bincount(cell, weights)` per component, which
    also adds in input order (`bsdf.builder.CellAccumulator.add`), without its 16 passes and temporaries.
    """
    cdef Py_ssize_t n = cell.shape[0], i, e
    cdef int c, cn
    cdef float wi
    cdef double wd
    cdef bint polarized = M is not None
    if w.shape[0] != n or (polarized and (M.shape[0] != 16 or M.shape[1] != n or sum_M.shape[1] != 16)):
        raise ValueError("bin_cells: inconsistent shapes")
    with nogil:
        for i in range(n):
            if polarized and i + PREFETCH_AHEAD < n:
                cn = cell[i + PREFETCH_AHEAD]
                if cn >= 0:
                    prefetch_write(&sum_M[cn, 0], 1, 3)
                    prefetch_write(&sum_M[cn, 8], 1, 3)
            c = cell[i]
            if c < 0:
                continue
            wi = w[i]
            wd = <double>wi
            sum_w[c] += wd
            sum_w2[c] += wd * wd
            if polarized:
                for e in range(16):
                    sum_M[c, e] += <double>(M[e, i] * wi)


# ----------------------------------------------------------------------------- Stokes frames


cdef inline void double_angle(float c, float d, float *c2, float *s2) noexcept nogil:
    """(cos 2psi, sin 2psi) from c, d as `core.stokes.double_angle_cd`: (c^2 - d^2) / r, 2 c d / r, r = 0 -> 1."""
    cdef float cc = c * c, dd = d * d
    cdef float r = cc + dd
    if r == 0:
        r = 1
    cdef float sn = c * d
    sn = sn + sn
    s2[0] = sn / r
    c2[0] = (cc - dd) / r


def exit_columns(const float[:, :] F, const float[:, :, :] A, const float[:, :] s, const float[:, :] k,
                 const long[::1] idx, float[:, :, :] out, float along_z_xy2):
    """out (4, K, m) <- the Stokes columns of the rays idx (rows 0..m-1 when idx is None) in the exit frame
    s' = z x k / |z x k| of their exit directions k (m, 3); s (n, 3) the rays' bases.  From the factors F
    (6, n) of a first interaction (`transport.exit_columns_of_factors`) or, F None, from the columns A
    (4, K, n) (gathered and rotated: `core.stokes.rotate_stokes_columns_cd`), with the rotation's
    c = s_y k_x - s_x k_y, d = s_z of `transport.StokesCarrier.exit_columns`.  Rows whose k is along z
    (k_x^2 + k_y^2 < along_z_xy2) take the fallback azimuth's frame, which this kernel leaves to the
    caller: it returns their number (their rows written with the generic frame, to be overwritten).
    """
    cdef Py_ssize_t m = k.shape[0], K = out.shape[1], j, i, col
    cdef bint factored = F is not None, gather = idx is not None
    cdef float kx, ky, c, d, E, S, a, b, cc, dd, c2, s2, x1, x2, a1, a2
    cdef Py_ssize_t along = 0
    if out.shape[0] != 4 or out.shape[2] != m or (gather and idx.shape[0] != m) or (factored and K != 4):
        raise ValueError("exit_columns: inconsistent shapes")
    if not factored and A is None:
        raise ValueError("exit_columns: neither factors nor columns")
    with nogil:
        for j in range(m):
            i = idx[j] if gather else j
            kx = k[j, 0]
            ky = k[j, 1]
            if kx * kx + ky * ky < along_z_xy2:
                along += 1
            c = s[i, 1] * kx - s[i, 0] * ky
            d = s[i, 2]
            double_angle(c, d, &E, &S)
            if factored:                      # the entries of `exit_columns_of_factors`, in its operations
                a = F[0, i]
                b = F[1, i]
                cc = F[2, i]
                dd = F[3, i]
                c2 = F[4, i]
                s2 = F[5, i]
                out[0, 0, j] = a
                out[0, 1, j] = b * c2
                out[0, 2, j] = b * s2
                out[0, 3, j] = 0
                out[3, 0, j] = 0
                out[3, 1, j] = dd * s2
                out[3, 2, j] = -(dd * c2)
                out[3, 3, j] = cc
                out[1, 0, j] = E * b
                out[2, 0, j] = -(b * S)
                out[1, 3, j] = S * dd
                out[2, 3, j] = dd * E
                x1 = a * c2
                x2 = -(cc * s2)
                out[1, 1, j] = E * x1 + S * x2
                out[2, 1, j] = x2 * E - x1 * S
                x1 = a * s2
                x2 = cc * c2
                out[1, 2, j] = E * x1 + S * x2
                out[2, 2, j] = x2 * E - x1 * S
            else:                             # gathered columns, rows 1 and 2 rotated
                for col in range(K):
                    a1 = A[1, col, i]
                    a2 = A[2, col, i]
                    out[0, col, j] = A[0, col, i]
                    out[1, col, j] = E * a1 + S * a2
                    out[2, col, j] = a2 * E - a1 * S
                    out[3, col, j] = A[3, col, i]
    return along


# ----------------------------------------------------------------------------- facet events


cdef inline float nan_to_num(float x) noexcept nogil:
    """np.nan_to_num for float32: NaN -> 0, +-inf -> +-FLT_MAX."""
    if x != x:
        return 0
    if x == INFINITY:
        return FLT_MAX
    if x == -INFINITY:
        return -FLT_MAX
    return x


cdef inline float clip01(float x) noexcept nogil:
    """np.clip(x, 0, 1) (NaN stays NaN)."""
    if x < 0:
        return 0
    if x > 1:
        return 1
    return x


cdef void interface_coefficients(float ci, float n1, float n2, float *R, float *T) noexcept nogil:
    """Mueller coefficients R = (aR, bR, cR, dR), T = (aT, bT, cT, dT) of a facet between real indices n1 -> n2
    at cos i = ci: `core.fresnel.interface_coefficients_f32` (real branch, total internal reflection
    included) operation by operation in float32."""
    cdef float q = n1 / n2, x = 1 - ci * ci
    if x < 0:                                        # np.maximum(0, x)
        x = 0
    cdef float sin2_t = (q * q) * x
    cdef bint tir = sin2_t >= 1
    x = 1 - sin2_t
    if x < 0:
        x = 0
    cdef float ct = sqrtf(x)
    cdef float a = n1 * ci, b = n2 * ct, c = n2 * ci, d = n1 * ct
    cdef float rs = (a - b) / (a + b), rp = (c - d) / (c + d)
    cdef float aR = <float>0.5 * (rs * rs + rp * rp), bR = <float>0.5 * (rs * rs - rp * rp), cR = rs * rp, dR = 0
    cdef float ts = (2 * a) / (a + b), tp = (2 * a) / (c + d)
    cdef float cT = ((b / a) * ts) * tp
    cdef float aT = 1 - aR, bT = -bR
    cdef float g, A1, B1, P1, Q1, den, ab, pq
    if tir:                                          # `fresnel._total_internal_reflection`
        x = sin2_t - 1
        if x < 0:
            x = 0
        g = sqrtf(x)
        A1 = n1 * ci
        B1 = n2 * g
        P1 = n2 * ci
        Q1 = n1 * g
        den = (A1 * A1 + B1 * B1) * (P1 * P1 + Q1 * Q1)
        ab = A1 * A1 - B1 * B1
        pq = P1 * P1 - Q1 * Q1
        aR = 1
        bR = 0
        cR = (ab * pq + (((4 * A1) * B1) * P1) * Q1) / den
        dR = ((((2 * P1) * Q1) * ab) - (((2 * A1) * B1) * pq)) / den
        aT = 0
        bT = 0
        cT = 0
    if tir or not isfinite(cT):
        cT = 0
    R[0] = nan_to_num(aR)
    R[1] = nan_to_num(bR)
    R[2] = nan_to_num(cR)
    R[3] = dR
    T[0] = aT
    T[1] = bT
    T[2] = cT
    T[3] = 0


def facet_event(const float[::1] nfx, const float[::1] nfy, const float[::1] nfz, const float[::1] kx,
                const float[::1] ky, const float[::1] kz, const float[:, :] s, const float[::1] ci,
                const unsigned char[::1] below, float n_above, float n_below, float[:, :, :] A,
                float[:, ::1] s_new, float[::1] c2, float[::1] s2, float[:, :] R, float[:, :] T,
                float[::1] pR):
    """The polarised event at the facets hit (`transport.StokesCarrier.reflectance`, real indices), per ray:
    the facet's basis s_new = n x k / |n x k| (the old s where |n x k| < 1e-6: normal incidence), the
    rotation's (cos 2psi, sin 2psi) onto it (c2, s2), the interface coefficients R (4, n), T (4, n) from
    n1, n2 = (n_below, n_above) below the surface, (n_above, n_below) above; the columns A (4, K, n)
    rotated in place (None: the identity, a first interaction, not rotated) and the reflectance of
    column 0's state pR = clip((M_R A)_00, 0, 1).  The float32 operations of the numpy code, in order.
    """
    cdef Py_ssize_t n = ci.shape[0], i, col, K = 0 if A is None else A.shape[1]
    cdef bint rotate = A is not None
    cdef float u0, u1, u2, sx, sy, sz, c, d, sn, n1, n2, a1, a2, E, S
    cdef float Rv[4]
    cdef float Tv[4]
    if s_new.shape[0] != n or R.shape[1] != n or T.shape[1] != n or (rotate and A.shape[2] != n):
        raise ValueError("facet_event: inconsistent shapes")
    with nogil:
        for i in range(n):
            u0 = nfy[i] * kz[i] - nfz[i] * ky[i]
            u1 = nfz[i] * kx[i] - nfx[i] * kz[i]
            u2 = nfx[i] * ky[i] - nfy[i] * kx[i]
            sx = s[i, 0]
            sy = s[i, 1]
            sz = s[i, 2]
            c = (sx * u0 + sy * u1) + sz * u2
            d = (sx * nfx[i] + sy * nfy[i]) + sz * nfz[i]
            sn = sqrtf((u0 * u0 + u1 * u1) + u2 * u2)
            if sn < <float>1e-6:
                sn = 1
                u0 = sx
                u1 = sy
                u2 = sz
                c = 1
                d = 0
            s_new[i, 0] = u0 / sn
            s_new[i, 1] = u1 / sn
            s_new[i, 2] = u2 / sn
            double_angle(c, d, &E, &S)
            c2[i] = E
            s2[i] = S
            if below[i]:
                n1 = n_below
                n2 = n_above
            else:
                n1 = n_above
                n2 = n_below
            interface_coefficients(ci[i], n1, n2, Rv, Tv)
            for col in range(4):
                R[col, i] = Rv[col]
                T[col, i] = Tv[col]
            if rotate:
                for col in range(K):
                    a1 = A[1, col, i]
                    a2 = A[2, col, i]
                    A[1, col, i] = E * a1 + S * a2
                    A[2, col, i] = a2 * E - a1 * S
                pR[i] = clip01(Rv[0] + Rv[1] * A[1, 0, i])
            else:
                pR[i] = clip01(Rv[0])
