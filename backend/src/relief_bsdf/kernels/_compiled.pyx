# cython: language_level=3, boundscheck=False, wraparound=False, cdivision=True, initializedcheck=False
"""Compiled kernels of the ray engine (package doc): C loops over rays, the GIL released.

Every kernel repeats the float32 / float64 operations of the numpy code it replaces, in the same
order (its docstring names that code), so that the results are bit for bit the same: every literal in
float arithmetic is cast (<float>2): Cython writes a bare 2 as the double 2.0, which turns a chain of
float32 operations into double ones with other roundings.  The module is
compiled with -ffp-contract=off (no fused multiply-add), -fno-tree-slp-vectorize (gcc packs the x and
y components of a ray into one SSE division whose unused lanes divide garbage, with microcode assists
for denormals: 4x slower than numpy), and -fno-math-errno -fno-trapping-math (no value changes; they
let gcc if-convert and vectorise `facet_loop`, whose ~12 divisions and square roots per ray bound a
scalar loop).
"""

from libc.math cimport INFINITY, copysignf, fabs, fabsf, sqrt, sqrtf
from libc.float cimport FLT_MAX
from cython.view cimport array as cvarray

cdef extern from *:
    void prefetch_write "__builtin_prefetch"(const void *addr, int rw, int locality) nogil

cdef extern from *:
    """
    typedef float *__restrict__ f32_out;
    typedef const float *__restrict__ f32_in;
    typedef unsigned char *__restrict__ u8_out;
    """
    ctypedef float *f32_out             # restrict pointers (as parameters: gcc honours restrict there only):
    ctypedef const float *f32_in        # no run-time aliasing checks, so gcc vectorises the loops
    ctypedef unsigned char *u8_out

cdef extern from *:
    """
    #if defined(__SSE2__)
    #include <emmintrin.h>
    /* sum[4 r + 0..3] += (double)(row * w): four float32 products converted exactly to float64 and added,
       entry by entry IEEE operations (no fused multiply-add): the numbers of the scalar form */
    static inline void relief_add4(double *sum, __m128 row, __m128 wv) {
        __m128 p = _mm_mul_ps(row, wv);
        _mm_storeu_pd(sum, _mm_add_pd(_mm_loadu_pd(sum), _mm_cvtps_pd(p)));
        _mm_storeu_pd(sum + 2, _mm_add_pd(_mm_loadu_pd(sum + 2), _mm_cvtps_pd(_mm_movehl_ps(p, p))));
    }
    #define RELIEF_ROW(x0, x1, x2, x3) _mm_set_ps((x3), (x2), (x1), (x0))
    #endif
    /* sum[e] += (double)(m[e] * w), e = 0..15, m[e] the e-th of 16 rows `stride` floats apart */
    static inline void relief_add_rows16(double *sum, const float *m, Py_ssize_t stride, float w) {
    #if defined(__SSE2__)
        __m128 wv = _mm_set1_ps(w);
        for (int r = 0; r < 4; r++) {
            const float *q = m + 4 * r * stride;
            relief_add4(sum + 4 * r, RELIEF_ROW(q[0], q[stride], q[2 * stride], q[3 * stride]), wv);
        }
    #else
        for (int e = 0; e < 16; e++) sum[e] += (double)(m[e * stride] * w);
    #endif
    }
    /* The 16 entries o0..o15 (row-major: o[4 i + j] is column j's Stokes component i) of Rot_exit (M Rot / p)
       from the factors (a, b, cc, dd, c2, s2) of a first interaction and the exit rotation (E, S) = (cos 2psi',
       sin 2psi'): `transport.exit_columns_of_factors`, operation by operation in float32 (the one C
       definition, for the whole and the compact records) */
    #define RELIEF_FACTORED16(a, b, cc, dd, c2, s2, E, S) \
        float x1 = (a) * (c2), x2 = -((cc) * (s2)), y1 = (a) * (s2), y2 = (cc) * (c2); \
        float o0 = (a), o1 = (b) * (c2), o2 = (b) * (s2), o3 = 0.0f; \
        float o4 = (E) * (b), o5 = (E) * x1 + (S) * x2, o6 = (E) * y1 + (S) * y2, o7 = (S) * (dd); \
        float o8 = -((b) * (S)), o9 = x2 * (E) - x1 * (S), o10 = y2 * (E) - y1 * (S), o11 = (dd) * (E); \
        float o12 = 0.0f, o13 = (dd) * (s2), o14 = -((dd) * (c2)), o15 = (cc);
    static inline void relief_factored_columns(float a, float b, float cc, float dd, float c2, float s2, float E,
                                               float S, float *o) {
        RELIEF_FACTORED16(a, b, cc, dd, c2, s2, E, S)
        o[0] = o0; o[1] = o1; o[2] = o2; o[3] = o3; o[4] = o4; o[5] = o5; o[6] = o6; o[7] = o7;
        o[8] = o8; o[9] = o9; o[10] = o10; o[11] = o11; o[12] = o12; o[13] = o13; o[14] = o14; o[15] = o15;
    }
    /* sum[e] += (double)(o[e] * w) for those 16 entries, kept in registers */
    static inline void relief_add_factored16(double *sum, float a, float b, float cc, float dd, float c2,
                                             float s2, float E, float S, float w) {
        RELIEF_FACTORED16(a, b, cc, dd, c2, s2, E, S)
    #if defined(__SSE2__)
        __m128 wv = _mm_set1_ps(w);
        relief_add4(sum, RELIEF_ROW(o0, o1, o2, o3), wv);
        relief_add4(sum + 4, RELIEF_ROW(o4, o5, o6, o7), wv);
        relief_add4(sum + 8, RELIEF_ROW(o8, o9, o10, o11), wv);
        relief_add4(sum + 12, RELIEF_ROW(o12, o13, o14, o15), wv);
    #else
        float o[16] = {o0, o1, o2, o3, o4, o5, o6, o7, o8, o9, o10, o11, o12, o13, o14, o15};
        for (int e = 0; e < 16; e++) sum[e] += (double)(o[e] * w);
    #endif
    }
    """
    void add_rows16 "relief_add_rows16"(double *sum, const float *m, Py_ssize_t stride, float w) nogil
    void add_factored16 "relief_add_factored16"(double *sum, float a, float b, float cc, float dd, float c2,
                                                float s2, float E, float S, float w) nogil
    void factored_columns "relief_factored_columns"(float a, float b, float cc, float dd, float c2, float s2,
                                                    float E, float S, float *o) nogil

cdef enum:
    PREFETCH_AHEAD = 16       # exits ahead: the sums of a cell come from memory (a table's sums exceed L2)


def bin_cells(const int[::1] cell, const float[::1] w, const float[:, :] M,
              double[::1] sum_w, double[::1] sum_w2, double[:, ::1] sum_M,
              const int[::1] group=None, int[::1] keys=None, float[::1] w_keys=None,
              const unsigned char[::1] compact=None, const long[::1] path_ids=None, long n_paths=0):
    """Add each exit i with cell[i] >= 0 to its cell: sum_w[c] += w, sum_w2[c] += w^2 (float64) and, when M
    (16, n) is given, sum_M[c, e] += M[e, i] w (the float32 product, summed in float64).  With group (the
    sub-tile of each exit's path), the binned exits' keys group * cells + cell and float64 weights are
    written in order into keys (int32) and w_keys (the float32 weights, exact in float64) (`CellAccumulator._group_parts`);
    returns how many.

    One pass over the exits in their order: the sums of `np.bincount(cell, weights)` per component, which
    also adds in input order (`bsdf.builder.CellAccumulator.add`), without its 16 passes and temporaries.
    compact (n,): exits whose M holds the compact form of `exit_columns` (flag 1) are expanded on the fly
    (`factored_columns`: the entries the whole form would hold, so the same sums).  path_ids (n,) given: group
    holds the sub-tile of each path (n_paths) and exit i's is group[path_ids[i] mod n_paths] (the first-hit
    split's transmitted branch has id + n_paths: `bsdf.builder.ExitSamples.groups`).
    """
    cdef Py_ssize_t n = cell.shape[0], i, e, j = 0, nc = sum_w.shape[0]
    cdef int c, cn
    cdef float wi
    cdef double wd
    cdef float o[16]
    cdef bint polarized = M is not None, grouped = group is not None, short = compact is not None
    cdef bint by_path = path_ids is not None
    cdef long pid
    cdef Py_ssize_t ms = 0 if M is None else M.strides[0] // sizeof(float)
    if polarized and M.shape[1] > 1 and M.strides[1] != sizeof(float):      # (a lone exit: any stride)
        raise ValueError("bin_cells: the Mueller rows must be contiguous")
    if w.shape[0] != n or (polarized and (M.shape[0] != 16 or M.shape[1] != n or sum_M.shape[1] != 16)) or (
            grouped and ((group.shape[0] != n and not by_path) or keys is None or w_keys is None or keys.shape[0] < n
                         or w_keys.shape[0] < n)) or (short and (not polarized or compact.shape[0] != n)) or (
            by_path and (not grouped or path_ids.shape[0] != n or n_paths <= 0 or group.shape[0] < n_paths)):
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
            if grouped:
                if by_path:
                    pid = path_ids[i]
                    pid = pid - n_paths if pid >= n_paths else pid
                    keys[j] = <int>(group[pid] * nc + c)
                else:
                    keys[j] = <int>(group[i] * nc + c)
                w_keys[j] = wi
                j += 1
            if polarized:                            # sum_M[c, e] += <double>(M_e * wi), e = 0..15
                if short and compact[i]:
                    add_factored16(&sum_M[c, 0], M[0, i], M[1, i], M[2, i], M[3, i], M[4, i], M[5, i], M[6, i],
                                   M[7, i], wi)
                else:
                    add_rows16(&sum_M[c, 0], &M[0, i], ms, wi)
    return j


def direction_parts(const float[:, :] k, float[::1] az, float[::1] kx, float[::1] ky):
    """az = min(|k_z|, 1) (NaN kept) and the contiguous components k_x, k_y of directions k (n, 3): the inputs of
    numpy's arccos and arctan2 in `bsdf.builder.CellIndex.with_side` (numpy's SIMD loops run on contiguous
    arrays only; on an (n, 3) array's columns arctan2 is ~3x slower)."""
    cdef Py_ssize_t n = k.shape[0], i
    cdef float z
    if az.shape[0] != n or kx.shape[0] != n or ky.shape[0] != n or k.shape[1] != 3:
        raise ValueError("direction_parts: inconsistent shapes")
    with nogil:
        for i in range(n):
            z = fabsf(k[i, 2])
            az[i] = 1 if z > 1 else z
            kx[i] = k[i, 0]
            ky[i] = k[i, 1]


def cells_of_angles(const float[::1] x, const float[::1] y, float t_scale, float t_off, float p_scale, float p_off,
                    const int[::1] ring_lut, const int[::1] az_lut, int n_az, const signed char[::1] side,
                    int side_cells, int[::1] out):
    """The cell of each exit from x = arccos min(|k_z|, 1) and y = atan2(k_y, k_x) (numpy's, float32), plus
    side * side_cells, or -1 outside the table: `bsdf.builder.CellIndex.__call__` (uniform edges: scale,
    offset, max 0, truncation, look-up tables indexed as np.take(..., mode="clip")) and
    `CellAccumulator.add`'s side offset in one pass.  The indices are clamped before truncation, the same
    for every value a direction gives (an index below 2^31); NaN gives index 0, as numpy's cast on x86."""
    cdef Py_ssize_t n = x.shape[0], i
    cdef float xv, yv, rmax = ring_lut.shape[0] - 1, amax = az_lut.shape[0] - 1
    cdef int ib, ia, c
    if y.shape[0] != n or side.shape[0] != n or out.shape[0] != n or rmax < 0 or amax < 0:
        raise ValueError("cells_of_angles: inconsistent shapes")
    with nogil:
        for i in range(n):
            xv = x[i] * t_scale
            xv = xv + t_off
            xv = xv if xv > 0 else 0                  # max 0 (NaN -> 0), clipped
            xv = rmax if xv > rmax else xv
            yv = y[i] * p_scale
            yv = yv + p_off
            yv = yv if yv > 0 else 0
            yv = amax if yv > amax else yv
            ib = ring_lut[<int>xv]
            ia = az_lut[<int>yv]
            c = ib * n_az + ia + side[i] * side_cells
            out[i] = -1 if (ib | ia) < 0 else c
    return None


# atan on [-tan(pi/8), tan(pi/8)] as u P(u^2): a least-squares fit of degree 11 whose largest error over
# 4e6 points of that interval is 1.2e-10 rad, evaluated in float32 (decision record 014: < 1.5e-6 rad in all)
cdef float ATAN_C0 = 0.9999999961633618, ATAN_C1 = -0.3333326985635032, ATAN_C2 = 0.19996982348496437
cdef float ATAN_C3 = -0.1422361730442797, ATAN_C4 = 0.10477428280503895, ATAN_C5 = -0.05831076666384826
cdef float TAN_PI8 = 0.41421356237309503, PI_4 = 0.7853981633974483, PI_2 = 1.5707963267948966
cdef float PI_1 = 3.141592653589793


cdef inline float atan_quadrant(float ay, float ax) noexcept nogil:
    """atan(ay / ax) in [0, pi/2] for ay, ax >= 0 (NaN for 0 / 0): the ratio of the smaller to the larger,
    reduced past tan(pi/8) by atan t = pi/4 + atan((t - 1) / (t + 1)), the polynomial, then pi/2 - a when
    swapped; float32, about 12 roundings of numbers below pi: within 1.5e-6 rad of atan."""
    cdef bint swap = ay > ax
    cdef float num = ax if swap else ay
    cdef float den = ay if swap else ax
    cdef float t = num / den
    cdef bint big = t > TAN_PI8
    cdef float u = (t - <float>1) / (t + <float>1) if big else t
    cdef float u2 = u * u
    cdef float q = ((((ATAN_C5 * u2 + ATAN_C4) * u2 + ATAN_C3) * u2 + ATAN_C2) * u2 + ATAN_C1) * u2 + ATAN_C0
    cdef float a = u * q
    a = a + PI_4 if big else a
    return PI_2 - a if swap else a


cdef inline int angle_index(float a, float scale, float off, float amax) noexcept nogil:
    """The look-up index of angle a (float32): `cells_of_angles`' operations (scale, offset, max 0, clip,
    truncation), non-decreasing in a."""
    cdef float v = a * scale
    v = v + off
    v = v if v > 0 else 0
    v = amax if v > amax else v
    return <int>v


cdef extern from *:
    """
    typedef int *__restrict__ i32_out;
    """
    ctypedef int *i32_out


cdef void direction_indices(Py_ssize_t n, f32_in k, Py_ssize_t sk, Py_ssize_t ck, float margin, float t_scale,
                            float t_off, float rmax, float p_scale, float p_off, float amax, i32_out ring,
                            i32_out az) noexcept nogil:
    """The look-up indices of `cells_of_directions` (ring, az), -1 in ring where the direction is left to numpy's
    angles (restrict pointers, selects only: the loop vectorises, four directions at a time)."""
    cdef Py_ssize_t i
    cdef float kx, ky, z, th, ph
    cdef int ib0, ib1, ia0, ia1
    cdef bint ok
    for i in range(n):
        kx = k[i * sk]
        ky = k[i * sk + ck]
        z = fabsf(k[i * sk + 2 * ck])
        z = 1 if z > 1 else z
        th = atan_quadrant(sqrtf((<float>1 - z) * (<float>1 + z)), z)
        ph = atan_quadrant(fabsf(ky), fabsf(kx))
        ph = PI_1 - ph if kx < 0 else ph
        ph = -ph if ky < 0 else ph
        ib0 = angle_index(th - margin, t_scale, t_off, rmax)
        ib1 = angle_index(th + margin, t_scale, t_off, rmax)
        ia0 = angle_index(ph - margin, p_scale, p_off, amax)
        ia1 = angle_index(ph + margin, p_scale, p_off, amax)
        ok = (th == th) & (ph == ph) & (ky != 0) & (ib0 == ib1) & (ia0 == ia1)
        ring[i] = ib0 if ok else -1
        az[i] = ia0


def cells_of_directions(const float[:, :] k, float t_scale, float t_off, float p_scale, float p_off,
                        const int[::1] ring_lut, const int[::1] az_lut, int n_az, const signed char[::1] side,
                        int side_cells, float margin, int[::1] out, long[::1] exact):
    """The cells of `cells_of_angles` straight from directions k (n, 3), without numpy's arccos and arctan2
    where they cannot matter.  Per direction the polar angle arccos min(|k_z|, 1) = atan2(sqrt((1 - z)(1 + z)),
    z) and the azimuth atan2(k_y, k_x) (`atan_quadrant`, float32: within 2e-6 rad of the true angles); numpy's
    float32 arccos and arctan2 (a few ulps) lie within margin (radians, >> both errors) of them, and the look-up
    index is non-decreasing in the angle, so where the indices of angle - margin and angle + margin agree
    they are the index of numpy's angle: out holds the cell (side * side_cells added, -1 outside the table).
    The others (an angle within margin of a cell edge, NaN, k_y = 0 where atan2 follows the sign of zero)
    are listed in exact (out -2) for the caller to finish with numpy's functions; returns their number.
    Its twin computes every cell from numpy's angles and lists none: the cells agree where this kernel
    settles them (tests/backend/kernels), and after the caller's finish everywhere."""
    cdef Py_ssize_t n = k.shape[0], i, ne = 0
    cdef float rmax = ring_lut.shape[0] - 1, amax = az_lut.shape[0] - 1
    cdef int ib, ia, r
    if side.shape[0] != n or out.shape[0] != n or exact.shape[0] < n or k.shape[1] != 3 or rmax < 0 or amax < 0:
        raise ValueError("cells_of_directions: inconsistent shapes")
    if n == 0:
        return 0
    cdef int[::1] ring = cvarray(shape=(n,), itemsize=sizeof(int), format="i")
    cdef Py_ssize_t sk = k.strides[0] // sizeof(float), ck = k.strides[1] // sizeof(float)
    with nogil:
        direction_indices(n, &k[0, 0], sk, ck, margin, t_scale, t_off, rmax, p_scale, p_off, amax, &ring[0], &out[0])
        for i in range(n):
            r = ring[i]
            if r < 0:
                exact[ne] = i
                ne += 1
                out[i] = -2
                continue
            ib = ring_lut[r]
            ia = az_lut[out[i]]
            out[i] = -1 if (ib | ia) < 0 else ib * n_az + ia + side[i] * side_cells
    return ne



cdef inline Py_ssize_t count_up_to(const double *a, Py_ssize_t n, const int *lut, Py_ssize_t nb, double scale,
                                   double v) noexcept nogil:
    """np.searchsorted(a[:n], v, side="right") (the number of a[i] <= v) for sorted a and v >= 0 not NaN, from
    a look-up table: lut[j] counts the a[i] <= (j - 1) / scale (none for j = 0), at most those <= v for v in
    bucket j = int(v scale), and the count goes on from there (a few steps: the buckets are finer than the edges)."""
    cdef Py_ssize_t j = <Py_ssize_t>(v * scale)
    j = 0 if j < 0 else (nb - 1 if j >= nb else j)
    cdef Py_ssize_t i = lut[j]
    while i < n and a[i] <= v:
        i += 1
    return i


def cells_of_edges(const float[:, :] k, const double[::1] te_sin2, int last_ring, const int[::1] lut_t, double scale_t,
                   const double[::1] pe_rel, const int[::1] lut_p, double scale_p, double pe0, double margin_deg,
                   const signed char[::1] side, int side_cells, int[::1] out, long[::1] exact):
    """The cells of directions k (n, 3) on searched edges (`builder.CellIndex` for edges that are not uniform:
    rings searched on sin^2 theta, azimuths on the float64 degrees of numpy's float32 arctan2), side * side_cells
    added, -1 outside the table, without numpy's arctan2 where it cannot matter.  The ring is numpy's exactly:
    sin^2 = float64(max(0, 1 - k_z^2)) (float32) counted in te_sin2 (S + 1 edges) as searchsorted(side="right")
    - 1 (`count_up_to`, lut_t over sin^2 in [0, 1] with scale_t buckets per unit), last_ring where sin^2 >= the
    last edge, S (outside) for NaN.  The azimuth v = (degrees(atan2(k_y, k_x)) - pe0) mod 360 from the float32
    `atan_quadrant` (within 2e-6 rad of atan2, as numpy's float32 arctan2 within 1e-6 rad: both far inside
    margin_deg): where v - margin_deg and v + margin_deg fall in one cell of pe_rel (the edges less pe0, A + 1 of
    them; lut_p with scale_p buckets per degree) without crossing 0 or 360 it is the cell of numpy's angle; the
    others (an azimuth within the margin of an edge, k_y = 0 where atan2 follows the sign of zero, NaN) are listed
    in exact (out -2) unless their ring alone puts them outside; returns their number (the caller finishes them
    with numpy's angles).  Its twin computes every cell with numpy and lists none."""
    cdef Py_ssize_t n = k.shape[0], i, ne = 0, ns = te_sin2.shape[0], na = pe_rel.shape[0]
    cdef Py_ssize_t nbt = lut_t.shape[0], nbp = lut_p.shape[0]
    cdef int S = <int>ns - 1, A = <int>na - 1, ib, ia, ia1
    cdef float kz, q, kx, ky, ph
    cdef double sin2, v, deg = 180.0 / 3.141592653589793
    if side.shape[0] != n or out.shape[0] != n or exact.shape[0] < n or k.shape[1] != 3 or S < 1 or A < 1 or \
            nbt < 1 or nbp < 1:
        raise ValueError("cells_of_edges: inconsistent shapes")
    with nogil:
        for i in range(n):
            kx = k[i, 0]
            ky = k[i, 1]
            kz = k[i, 2]
            q = <float>1 - kz * kz
            q = 0 if q < 0 else q
            sin2 = <double>q
            if sin2 != sin2:
                ib = S
            elif sin2 >= te_sin2[ns - 1]:
                ib = last_ring
            else:
                ib = <int>count_up_to(&te_sin2[0], ns, &lut_t[0], nbt, scale_t, sin2) - 1
            if ib < 0 or ib >= S:
                out[i] = -1
                continue
            if ky == 0 or kx != kx or ky != ky:
                exact[ne] = i
                ne += 1
                out[i] = -2
                continue
            ph = atan_quadrant(fabsf(ky), fabsf(kx))
            ph = PI_1 - ph if kx < 0 else ph
            ph = -ph if ky < 0 else ph
            v = <double>ph * deg - pe0
            while v < 0:
                v += 360.0
            while v >= 360.0:
                v -= 360.0
            if v - margin_deg < 0 or v + margin_deg >= 360.0:
                exact[ne] = i
                ne += 1
                out[i] = -2
                continue
            ia = <int>count_up_to(&pe_rel[0], na, &lut_p[0], nbp, scale_p, v - margin_deg) - 1
            ia1 = <int>count_up_to(&pe_rel[0], na, &lut_p[0], nbp, scale_p, v + margin_deg) - 1
            if ia != ia1:
                exact[ne] = i
                ne += 1
                out[i] = -2
                continue
            out[i] = -1 if (ia < 0 or ia >= A) else ib * A + ia + side[i] * side_cells
    return ne

ctypedef fused key_t:
    int
    long

ctypedef fused weight_t:
    float
    double


def add_at(const key_t[::1] keys, const weight_t[::1] w, double[::1] out):
    """out[keys[i]] += w[i] (added in float64) in the order of i: `np.bincount(keys, w)` added into out
    without its temporary (`CellAccumulator.sum_w_group`, batch after batch in merge order: the order of
    the concatenation).  int32 or int64 keys, float32 (`bin_cells`' parts) or float64 weights."""
    cdef Py_ssize_t n = keys.shape[0], i
    if w.shape[0] != n:
        raise ValueError("add_at: inconsistent shapes")
    with nogil:
        for i in range(n):
            out[keys[i]] += <double>w[i]


# ----------------------------------------------------------------------------- Stokes frames


cdef inline void double_angle(float c, float d, float *c2, float *s2) noexcept nogil:
    """(cos 2psi, sin 2psi) from c, d as `core.stokes.double_angle_cd`: (c^2 - d^2) / r, 2 c d / r, r = 0 -> 1."""
    cdef float cc = c * c, dd = d * d
    cdef float r = cc + dd
    r = 1 if r == 0 else r
    cdef float sn = c * d
    sn = sn + sn
    s2[0] = sn / r
    c2[0] = (cc - dd) / r


def exit_columns(const float[:, :] F, const float[:, :, :] A, const float[:, :] s, const float[:, :] k,
                 const long[::1] idx, float[:, :, :] out, float along_z_xy2, unsigned char[::1] compact=None):
    """out (4, K, m) <- the Stokes columns of the rays idx (rows 0..m-1 when idx is None) in the exit frame
    s' = z x k / |z x k| of their exit directions k (m, 3); s (n, 3) the rays' bases.  From the factors F
    (6, n) of a first interaction (`transport.exit_columns_of_factors`) or, F None, from the columns A
    (4, K, n) (gathered and rotated: `core.stokes.rotate_stokes_columns_cd`), with the rotation's
    c = s_y k_x - s_x k_y, d = s_z of `transport.StokesCarrier.exit_columns`.  Rows whose k is along z
    (k_x^2 + k_y^2 < along_z_xy2) take the fallback azimuth's frame, which this kernel leaves to the
    caller: it returns their number (their rows written with the generic frame, to be overwritten).

    compact (m,) given (an exit record's flags, `exits.Exits.compact`): records from factors are written
    compactly, the 6 factors and (E, S) = (cos 2psi', sin 2psi') of the exit rotation in out[0] and out[1]
    (the flat rows 0-7), flag 1, for `bin_cells` / `expand_compact` to expand (`factored_columns`: the same
    numbers); records from columns are written whole, flag 0.
    """
    cdef Py_ssize_t m = k.shape[0], K = out.shape[1], j, i, col, e
    cdef bint factored = F is not None, gather = idx is not None, short = compact is not None
    cdef float kx, ky, c, d, E, S, a1, a2
    cdef float o[16]
    cdef Py_ssize_t along = 0
    if out.shape[0] != 4 or out.shape[2] != m or (gather and idx.shape[0] != m) or (factored and K != 4) or (
            short and compact.shape[0] != m):
        raise ValueError("exit_columns: inconsistent shapes")
    if not factored and A is None:
        raise ValueError("exit_columns: neither factors nor columns")
    if factored and short and m and (out.strides[2] != sizeof(float)):
        raise ValueError("exit_columns: the record's rows must be contiguous")
    with nogil:
        if factored and short:                # compact: the factors, c and d, then (E, S) in a vector pass
            for j in range(m):
                i = idx[j] if gather else j
                kx = k[j, 0]
                ky = k[j, 1]
                if kx * kx + ky * ky < along_z_xy2:
                    along += 1
                out[1, 2, j] = s[i, 1] * kx - s[i, 0] * ky
                out[1, 3, j] = s[i, 2]
                out[0, 0, j] = F[0, i]
                out[0, 1, j] = F[1, i]
                out[0, 2, j] = F[2, i]
                out[0, 3, j] = F[3, i]
                out[1, 0, j] = F[4, i]
                out[1, 1, j] = F[5, i]
                compact[j] = 1
            if m:
                double_angle_rows(m, &out[1, 2, 0], &out[1, 3, 0])
        else:
            for j in range(m):
                i = idx[j] if gather else j
                kx = k[j, 0]
                ky = k[j, 1]
                if kx * kx + ky * ky < along_z_xy2:
                    along += 1
                c = s[i, 1] * kx - s[i, 0] * ky
                d = s[i, 2]
                double_angle(c, d, &E, &S)
                if factored:                       # the entries of `exit_columns_of_factors`
                    factored_columns(F[0, i], F[1, i], F[2, i], F[3, i], F[4, i], F[5, i], E, S, o)
                    for e in range(16):
                        out[e >> 2, e & 3, j] = o[e]
                else:                             # gathered columns, rows 1 and 2 rotated
                    if short:
                        compact[j] = 0
                    for col in range(K):
                        a1 = A[1, col, i]
                        a2 = A[2, col, i]
                        out[0, col, j] = A[0, col, i]
                        out[1, col, j] = E * a1 + S * a2
                        out[2, col, j] = a2 * E - a1 * S
                        out[3, col, j] = A[3, col, i]
    return along


cdef void double_angle_rows(Py_ssize_t n, f32_out cr, f32_out dr) noexcept nogil:
    """In place over rows c, d: (c, d) <- (cos 2psi, sin 2psi) = `double_angle(c, d)` (restrict pointers,
    no branches: the loop vectorises)."""
    cdef Py_ssize_t i
    cdef float E, S
    for i in range(n):
        double_angle(cr[i], dr[i], &E, &S)
        cr[i] = E
        dr[i] = S


def expand_compact(float[:, :] M, unsigned char[::1] compact, const long[::1] idx=None):
    """In place: the exits held compactly (compact[i] 1, `exit_columns`) of M (16, n) written whole (the 16
    entries of `factored_columns`), their flags cleared; idx given: those exits only."""
    cdef Py_ssize_t n = M.shape[1], j, i, e, m = n if idx is None else idx.shape[0]
    cdef float o[16]
    if M.shape[0] != 16 or compact.shape[0] != n:
        raise ValueError("expand_compact: inconsistent shapes")
    with nogil:
        for j in range(m):
            i = j if idx is None else idx[j]
            if not compact[i]:
                continue
            factored_columns(M[0, i], M[1, i], M[2, i], M[3, i], M[4, i], M[5, i], M[6, i], M[7, i], o)
            for e in range(16):
                M[e, i] = o[e]
            compact[i] = 0


# ----------------------------------------------------------------------------- facet events


cdef inline float nan_to_num(float x) noexcept nogil:
    """np.nan_to_num for float32: NaN -> 0, +-inf -> +-FLT_MAX."""
    x = 0 if x != x else x
    x = FLT_MAX if x == INFINITY else x
    return -FLT_MAX if x == -INFINITY else x


cdef inline float clip01(float x) noexcept nogil:
    """np.clip(x, 0, 1) (NaN stays NaN)."""
    x = 0 if x < 0 else x
    return 1 if x > 1 else x


cdef inline void interface_coefficients(float ci, float n1, float n2, float *R, float *T) noexcept nogil:
    """Mueller coefficients R = (aR, bR, cR, dR), T = (aT, bT, cT, dT) of a facet between real indices n1 -> n2
    at cos i = ci: `core.fresnel.interface_coefficients_f32` (real branch, total internal reflection
    included) operation by operation in float32.  Branch-free (both branches computed, one selected), so
    that the loop calling it vectorises."""
    cdef float q = n1 / n2, x = <float>1 - ci * ci
    x = 0 if x < 0 else x                            # np.maximum(0, x) (NaN kept)
    cdef float sin2_t = (q * q) * x
    x = <float>1 - sin2_t
    x = 0 if x < 0 else x
    cdef float ct = sqrtf(x)
    cdef float a = n1 * ci, b = n2 * ct, c = n2 * ci, d = n1 * ct
    cdef float rs = (a - b) / (a + b), rp = (c - d) / (c + d)
    cdef float aR = <float>0.5 * (rs * rs + rp * rp), bR = <float>0.5 * (rs * rs - rp * rp), cR = rs * rp
    cdef float ts = (<float>2 * a) / (a + b), tp = (<float>2 * a) / (c + d)
    cdef float cT = ((b / a) * ts) * tp
    # past the critical angle (`fresnel._total_internal_reflection`)
    x = sin2_t - <float>1
    x = 0 if x < 0 else x
    cdef float g = sqrtf(x)
    cdef float A1 = n1 * ci, B1 = n2 * g, P1 = n2 * ci, Q1 = n1 * g
    cdef float den = (A1 * A1 + B1 * B1) * (P1 * P1 + Q1 * Q1)
    cdef float ab = A1 * A1 - B1 * B1, pq = P1 * P1 - Q1 * Q1
    cdef float cR_tir = (ab * pq + (((<float>4 * A1) * B1) * P1) * Q1) / den
    cdef float dR_tir = ((((<float>2 * P1) * Q1) * ab) - (((<float>2 * A1) * B1) * pq)) / den
    R[0] = 1 if sin2_t >= 1 else nan_to_num(aR)      # sin2_t >= 1: total internal reflection
    R[1] = 0 if sin2_t >= 1 else nan_to_num(bR)
    R[2] = nan_to_num(cR_tir if sin2_t >= 1 else cR)
    R[3] = dR_tir if sin2_t >= 1 else 0
    T[0] = 0 if sin2_t >= 1 else <float>1 - aR
    T[1] = 0 if sin2_t >= 1 else -bR
    cT = 0 if fabsf(cT) > FLT_MAX else cT            # not finite (np.isfinite): infinite here, NaN next
    cT = 0 if cT != cT else cT
    T[2] = 0 if sin2_t >= 1 else cT
    T[3] = 0




def facet_event(const float[::1] nfx, const float[::1] nfy, const float[::1] nfz, const float[::1] kx,
                const float[::1] ky, const float[::1] kz, const float[:, :] s, const float[::1] ci,
                const float[::1] n1, const float[::1] n2, float[:, :, ::1] A, float[:, ::1] s_new,
                float[:, :] scratch, float[::1] c2, float[::1] s2, float[:, :] R, float[:, :] T, float[::1] pR,
                float[:, :] F_r=None, float[:, :] F_t=None):
    """The polarised event at the facets hit (`transport.StokesCarrier.reflectance`, real indices), per ray:
    the facet's basis s_new = n x k / |n x k| (the old s where |n x k| < 1e-6: normal incidence), the
    rotation's (cos 2psi, sin 2psi) onto it (c2, s2), the interface coefficients R (4, n), T (4, n) from
    the indices n1 -> n2 of each ray (`facet_geometry`); the columns A (4, K, n)
    rotated in place (None: the identity, a first interaction, not rotated) and the reflectance of
    column 0's state pR = clip((M_R A)_00, 0, 1).  The float32 operations of the numpy code, in order;
    written without branches over restrict pointers, so that gcc vectorises the loops (numpy's passes
    are SIMD; a scalar C loop is bound by its ~12 divisions and square roots per ray).  scratch: (3, n) rows
    for the new basis before it is interleaved into s_new.  F_r, F_t (6, n) given (rays at their first
    interaction, A None, both branches kept): the factors of both branches written instead of R, T, c2, s2
    (`transport.first_interaction_factors`' numbers for `reflected` and `transmitted_copy`; `facet_split_loop`).
    """
    cdef Py_ssize_t n = ci.shape[0], i, col, K = 0 if A is None else A.shape[1]
    cdef Py_ssize_t ss = s.strides[0] // sizeof(float), sc = s.strides[1] // sizeof(float)
    if s_new.shape[0] != n or R.shape[1] != n or T.shape[1] != n or s.shape[0] != n or (A is not None and
                                                                                         A.shape[2] != n):
        raise ValueError("facet_event: inconsistent shapes")
    if n == 0:
        return
    if R.strides[1] != sizeof(float) or T.strides[1] != sizeof(float) or scratch.strides[1] != sizeof(float) \
            or scratch.shape[0] != 3 or scratch.shape[1] != n or n1.shape[0] != n or n2.shape[0] != n:
        raise ValueError("facet_event: inconsistent shapes (rows of R, T and scratch contiguous)")
    cdef bint split = F_r is not None
    if split and (A is not None or F_t is None or F_r.shape[0] != 6 or F_t.shape[0] != 6 or F_r.shape[1] != n
                  or F_t.shape[1] != n or F_r.strides[1] != sizeof(float) or F_t.strides[1] != sizeof(float)):
        raise ValueError("facet_event: the split's factors need A None and contiguous (6, n) rows F_r, F_t")
    with nogil:
        if split:
            facet_split_loop(n, &nfx[0], &nfy[0], &nfz[0], &kx[0], &ky[0], &kz[0], &s[0, 0], ss, sc, &ci[0], &n1[0],
                             &n2[0], &scratch[0, 0], &scratch[1, 0], &scratch[2, 0], &F_r[0, 0], &F_r[1, 0],
                             &F_r[2, 0], &F_r[3, 0], &F_r[4, 0], &F_r[5, 0], &F_t[0, 0], &F_t[1, 0], &F_t[2, 0],
                             &F_t[3, 0], &F_t[4, 0], &F_t[5, 0], &pR[0])
        else:
            facet_loop(n, &nfx[0], &nfy[0], &nfz[0], &kx[0], &ky[0], &kz[0], &s[0, 0], ss, sc, &ci[0], &n1[0],
                       &n2[0], &scratch[0, 0], &scratch[1, 0], &scratch[2, 0], &c2[0], &s2[0], &R[0, 0], &R[1, 0],
                       &R[2, 0], &R[3, 0], &T[0, 0], &T[1, 0], &T[2, 0], &T[3, 0], &pR[0])
        for i in range(n):
            s_new[i, 0] = scratch[0, i]
            s_new[i, 1] = scratch[1, i]
            s_new[i, 2] = scratch[2, i]
        for col in range(K):                          # the columns rotated onto the facet's basis
            rotate_loop(n, &c2[0], &s2[0], &A[1, col, 0], &A[2, col, 0])
        if K:
            reflectance_loop(n, &R[0, 0], &R[1, 0], &A[1, 0, 0], &pR[0])


cdef inline void facet_basis(float nx, float ny, float nz, float kx, float ky, float kz, float sx, float sy,
                             float sz, float *b) noexcept nogil:
    """The facet's basis s_new = n x k / |n x k| (b[0:3]; the old s where |n x k| < 1e-6: normal incidence)
    and the rotation's (cos 2psi, sin 2psi) onto it (b[3:5]): the first operations of `facet_event`."""
    cdef float u0, u1, u2, c, d, sn
    u0 = ny * kz - nz * ky
    u1 = nz * kx - nx * kz
    u2 = nx * ky - ny * kx
    c = (sx * u0 + sy * u1) + sz * u2
    d = (sx * nx + sy * ny) + sz * nz
    sn = sqrtf((u0 * u0 + u1 * u1) + u2 * u2)
    # |u| < 1e-6: normal incidence on the facet, the basis kept
    u0 = sx if sn < <float>1e-6 else u0
    u1 = sy if sn < <float>1e-6 else u1
    u2 = sz if sn < <float>1e-6 else u2
    c = 1 if sn < <float>1e-6 else c
    d = 0 if sn < <float>1e-6 else d
    sn = 1 if sn < <float>1e-6 else sn
    b[0] = u0 / sn
    b[1] = u1 / sn
    b[2] = u2 / sn
    double_angle(c, d, &b[3], &b[4])


cdef void facet_loop(Py_ssize_t n, f32_in nfx, f32_in nfy, f32_in nfz, f32_in kx, f32_in ky, f32_in kz, f32_in s,
                     Py_ssize_t ss, Py_ssize_t sc, f32_in ci, f32_in n1, f32_in n2, f32_out snx, f32_out sny,
                     f32_out snz, f32_out c2, f32_out s2, f32_out r0, f32_out r1, f32_out r2, f32_out r3,
                     f32_out t0, f32_out t1, f32_out t2, f32_out t3, f32_out pR) noexcept nogil:
    """The loop of `facet_event` over restrict pointer parameters (gcc honours restrict on parameters), float
    data only and no branches (selects), so that it vectorises with baseline SSE2; the new basis in rows."""
    cdef Py_ssize_t i
    cdef float b[5]
    cdef float Rv[4]
    cdef float Tv[4]
    for i in range(n):
        facet_basis(nfx[i], nfy[i], nfz[i], kx[i], ky[i], kz[i], s[i * ss], s[i * ss + sc], s[i * ss + 2 * sc], b)
        snx[i] = b[0]
        sny[i] = b[1]
        snz[i] = b[2]
        c2[i] = b[3]
        s2[i] = b[4]
        interface_coefficients(ci[i], n1[i], n2[i], Rv, Tv)
        r0[i] = Rv[0]
        r1[i] = Rv[1]
        r2[i] = Rv[2]
        r3[i] = Rv[3]
        t0[i] = Tv[0]
        t1[i] = Tv[1]
        t2[i] = Tv[2]
        t3[i] = Tv[3]
        pR[i] = clip01(Rv[0])


cdef void facet_split_loop(Py_ssize_t n, f32_in nfx, f32_in nfy, f32_in nfz, f32_in kx, f32_in ky, f32_in kz,
                           f32_in s, Py_ssize_t ss, Py_ssize_t sc, f32_in ci, f32_in n1, f32_in n2, f32_out snx,
                           f32_out sny, f32_out snz, f32_out fr0, f32_out fr1, f32_out fr2, f32_out fr3,
                           f32_out fr4, f32_out fr5, f32_out ft0, f32_out ft1, f32_out ft2, f32_out ft3,
                           f32_out ft4, f32_out ft5, f32_out pR) noexcept nogil:
    """`facet_loop` for rays at their first interaction that split (`facet_event` with F_r, F_t): instead of
    R, T and the rotation, the factors of both branches: R / max(pR, 1e-30) and T / max(1 - pR, 1e-30) (the
    division a multiplication by the float32 reciprocal, as `transport.first_interaction_factors`), c2, s2."""
    cdef Py_ssize_t i
    cdef float b[5]
    cdef float Rv[4]
    cdef float Tv[4]
    cdef float p, x, inv_r, inv_t
    for i in range(n):
        facet_basis(nfx[i], nfy[i], nfz[i], kx[i], ky[i], kz[i], s[i * ss], s[i * ss + sc], s[i * ss + 2 * sc], b)
        snx[i] = b[0]
        sny[i] = b[1]
        snz[i] = b[2]
        interface_coefficients(ci[i], n1[i], n2[i], Rv, Tv)
        p = clip01(Rv[0])
        pR[i] = p
        inv_r = <float>1 / (<float>1e-30 if p < <float>1e-30 else p)
        x = <float>1 - p
        inv_t = <float>1 / (<float>1e-30 if x < <float>1e-30 else x)
        fr0[i] = Rv[0] * inv_r
        fr1[i] = Rv[1] * inv_r
        fr2[i] = Rv[2] * inv_r
        fr3[i] = Rv[3] * inv_r
        fr4[i] = b[3]
        fr5[i] = b[4]
        ft0[i] = Tv[0] * inv_t
        ft1[i] = Tv[1] * inv_t
        ft2[i] = Tv[2] * inv_t
        ft3[i] = Tv[3] * inv_t
        ft4[i] = b[3]
        ft5[i] = b[4]


cdef void rotate_loop(Py_ssize_t n, f32_in c2, f32_in s2, f32_out a1, f32_out a2) noexcept nogil:
    """Rows 1, 2 of one Stokes column rotated (`core.stokes.rotate_stokes_columns_cd`'s operations)."""
    cdef Py_ssize_t i
    cdef float x1, x2
    for i in range(n):
        x1 = a1[i]
        x2 = a2[i]
        a1[i] = c2[i] * x1 + s2[i] * x2
        a2[i] = x2 * c2[i] - x1 * s2[i]


cdef void reflectance_loop(Py_ssize_t n, f32_in aR, f32_in bR, f32_in a10, f32_out pR) noexcept nogil:
    """pR = clip(aR + bR A_10, 0, 1): the reflectance of column 0's state after the rotation."""
    cdef Py_ssize_t i
    for i in range(n):
        pR[i] = clip01(aR[i] + bR[i] * a10[i])



# ----------------------------------------------------------------------------- geometry of a batch


cdef inline float fmin_f(float a, float b) noexcept nogil:
    """np.fmin: the smaller, a NaN ignored (inline: libm's fminf is a call)."""
    if b != b or a < b:
        return a
    return b


def slab_distances(const float[:, :] o, const float[:, :] k, float hx, float hy, float zh, float zc,
                   float[:, :] T, float[::1] t_lat, float[::1] tfar):
    """Distances along k (n, 3) from o to the tile's sides and the slab's faces (`tracer.ReliefTracer.query`):
    T[j, i] = (copysign(h_j, k_j) - o_j + c_j) / k_j with h = (hx, hy, zh), c = (0, 0, zc) (T (3, n): rows
    tx, ty, tz); t_lat = fmin(T_x, T_y), tfar = max(fmin(t_lat, T_z), 0).  The float32 operations of the
    numpy code, in order: one pass per component over the rows of o and k (contiguous rows: the division
    loops vectorise), then one over the distances."""
    cdef Py_ssize_t n = k.shape[0], i
    if o.shape[0] != n or T.shape[0] != 3 or T.shape[1] != n or t_lat.shape[0] != n or tfar.shape[0] != n:
        raise ValueError("slab_distances: inconsistent shapes")
    if n == 0:
        return
    if T.strides[1] != sizeof(float):
        raise ValueError("slab_distances: the rows of T must be contiguous")
    cdef Py_ssize_t so = o.strides[0] // sizeof(float), co = o.strides[1] // sizeof(float)
    cdef Py_ssize_t sk = k.strides[0] // sizeof(float), ck = k.strides[1] // sizeof(float)
    with nogil:
        slab_component(n, &o[0, 0], so, &k[0, 0], sk, hx, <float>0, &T[0, 0])
        slab_component(n, &o[0, 0] + co, so, &k[0, 0] + ck, sk, hy, <float>0, &T[1, 0])
        slab_component(n, &o[0, 0] + 2 * co, so, &k[0, 0] + 2 * ck, sk, zh, zc, &T[2, 0])
        slab_limits(n, &T[0, 0], &T[1, 0], &T[2, 0], &t_lat[0], &tfar[0])


def slab_far(const float[:, :] o, const float[:, :] k, float hx, float hy, float zh, float zc, float[::1] tfar,
             unsigned char[::1] lat_first):
    """`slab_distances` for a query: only tfar (Embree's limit) and whether a tile side comes first (t_lat < tz:
    a ray that hits nothing re-enters through it), the distances themselves not written (a ray that
    re-enters gets them again from `slab_distances`).  The same operations."""
    cdef Py_ssize_t n = k.shape[0]
    if o.shape[0] != n or tfar.shape[0] != n or lat_first.shape[0] != n:
        raise ValueError("slab_far: inconsistent shapes")
    if n == 0:
        return
    cdef Py_ssize_t so = o.strides[0] // sizeof(float), co = o.strides[1] // sizeof(float)
    cdef Py_ssize_t sk = k.strides[0] // sizeof(float), ck = k.strides[1] // sizeof(float)
    with nogil:
        slab_far_loop(n, &o[0, 0], so, co, &k[0, 0], sk, ck, hx, hy, zh, zc, &tfar[0], &lat_first[0])


cdef void slab_far_loop(Py_ssize_t n, f32_in o, Py_ssize_t so, Py_ssize_t co, f32_in k, Py_ssize_t sk,
                        Py_ssize_t ck, float hx, float hy, float zh, float zc, f32_out tfar,
                        u8_out lat) noexcept nogil:
    """The loop of `slab_far` over restrict pointers (rows of strides so, sk; components co, ck), selects only."""
    cdef Py_ssize_t i
    cdef float kx, ky, kz, tx, ty, tz, tl, tf
    for i in range(n):
        kx = k[i * sk]
        ky = k[i * sk + ck]
        kz = k[i * sk + 2 * ck]
        tx = ((copysignf(hx, kx) - o[i * so]) + <float>0) / kx
        ty = ((copysignf(hy, ky) - o[i * so + co]) + <float>0) / ky
        tz = ((copysignf(zh, kz) - o[i * so + 2 * co]) + zc) / kz
        tl = tx if (ty != ty or tx < ty) else ty
        lat[i] = tl < tz
        tf = tl if (tz != tz or tl < tz) else tz
        tfar[i] = 0 if tf < 0 else tf


cdef void slab_component(Py_ssize_t n, f32_in o, Py_ssize_t so, f32_in k, Py_ssize_t sk, float h, float c,
                         f32_out t) noexcept nogil:
    """t[i] = ((copysign(h, k_i) - o_i) + c) / k_i over one component of rows o, k (row strides so, sk)."""
    cdef Py_ssize_t i
    cdef float kv
    for i in range(n):
        kv = k[i * sk]
        t[i] = ((copysignf(h, kv) - o[i * so]) + c) / kv


cdef void slab_limits(Py_ssize_t n, f32_in tx, f32_in ty, f32_in tz, f32_out t_lat, f32_out tfar) noexcept nogil:
    """t_lat = fmin(tx, ty), tfar = max(fmin(t_lat, tz), 0) (NaN ignored by fmin, kept by max)."""
    cdef Py_ssize_t i
    cdef float tl, tf, a, b
    for i in range(n):
        a = tx[i]
        b = ty[i]
        tl = a if (b != b or a < b) else b
        t_lat[i] = tl
        b = tz[i]
        tf = tl if (b != b or tl < b) else b
        tfar[i] = 0 if tf < 0 else tf


def classify_misses(const unsigned char[::1] hit, const unsigned char[::1] lat_first, const float[:, :] k,
                    const unsigned char[::1] below, signed char above_code, signed char below_code,
                    signed char leak_code, long[::1] exit_idx, signed char[::1] exit_state, long[::1] wrap_idx):
    """The rays that hit nothing (hit 0), in order, sorted into those that reached a slab face first
    (lat_first 0, i.e. not t_lat < tz: they leave; their indices into exit_idx and their states into
    exit_state) and those that reached a tile side first (wrap_idx: they re-enter); returns (exits, wraps).  The state of an exit is
    above_code going up (k_z > 0), below_code going down, leak_code when that is the side the ray was not on
    (going up from below, or down from above): `transport._misses` and `transport._exit_state` in one pass."""
    cdef Py_ssize_t n = hit.shape[0], i, ne = 0, nw = 0
    cdef bint up
    if lat_first.shape[0] != n or k.shape[0] != n or below.shape[0] != n or \
            exit_idx.shape[0] < n or exit_state.shape[0] < n or wrap_idx.shape[0] < n:
        raise ValueError("classify_misses: inconsistent shapes")
    with nogil:
        for i in range(n):
            if hit[i]:
                continue
            if lat_first[i]:
                wrap_idx[nw] = i
                nw += 1
                continue
            up = k[i, 2] > 0
            exit_idx[ne] = i
            exit_state[ne] = leak_code if up == (below[i] != 0) else (above_code if up else below_code)
            ne += 1
    return ne, nw


def facet_geometry(const float[:, :] ng, const float[:, :] k, const unsigned char[::1] below, float eta_up,
                   float eta_dn, float n_above, float n_below, float[:, :] out, unsigned char[::1] tir,
                   unsigned char[::1] leak):
    """The facets hit (`transport._hits`, `_facet`) per ray from Embree's normals ng (n, 3): out (10, n) holds
    rows kx, ky, kz (the directions, contiguous), nfx, nfy, nfz (the unit normal on the incident side:
    ng / |ng| with the sign of ng_z, negated below the surface), cos i = |k . n_up|, cos t (Snell, 0 past
    the critical angle), eta = n1 / n2, k . n_up and the indices n1, n2 (n_below, n_above below the surface,
    n_above, n_below above: `transport.Media.pair`); tir and leak (k . n_up > 0 is not `below`: a ray on
    the wrong side) as 0 / 1; out has 12 rows.  The float32 operations of the numpy code, in order: a loop
    over the rays' components (strided loads, selects only: it vectorises), then the flags (tir is
    sin^2 t >= 1, i.e. cos t = sqrt(max(1 - sin^2 t, 0)) == 0)."""
    cdef Py_ssize_t n = k.shape[0], i
    if ng.shape[0] != n or out.shape[0] != 12 or out.shape[1] != n or tir.shape[0] != n or leak.shape[0] != n:
        raise ValueError("facet_geometry: inconsistent shapes")
    if n == 0:
        return
    if out.strides[1] != sizeof(float):
        raise ValueError("facet_geometry: the rows of out must be contiguous")
    cdef Py_ssize_t sg = ng.strides[0] // sizeof(float), cg = ng.strides[1] // sizeof(float)
    cdef Py_ssize_t sk = k.strides[0] // sizeof(float), ck = k.strides[1] // sizeof(float)
    with nogil:
        facet_geometry_loop(n, &ng[0, 0], sg, cg, &k[0, 0], sk, ck, &below[0], eta_up, eta_dn, n_above, n_below,
                            &out[0, 0], &out[1, 0], &out[2, 0], &out[3, 0], &out[4, 0], &out[5, 0], &out[6, 0],
                            &out[7, 0], &out[8, 0], &out[9, 0], &out[10, 0], &out[11, 0])
        for i in range(n):
            tir[i] = out[7, i] == 0
            leak[i] = (out[9, i] > 0) != (below[i] != 0)


cdef void facet_geometry_loop(Py_ssize_t n, f32_in ng, Py_ssize_t sg, Py_ssize_t cg, f32_in k, Py_ssize_t sk,
                              Py_ssize_t ck, const unsigned char *below, float eta_up, float eta_dn,
                              float n_above, float n_below, f32_out kxo, f32_out kyo, f32_out kzo, f32_out nxo,
                              f32_out nyo, f32_out nzo, f32_out cio, f32_out cto, f32_out etao, f32_out doto,
                              f32_out n1o, f32_out n2o) noexcept nogil:
    """The float rows of `facet_geometry` (restrict pointers, selects only)."""
    cdef Py_ssize_t i
    cdef float gx, gy, gz, kx, ky, kz, inv, dot, s, ci, eta, sin2t, ct
    cdef bint b
    for i in range(n):
        gx = ng[i * sg]
        gy = ng[i * sg + cg]
        gz = ng[i * sg + 2 * cg]
        kx = k[i * sk]
        ky = k[i * sk + ck]
        kz = k[i * sk + 2 * ck]
        inv = copysignf(<float>1 / sqrtf((gx * gx + gy * gy) + gz * gz), gz)
        dot = ((kx * gx + ky * gy) + kz * gz) * inv
        b = below[i] != 0
        s = -inv if b else inv
        ci = fabsf(dot)
        eta = eta_up if b else eta_dn
        sin2t = (<float>1 - ci * ci) * (eta * eta)
        ct = <float>1 - sin2t
        ct = 0 if ct < 0 else ct
        ct = sqrtf(ct)
        kxo[i] = kx
        kyo[i] = ky
        kzo[i] = kz
        nxo[i] = gx * s
        nyo[i] = gy * s
        nzo[i] = gz * s
        cio[i] = ci
        cto[i] = ct
        etao[i] = eta
        doto[i] = dot
        n1o[i] = n_below if b else n_above
        n2o[i] = n_above if b else n_below


# ----------------------------------------------------------------------------- gathers, tags, new rays


def beam_origins(const long[::1] ix, const long[::1] iy, const double[:, ::1] jit, double sx, double hx, double sy,
                 double hy, float z, float[:, ::1] o):
    """Origins of a chunk's rays in their strata (`methods.ray.method._incidence_task`): o = ((ix + jit_0) sx - hx,
    (iy + jit_1) sy - hy, z), computed in float64 and rounded to float32 as numpy's column assignments do."""
    cdef Py_ssize_t n = ix.shape[0], i
    if iy.shape[0] != n or jit.shape[0] != n or jit.shape[1] != 2 or o.shape[0] != n or o.shape[1] != 3:
        raise ValueError("beam_origins: inconsistent shapes")
    with nogil:
        for i in range(n):
            o[i, 0] = <float>((<double>ix[i] + jit[i, 0]) * sx - hx)
            o[i, 1] = <float>((<double>iy[i] + jit[i, 1]) * sy - hy)
            o[i, 2] = z


def gather_records(const long[::1] idx, const float[:, :] k, const float[::1] w, const short[::1] nb,
                   const long[::1] ids, float[:, ::1] k_out, float[::1] w_out, short[::1] nb_out, long[::1] ids_out):
    """Rows idx of the rays' direction k (n, 3), weight, bounce count and output id into an exit record's slot
    (`exits.Exits.put`: the four `np.take` in one pass)."""
    cdef Py_ssize_t m = idx.shape[0], j, i
    if k_out.shape[0] != m or w_out.shape[0] != m or nb_out.shape[0] != m or ids_out.shape[0] != m:
        raise ValueError("gather_records: inconsistent shapes")
    with nogil:
        for j in range(m):
            i = idx[j]
            k_out[j, 0] = k[i, 0]
            k_out[j, 1] = k[i, 1]
            k_out[j, 2] = k[i, 2]
            w_out[j] = w[i]
            nb_out[j] = nb[i]
            ids_out[j] = ids[i]


def near_direction(const float[:, :] dirs, float d0, float d1, float d2, float cos_min, long[::1] out):
    """Indices (in order, into out; their number returned) of the directions whose float32 dot product
    (d . d0 + ...) with (d0, d1, d2) exceeds cos_min: the prefilter of `bsdf.builder.specular_flags`, its
    operations in its order."""
    cdef Py_ssize_t n = dirs.shape[0], i, j = 0
    cdef float c
    if out.shape[0] < n:
        raise ValueError("near_direction: out too short")
    with nogil:
        for i in range(n):
            c = (dirs[i, 0] * d0 + dirs[i, 1] * d1) + dirs[i, 2] * d2
            if c > cos_min:
                out[j] = i
                j += 1
    return j


def near_two_directions(const float[:, :] dirs, float a0, float a1, float a2, float b0, float b1, float b2,
                        float cos_min, long[::1] out_a, long[::1] out_b):
    """`near_direction` for two directions a and b in one pass over the directions: (count a, count b)."""
    cdef Py_ssize_t n = dirs.shape[0], i, ja = 0, jb = 0
    cdef float x, y, z
    if out_a.shape[0] < n or out_b.shape[0] < n:
        raise ValueError("near_two_directions: out too short")
    with nogil:
        for i in range(n):
            x = dirs[i, 0]
            y = dirs[i, 1]
            z = dirs[i, 2]
            if (x * a0 + y * a1) + z * a2 > cos_min:
                out_a[ja] = i
                ja += 1
            if (x * b0 + y * b1) + z * b2 > cos_min:
                out_b[jb] = i
                jb += 1
    return ja, jb


def subtile_index(const float[:, :] p, float hx, float hy, float half_x, float half_y, float scale_x,
                  float scale_y, bint mirrored, int gx, int gy, int[::1] out):
    """Sub-tile iy * gx + ix of each point p (n, >= 2) (`tracer.ReliefTracer.subtile_of`): u = p + h, folded
    (half - |u - half|) on a mirror-extended tile, truncated u * scale clipped to the grid; its float32
    and int32 operations."""
    cdef Py_ssize_t n = p.shape[0], i
    if out.shape[0] != n:
        raise ValueError("subtile_index: inconsistent shapes")
    with nogil:
        for i in range(n):
            out[i] = subtile(p[i, 0], p[i, 1], hx, hy, half_x, half_y, scale_x, scale_y, mirrored, gx, gy)


cdef inline int subtile(float px, float py, float hx, float hy, float half_x, float half_y, float scale_x,
                        float scale_y, bint mirrored, int gx, int gy) noexcept nogil:
    """The sub-tile of one point (`subtile_index`)."""
    cdef float ux = px + hx, uy = py + hy
    cdef int ix, iy
    if mirrored:
        ux = half_x - fabsf(ux - half_x)
        uy = half_y - fabsf(uy - half_y)
    ix = <int>(ux * scale_x)
    iy = <int>(uy * scale_y)
    ix = 0 if ix < 0 else (gx - 1 if ix > gx - 1 else ix)
    iy = 0 if iy < 0 else (gy - 1 if iy > gy - 1 else iy)
    return ix + iy * gx


def gather_rays(const long[::1] idx, const float[:, :] o, const float[:, :] k, const unsigned char[::1] below,
                const float[::1] w, const short[::1] nb, const long[::1] ids, float[:, ::1] o_out,
                float[:, ::1] k_out, unsigned char[::1] below_out, float[::1] w_out, short[::1] nb_out,
                long[::1] ids_out):
    """Rows idx of a batch's origins, directions, side, weight, bounce count and id (`transport.Rays.take`:
    six `np.take` in one pass)."""
    cdef Py_ssize_t m = idx.shape[0], j, i
    if o_out.shape[0] != m or k_out.shape[0] != m or below_out.shape[0] != m or w_out.shape[0] != m \
            or nb_out.shape[0] != m or ids_out.shape[0] != m:
        raise ValueError("gather_rays: inconsistent shapes")
    with nogil:
        for j in range(m):
            i = idx[j]
            o_out[j, 0] = o[i, 0]
            o_out[j, 1] = o[i, 1]
            o_out[j, 2] = o[i, 2]
            k_out[j, 0] = k[i, 0]
            k_out[j, 1] = k[i, 1]
            k_out[j, 2] = k[i, 2]
            below_out[j] = below[i]
            w_out[j] = w[i]
            nb_out[j] = nb[i]
            ids_out[j] = ids[i]


def split_rays(const float[::1] kx, const float[::1] ky, const float[::1] kz, const float[::1] nfx,
               const float[::1] nfy, const float[::1] nfz, const float[::1] eta, const float[::1] ci,
               const float[::1] ct, const float[::1] th, const float[:, :] o, float eps, float[:, ::1] p,
               float[:, ::1] o_r, float[:, ::1] k_r, float[:, ::1] o_t, float[:, ::1] k_t, tuple grid=None,
               const long[::1] ids=None, int[::1] group=None):
    """Both branches of the rays' first interaction (`transport._interact`, `_split_copies`): the hit point
    p = k th + o, the reflected direction k + 2 ci nf and origin p + eps nf, the refracted direction
    (eta k + (eta ci - ct) nf) / |.| and origin p - eps nf.  The float32 operations of the numpy code.
    p None: the hit points are not kept; grid given (`tracer.ReliefTracer.subtile_grid`): the sub-tile of each
    hit point is written to group[ids[i]] (`transport._tag_first_hits`, `subtile_index`'s numbers)."""
    cdef Py_ssize_t n = th.shape[0], i
    cdef float px, py, pz, bt, b, vx, vy, vz, nr
    cdef bint keep = p is not None, tag = grid is not None
    cdef float hx = 0, hy = 0, half_x = 0, half_y = 0, scale_x = 0, scale_y = 0
    cdef bint mirrored = False
    cdef int gx = 1, gy = 1
    if o.shape[0] != n or (keep and p.shape[0] != n) or o_r.shape[0] != n or k_r.shape[0] != n or \
            o_t.shape[0] != n or k_t.shape[0] != n or (tag and (ids is None or group is None or ids.shape[0] != n)):
        raise ValueError("split_rays: inconsistent shapes")
    if tag:
        hx, hy, half_x, half_y, scale_x, scale_y, mirrored, gx, gy = grid
    with nogil:
        for i in range(n):
            px = kx[i] * th[i] + o[i, 0]
            py = ky[i] * th[i] + o[i, 1]
            pz = kz[i] * th[i] + o[i, 2]
            if keep:
                p[i, 0] = px
                p[i, 1] = py
                p[i, 2] = pz
            if tag:
                group[ids[i]] = subtile(px, py, hx, hy, half_x, half_y, scale_x, scale_y, mirrored, gx, gy)
            b = <float>2 * ci[i]
            k_r[i, 0] = b * nfx[i] + kx[i]
            k_r[i, 1] = b * nfy[i] + ky[i]
            k_r[i, 2] = b * nfz[i] + kz[i]
            o_r[i, 0] = px + eps * nfx[i]
            o_r[i, 1] = py + eps * nfy[i]
            o_r[i, 2] = pz + eps * nfz[i]
            bt = eta[i] * ci[i] - ct[i]
            vx = eta[i] * kx[i] + bt * nfx[i]
            vy = eta[i] * ky[i] + bt * nfy[i]
            vz = eta[i] * kz[i] + bt * nfz[i]
            nr = sqrtf((vx * vx + vy * vy) + vz * vz)
            k_t[i, 0] = vx / nr
            k_t[i, 1] = vy / nr
            k_t[i, 2] = vz / nr
            o_t[i, 0] = px - eps * nfx[i]
            o_t[i, 1] = py - eps * nfy[i]
            o_t[i, 2] = pz - eps * nfz[i]


def split_weights(const float[::1] w, const float[::1] pR, const unsigned char[::1] below, const long[::1] ids,
                  const short[::1] nb, long n0, float[::1] w_r, float[::1] w_t, unsigned char[::1] below_t,
                  long[::1] ids_t, short[::1] nb_next):
    """The scalars of both branches of the rays' first interaction (`transport._first_interaction_compiled`,
    `_split_copies`): w_r = w pR, w_t = w (1 - pR), below_t = not below, ids_t = ids + n0, nb_next = nb + 1;
    returns how many rays transmit something (pR < 1).  numpy's float32 / integer operations."""
    cdef Py_ssize_t n = w.shape[0], i, j = 0
    cdef float p
    if pR.shape[0] != n or below.shape[0] != n or ids.shape[0] != n or nb.shape[0] != n or w_r.shape[0] != n \
            or w_t.shape[0] != n or below_t.shape[0] != n or ids_t.shape[0] != n or nb_next.shape[0] != n:
        raise ValueError("split_weights: inconsistent shapes")
    with nogil:
        for i in range(n):
            p = pR[i]
            w_r[i] = w[i] * p
            w_t[i] = w[i] * (<float>1 - p)
            below_t[i] = below[i] == 0
            ids_t[i] = ids[i] + n0
            nb_next[i] = <short>(nb[i] + 1)
            j += p < 1
    return j
