"""The ONE bounce loop of the ray method, generic over what a ray carries.

A batch of rays (`Rays`: float32 structure of arrays) is traced through the relief layer
until every ray has left it or is lost.  At each hit the local facet is a flat interface
between n1 (the ray's medium) and n2: Snell refraction, total internal reflection, and a
Fresnel event whose physics depends on what the ray carries - the *carrier* (as Mitsuba 3
compiles one integrator for scalar and polarised light; the loop is written once):

- `IntensityCarrier`: unpolarised intensity, the power weight alone; the event's reflectance
  is the unpolarised Fresnel reflectance (|r_s|^2 + |r_p|^2) / 2 of the facet (the usual
  scalar approximation, which ignores that the first bounce polarises the light for the
  second).  Complex indices (metals) use the float64 reference amplitudes.
- `StokesCarrier`: K Stokes columns per ray (K = 1: one Stokes vector; K = 4: a Mueller
  matrix whose columns answer the incident basis states) in the basis (s, p = s x k).  At a
  hit the basis is rotated about k onto the facet's s = n x k / |n x k| (core.stokes
  convention), the facet's Mueller matrix (`core.fresnel.interface_coefficients_f32`, the
  form of `mueller_interface`, Born & Wolf 1.5.20-21, 1.5.27) is applied, and the reflectance
  of the ray's current state, P_R = (M_R S)_0 / S_0 of column 0, drives the choice.

Reflect or refract (Veach 1997 sec. 4.2): with `split_first` every ray's first interaction
yields both branches deterministically (reflected: output id i, weight w P_R; transmitted:
id i + n, weight w (1 - P_R)); the first interactions of a chunk are all done before the
roulette phase starts (so a chunk's random numbers come in a fixed order).  Afterwards
Russian roulette with probability P_R and renormalisation S <- M S / P keep every weight
unchanged (unbiased; energy conserved ray by ray in lossless media).
Common random numbers: the roulette's uniform number of a path at its b-th interaction is a
hash of (chunk key, output id, b) (`path_uniforms`: counter-based, like Philox / Random123,
Salmon et al. 2011), not the next number of a shared stream, so a path meets the same numbers
whatever the other paths did: re-tracing a relief whose heights changed a little (a fit's
iterations) changes only the paths that really change, and the objective is smooth in the
heights.  The chunk key is drawn from the chunk's generator (one number, after the entry
points), so a seed still names every number.  Light transmitted into
an absorbing medium ends as LOST_ABSORBED; rays found on the wrong side of the surface
(numerical leaks) as LOST_LEAK; rays still bouncing after `max_bounces` as LOST_BOUNCES.
Regime: geometric optics (features >> wavelength), no interference between rays.

Speed: a handful of float32 numpy passes per bounce, one gather per bounce (the rays that
hit), finished rays written once into the preallocated `Exits` (their exit-frame Stokes
columns gathered and rotated in the record's own slot); a ray's first interaction kept as the
6 factors of its Mueller columns (`first_interaction_factors`: most rays leave after it, and their
exit columns are computed from the factors in the record's slot, `exit_columns_of_factors`, the same
float32 operations as materialising and rotating the 16); freed temporaries stay in the heap
(`keep_freed_heap`: no page faults per bounce); no
BLAS call (a matrix product wakes OpenBLAS's spinning thread pool); the in-place float32
kernels on the (4, K, n) Stokes columns are the core's (`core.stokes.rotate_stokes_columns`,
`apply_interface_mueller_columns`, `s_axis_rows`; `core.frames.dot_rows`, `cross_rows`),
tested equal to the reference definitions beside them; the (n, 3) vectors of an interaction
(directions, normals, the facet basis) are worked on as contiguous component arrays and written
into (n, 3) rows once (`_unit_rows`: the operations of `core.frames.dot_rows`, `divide_rows`,
`scale_rows` in the same order, on unstrided arrays, ~3x faster per operation).
The passes over a batch's rays are kernels (`relief_bsdf.kernels`: compiled, or their numpy twins, the
same numbers): the facets of a batch (`_hits`), the polarised event for real indices
(`StokesCarrier.reflectance`; at a first interaction that splits, both branches' factors in the same
pass), the branches' rays and scalars, the sorting of the misses, the gathers and the exit columns; an
exit whose path interacted once is held compactly (its 6 factors and exit rotation,
`exits.Exits.compact`) and expanded by the binning.
"""
from __future__ import annotations

import ctypes
import sys
from dataclasses import dataclass, field

import numpy as np

from relief_bsdf import kernels
from relief_bsdf.core.frames import cross_rows, dot_rows
from relief_bsdf.core.fresnel import interface_coefficients_f32, reflectance_unpolarized_f32
from relief_bsdf.core.stokes import (apply_interface_mueller_columns, double_angle_cd,
                                     rotate_stokes_columns_cd, s_axis_rows)
from relief_bsdf.methods.ray.exits import ABOVE, BELOW, LOST_ABSORBED, LOST_BOUNCES, LOST_LEAK, Exits, padded_rows

F32 = np.float32
ALONG_Z_XY2 = F32(1e-14)     # k_x^2 + k_y^2 below which an exit is along z: its frame is the fallback azimuth's


_HEAP_KEPT = False
_M_TRIM_THRESHOLD, _M_MMAP_THRESHOLD = -1, -3          # glibc mallopt parameters (malloc.h)


def keep_freed_heap(mmap_max_bytes: int = 1 << 25, trim_bytes: int = 1 << 28) -> bool:
    """Let glibc's malloc keep freed memory for reuse (once per process; no-op elsewhere).

    The loop allocates its float32 temporaries afresh each bounce (MB each: (4, 4, n) Stokes
    columns of a 65536-ray chunk are 4 MB).  By default glibc serves such blocks with mmap
    and hands freed heap tops back to the kernel once they exceed a small threshold, so each
    bounce pays page faults and page zeroing again (a fifth of the polarised engine's time on
    a 512^2 tile).  Blocks up to `mmap_max_bytes` from the heap and freed space up to
    `trim_bytes` kept (glibc mallopt M_MMAP_THRESHOLD, M_TRIM_THRESHOLD) make them reused
    memory; the cost is resident memory the process keeps (at most ~trim_bytes per arena).
    Changes no number.  True when the settings are in force.
    """
    global _HEAP_KEPT
    if _HEAP_KEPT or not sys.platform.startswith("linux"):
        return _HEAP_KEPT
    try:
        libc = ctypes.CDLL("libc.so.6")
        _HEAP_KEPT = bool(libc.mallopt(_M_MMAP_THRESHOLD, int(mmap_max_bytes))
                          and libc.mallopt(_M_TRIM_THRESHOLD, int(trim_bytes)))
    except (OSError, AttributeError):              # not glibc (musl, ...): keep its defaults
        _HEAP_KEPT = False
    return _HEAP_KEPT


# ----------------------------------------------------------------------------- data


@dataclass
class TraceSettings:
    """How a chunk is traced: bounce limit, deterministic first-hit split, exit frame along z."""

    max_bounces: int = 100
    split_first: bool = False
    phi_exit_rad: float = 0.0        # exit Stokes frame of a ray leaving exactly along z (s from the azimuth)
    subtiles: tuple | None = None    # (gx, gy): tag each path with the sub-tile of its first hit (Exits.first_group)


@dataclass
class Media:
    """The two media of the layer: n_above (real, the lit side) and n_below (complex for a metal)."""

    n_above: float
    n_below: float | complex
    eta_dn: np.float32 = field(init=False)      # n1 / n2 for a ray above the surface
    eta_up: np.float32 = field(init=False)      # n1 / n2 for a ray below it
    is_complex: bool = field(init=False)
    absorbing_below: bool = field(init=False)

    def __post_init__(self):
        self.is_complex = bool(np.iscomplexobj(self.n_above) or np.iscomplexobj(self.n_below))
        if self.is_complex:
            self.eta_dn = F32(np.real(self.n_above / self.n_below))
            self.eta_up = F32(np.real(self.n_below / self.n_above))
        else:
            na, nb = F32(self.n_above), F32(self.n_below)
            self.eta_dn, self.eta_up = na / nb, nb / na
        self.absorbing_below = self.is_complex and float(np.imag(self.n_below)) > 0

    def pair(self, below: np.ndarray):
        """Per-ray (n1, n2): float32 for real indices, complex128 otherwise."""
        if self.is_complex:
            na, nb = complex(self.n_above), complex(self.n_below)
            return np.where(below, nb, na), np.where(below, na, nb)
        na, nb = F32(self.n_above), F32(self.n_below)
        return np.where(below, nb, na), np.where(below, na, nb)


@dataclass
class Rays:
    """Rays in flight: origins o and unit directions k (n, 3) float32, below (in the lower medium),
    weight w, bounce count nb, output id; for polarised light Stokes columns A (4, K, n) in the
    basis (s, s x k) with s (n, 3)."""

    o: np.ndarray
    k: np.ndarray
    below: np.ndarray
    w: np.ndarray
    nb: np.ndarray
    ids: np.ndarray
    A: np.ndarray | None = None
    s: np.ndarray | None = None
    F: np.ndarray | None = None      # factored columns of a ray's first interaction (`first_interaction_factors`)

    @property
    def size(self) -> int:
        return self.ids.size

    def take(self, idx: np.ndarray) -> "Rays":
        A = None if self.A is None else np.take(self.A, idx, axis=2)
        s = None if self.s is None else take_rows(self.s, idx)
        F = None if self.F is None else take_factors(self.F, idx)
        m = idx.size                                # the six gathers in one pass
        r = Rays(np.empty((m, 3), F32), np.empty((m, 3), F32), np.empty(m, bool), np.empty(m, F32),
                 np.empty(m, np.int16), np.empty(m, np.int64), A, s, F)
        kernels.gather_rays(idx.astype(np.int64, copy=False), self.o, self.k, self.below.view(np.uint8), self.w,
                            self.nb, self.ids, r.o, r.k, r.below.view(np.uint8), r.w, r.nb, r.ids)
        return r

    def columns(self, K: int) -> np.ndarray:
        """The Stokes columns (4, K, n), materialised from the factors or the identity when not held."""
        if self.A is not None:
            return self.A
        if self.F is not None:
            return columns_of_factors(self.F)
        return identity_columns(K, self.size)

    @staticmethod
    def concat(parts: list) -> "Rays":
        if len(parts) == 1:
            return parts[0]
        cat = np.concatenate
        A = F = None
        withA = [p.A for p in parts if p.A is not None]
        if withA:                                   # full columns somewhere: materialise the others
            A = cat([p.columns(withA[0].shape[1]) for p in parts], axis=2)
        elif all(p.F is not None for p in parts):   # every ray still after its first interaction: factors
            F = cat([p.F for p in parts], axis=1, out=padded_rows((6,), sum(p.size for p in parts)))
        elif any(p.F is not None for p in parts):   # factors and identities (no first-hit split)
            A = cat([p.columns(4) for p in parts], axis=2)
        s = None if parts[0].s is None else cat([p.s for p in parts])
        return Rays(cat([p.o for p in parts]), cat([p.k for p in parts]), cat([p.below for p in parts]),
                    cat([p.w for p in parts]), cat([p.nb for p in parts]), cat([p.ids for p in parts]), A, s, F)

    @staticmethod
    def empty(K: int = 0) -> "Rays":
        return Rays(np.zeros((0, 3), F32), np.zeros((0, 3), F32), np.zeros(0, bool), np.zeros(0, F32),
                    np.zeros(0, np.int16), np.zeros(0, np.int64), np.zeros((4, K, 0), F32) if K else None,
                    np.zeros((0, 3), F32) if K else None)


def take_rows(a: np.ndarray, idx: np.ndarray) -> np.ndarray:
    """np.take(a, idx, axis=0), except that a broadcast row (stride 0: the one Stokes basis of a beam's
    rays before they interact, `StokesCarrier.start`) stays a broadcast view: no copy (numpy's take
    from a stride-0 array is 3x slower than from a contiguous one)."""
    if a.shape[0] and a.strides[0] == 0:
        return np.broadcast_to(a[0], (idx.size,) + a.shape[1:])
    return np.take(a, idx, axis=0)


def take_factors(F: np.ndarray, idx: np.ndarray) -> np.ndarray:
    """np.take(F, idx, axis=1) of factors (6, n) held in padded rows (`exits.padded_rows`), row by row into
    padded rows: numpy's take along an axis first copies a non-contiguous array whole."""
    out = padded_rows((F.shape[0],), idx.size)
    for r in range(F.shape[0]):
        np.take(F[r], idx, out=out[r], mode="clip")
    return out


def identity_columns(K: int, n: int) -> np.ndarray:
    """Stokes columns (4, K, n) of the incident basis states: the identity Mueller matrix."""
    A = np.zeros((4, K, n), F32)
    for i in range(min(4, K)):
        A[i, i] = 1
    return A


def first_interaction_factors(coef, c2, s2, inv_p) -> np.ndarray:
    """The factors (6, n) of the Mueller columns M Rot / p of rays still in their incident basis:
    rows a, b, c, d (the facet's interface coefficients times inv_p, core.fresnel) and c2, s2
    (cos 2psi, sin 2psi of the frame rotation, core.stokes).  Six numbers per ray instead of the
    16 of the product (`columns_of_factors`): what a ray carries after its first interaction until
    it interacts again (most rays leave first: their exit columns come from the factors,
    `StokesCarrier.exit_columns`)."""
    F = padded_rows((6,), np.size(coef[0]))
    for x, o in zip(coef, F[:4]):
        np.multiply(x, inv_p, out=o)
    F[4] = c2
    F[5] = s2
    return F


def columns_of_factors(F: np.ndarray) -> np.ndarray:
    """Mueller columns (4, 4, n) of M Rot / p from its factors (`first_interaction_factors`): Rot the
    frame rotation by psi (core.stokes: cos 2psi = c2, sin 2psi = s2), M = [[a,b,0,0], [b,a,0,0],
    [0,0,c,d],[0,0,-d,c]] the facet's interface matrix over p (core.fresnel coefficients), the
    product written out: [[a, b c2, b s2, 0], [b, a c2, a s2, 0], [0, -c s2, c c2, d], [0, d s2, -d c2, c]]
    (tested equal to the core's matrices multiplied)."""
    a, b, c, d, c2, s2 = F
    A = np.empty((4, 4, a.size), F32)
    A[0, 0] = a
    A[1, 0] = b
    A[3, 3] = c
    A[2, 3] = d
    A[0, 3] = A[1, 3] = A[2, 0] = A[3, 0] = 0
    np.multiply(b, c2, out=A[0, 1])
    np.multiply(b, s2, out=A[0, 2])
    np.multiply(a, c2, out=A[1, 1])
    np.multiply(a, s2, out=A[1, 2])
    np.multiply(c, s2, out=A[2, 1])
    np.negative(A[2, 1], out=A[2, 1])
    np.multiply(c, c2, out=A[2, 2])
    np.multiply(d, s2, out=A[3, 1])
    np.multiply(d, c2, out=A[3, 2])
    np.negative(A[3, 2], out=A[3, 2])
    return A


def first_interaction_columns(coef, c2, s2, inv_p) -> np.ndarray:
    """Mueller columns (4, 4, n) of M Rot / p for rays still in their incident basis (A = identity):
    `columns_of_factors` of `first_interaction_factors`."""
    return columns_of_factors(first_interaction_factors(coef, c2, s2, inv_p))


def exit_columns_of_factors(F: np.ndarray, c: np.ndarray, d: np.ndarray, out: np.ndarray) -> None:
    """out (4, 4, m) <- Rot_exit (M Rot / p) from the factors F (6, m) (`first_interaction_factors`) and
    the exit rotation's c ~ s . s_exit, d ~ p . s_exit (as `core.stokes.rotate_stokes_columns_cd`).
    The same float32 operations as `rotate_stokes_columns_cd(columns_of_factors(F), c, d)` entry by
    entry (rows 1, 2: E x1 + S x2 and x2 E - x1 S with E, S = cos 2psi', sin 2psi'), skipping only
    the products with the structural zeros of M Rot: equal to it (up to the sign of a zero, which no
    sum sees).  10 of the 16 entries are one or two products."""
    a, b, cc, dd, c2, s2 = F
    E, S = double_angle_cd(c, d)
    mul = np.multiply
    out[0, 0] = a
    out[0, 3] = 0
    mul(b, c2, out=out[0, 1])
    mul(b, s2, out=out[0, 2])
    out[3, 0] = 0
    mul(dd, s2, out=out[3, 1])
    mul(dd, c2, out=out[3, 2])
    np.negative(out[3, 2], out=out[3, 2])
    out[3, 3] = cc
    mul(E, b, out=out[1, 0])                        # column 0: (b, 0) rotated
    mul(b, S, out=out[2, 0])
    np.negative(out[2, 0], out=out[2, 0])
    mul(S, dd, out=out[1, 3])                       # column 3: (0, d) rotated
    mul(dd, E, out=out[2, 3])
    x1 = np.empty_like(a)
    x2 = np.empty_like(a)
    t = np.empty_like(a)
    for j, (u1, v1, u2, v2) in ((1, (a, c2, cc, s2)), (2, (a, s2, cc, c2))):
        mul(u1, v1, out=x1)                         # row 1 of M Rot: a c2, a s2
        mul(u2, v2, out=x2)                         # row 2: -c s2, c c2
        if j == 1:
            np.negative(x2, out=x2)
        mul(E, x1, out=out[1, j])
        mul(S, x2, out=t)
        out[1, j] += t
        mul(x2, E, out=out[2, j])
        x1 *= S
        out[2, j] -= x1


@dataclass
class Facet:
    """The facets hit by a batch: unit normal on the incident side (components), cos of the
    incidence and refraction angles, n1 / n2 and the total-internal-reflection mask."""

    nfx: np.ndarray
    nfy: np.ndarray
    nfz: np.ndarray
    ci: np.ndarray
    ct: np.ndarray
    eta: np.ndarray
    tir: np.ndarray
    k3: tuple = ()          # the rays' direction components (kx, ky, kz), contiguous (`_hits`)
    n_pair: tuple | None = None   # per-ray float32 indices (n1, n2) when the compiled kernels made the facets

    def normal(self) -> np.ndarray:
        return np.stack([self.nfx, self.nfy, self.nfz], axis=1)


# ----------------------------------------------------------------------------- carriers


class IntensityCarrier:
    """Unpolarised intensity: the ray's weight is all it carries (module doc)."""

    K = 0

    def start(self, rays: Rays, s_init=None) -> None:
        """Nothing to set up."""

    def reflectance(self, rays: Rays, f: Facet, media: Media, split: bool = False) -> np.ndarray:
        """Unpolarised Fresnel reflectance of each event (1 past the critical angle)."""
        if media.is_complex:
            n1, n2 = media.pair(rays.below)
            pR = interface_coefficients_f32(f.ci, n1, n2)[0][0].astype(F32)
        else:
            # Born & Wolf 1.5.20-21 divided through by n2: (n1, n2) -> (eta, 1)
            pR = reflectance_unpolarized_f32(f.ci, f.eta, F32(1), f.ct)
        pR[f.tir] = 1
        return pR

    def transmitted_copy(self, rays: Rays, j, pR_j) -> tuple:
        return None, None, None

    def reflected(self, rays: Rays, pR) -> None:
        """Nothing but the weight changes."""

    def chosen(self, rays: Rays, refl, pR) -> None:
        """Nothing but the direction changes (weights stay)."""

    def exit_columns(self, rays: Rays, idx, phi_exit_rad: float, k_exit, out, compact=None) -> None:
        """Nothing to record."""


class StokesCarrier:
    """K Stokes columns per ray, rotated onto each facet's s/p basis (module doc).

    A ray's first interaction (from the identity columns) leaves it with the factors of M Rot / p
    (`first_interaction_factors`, rays.F: 6 numbers, not 16); they become columns (rays.A) only
    when the ray interacts again or meets rays with columns (`Rays.concat`), and a ray that leaves
    first has its exit columns computed from them (`exit_columns_of_factors`): the same numbers.
    `factored = False` materialises the columns at once (the reference the tests compare with).
    """

    factored = True

    def __init__(self, K: int):
        self.K = int(K)
        self._ev = None
        self._split = None              # (F_r, F_t) of a first interaction's both branches (`_reflectance_real`)

    def start(self, rays: Rays, s_init=None) -> None:
        """Initial basis s = z x k (or the given s_init for every ray); rays.A None stands for the
        identity columns (the incident basis states) until the first interaction."""
        if s_init is None:
            rays.s = s_axis_rows(rays.k)
        else:
            # a read-only broadcast view (no copy): the basis is replaced, never written in place
            rays.s = np.broadcast_to(np.asarray(s_init, F32), rays.k.shape)

    def reflectance(self, rays: Rays, f: Facet, media: Media, split: bool = False) -> np.ndarray:
        """Rotate the columns onto the facet's basis; P_R of column 0's state.

        The facet's basis is s' = n x k / |n x k|.  With s' = u / |u|, u = n x k, and s, p = s x k
        the ray's basis (s . k = 0, |k| = 1): s . u = |u| (s . s') and p . u = s . n, so the
        rotation's (c, d) = (s . s', p . s') are (s . u, s . n) / |u| (`rotate_stokes_columns_cd`
        needs them only up to that factor): two dot products instead of a cross product.
        Real indices (f.n_pair): one pass over the rays, `kernels.facet_event`; split (the first-hit split
        will keep both branches): rays at their first interaction get both branches' factors from the same
        pass (`first_interaction_factors`' numbers).  Complex indices (a metal): the numpy code below.
        """
        if f.n_pair is not None:
            return self._reflectance_real(rays, f, split)
        k, s_old = rays.k, rays.s
        kx, ky, kz = f.k3
        # u = n x k in three contiguous arrays (column ops on an (n, 3) array are strided, ~3x slower),
        # written into the new basis's (n, 3) rows once, by the division s' = u / |u|
        u0 = f.nfy * kz
        u0 -= f.nfz * ky
        u1 = f.nfz * kx
        u1 -= f.nfx * kz
        u2 = f.nfx * ky
        u2 -= f.nfy * kx
        sx, sy, sz = s_old[:, 0], s_old[:, 1], s_old[:, 2]
        c = sx * u0
        c += sy * u1
        c += sz * u2
        d = sx * f.nfx
        d += sy * f.nfy
        d += sz * f.nfz
        sn = u0 * u0                                # |u|^2 = u . u (as core.frames.dot_rows)
        sn += u1 * u1
        sn += u2 * u2
        np.sqrt(sn, out=sn)
        degenerate = sn < 1e-6                      # normal incidence on the facet: keep the basis
        if degenerate.any():
            sn[degenerate] = 1
            for i, ui in enumerate((u0, u1, u2)):
                ui[degenerate] = s_old[degenerate, i]
            c[degenerate] = 1
            d[degenerate] = 0
        s_new = np.empty(k.shape, F32)
        for i, ui in enumerate((u0, u1, u2)):       # as core.frames.divide_rows
            np.divide(ui, sn, out=s_new[:, i])
        n1, n2 = media.pair(rays.below)
        R, T = interface_coefficients_f32(f.ci, n1, n2)
        if rays.F is not None:                      # a second interaction: the factors become columns
            rays.A, rays.F = columns_of_factors(rays.F), None
        if rays.A is None:                          # still the identity (first interaction): no rotation yet
            self._ev = (R, T, s_new, double_angle_cd(c, d))
            return np.clip(R[0], 0, 1).astype(F32, copy=False)  # column 0 (unpolarised) is not changed by a rotation
        rotate_stokes_columns_cd(rays.A, c, d)
        self._ev = (R, T, s_new, None)
        return np.clip(R[0] + R[1] * rays.A[1, 0], 0, 1).astype(F32, copy=False)

    def _reflectance_real(self, rays: Rays, f: Facet, split: bool = False) -> np.ndarray:
        """`reflectance` for real indices in one pass over the rays (`kernels.facet_event`)."""
        n = rays.size
        if split and self.factored and rays.A is None and rays.F is None:
            # both branches' factors instead of R, T and the rotation (whose arguments the kernel leaves
            # unwritten: rows 0-2 stand in for them and serve as the new basis's scratch; row 3 is P_R)
            s_new, rows = np.empty((n, 3), F32), padded_rows((4,), n)
            F_r, F_t = padded_rows((6,), n), padded_rows((6,), n)
            kernels.facet_event(f.nfx, f.nfy, f.nfz, *f.k3, rays.s, f.ci, *f.n_pair, None, s_new, rows[0:3], rows[0],
                           rows[0], rows[0:3], rows[0:3], rows[3], F_r, F_t)
            self._ev, self._split = (None, None, s_new, None), (F_r, F_t)
            return rows[3]
        if rays.F is not None:                      # a second interaction: the factors become columns
            rays.A, rays.F = columns_of_factors(rays.F), None
        elif rays.A is not None and not rays.A.flags.c_contiguous:
            rays.A = np.ascontiguousarray(rays.A)
        s_new = np.empty((n, 3), F32)
        rows = padded_rows((14,), n)                # c2, s2, R (4), T (4), pR, the new basis's components (3)
        rot, R, T, pR = rows[0:2], rows[2:6], rows[6:10], rows[10]
        kernels.facet_event(f.nfx, f.nfy, f.nfz, *f.k3, rays.s, f.ci, *f.n_pair, rays.A, s_new, rows[11:14], rot[0],
                       rot[1], R, T, pR)
        self._ev = (R, T, s_new, None if rays.A is not None else (rot[0], rot[1]))
        return pR

    def transmitted_copy(self, rays: Rays, j, pR_j) -> tuple:
        """(A, s, F) of the transmitted copies of rays j (None: all; first-hit split), renormalised by
        1 - P_R (F: the factors of a first interaction, A None; else A)."""
        _, T, s_new, rot = self._ev
        if self._split is not None:
            full = j is None
            return None, s_new if full else np.take(s_new, j, axis=0), \
                self._split[1] if full else take_factors(self._split[1], j)
        inv = 1 / np.maximum(1 - pR_j, F32(1e-30))
        full = j is None
        sel = (lambda a: a) if full else (lambda a: np.take(a, j, axis=0))
        s_t = s_new if full else np.take(s_new, j, axis=0)   # never modified in place (replaced per event)
        if rot is not None:
            F = first_interaction_factors([sel(x) for x in T], sel(rot[0]), sel(rot[1]), inv)
            return (None, s_t, F) if self.factored else (columns_of_factors(F), s_t, None)
        A = rays.A.copy() if full else np.take(rays.A, j, axis=2)
        apply_interface_mueller_columns(A, *(sel(x) for x in T), inv)
        return A, s_t, None

    def reflected(self, rays: Rays, pR) -> None:
        """Every ray keeps its reflected branch (first-hit split), renormalised by P_R."""
        R, _, s_new, rot = self._ev
        if self._split is not None:
            rays.F, rays.s, self._split = self._split[0], s_new, None
            return
        inv = 1 / np.maximum(pR, F32(1e-30))
        if rot is not None:
            self._first(rays, first_interaction_factors(R, rot[0], rot[1], inv))
        else:
            apply_interface_mueller_columns(rays.A, *R, inv)
        rays.s = s_new

    def chosen(self, rays: Rays, refl, pR) -> None:
        """Roulette outcome per ray: reflected (refl) or transmitted, renormalised by its probability."""
        R, T, s_new, rot = self._ev
        pc = np.where(refl, pR, 1 - pR)
        coef = [np.where(refl, r, t) for r, t in zip(R, T)]
        if rot is not None:
            self._first(rays, first_interaction_factors(coef, rot[0], rot[1], 1 / np.maximum(pc, F32(1e-30))))
        else:
            apply_interface_mueller_columns(rays.A, *coef, 1 / np.maximum(pc, F32(1e-30)))
        rays.s = s_new

    def _first(self, rays: Rays, F: np.ndarray) -> None:
        """The rays' state after their first interaction: its factors (or, not factored, columns)."""
        if self.factored:
            rays.F = F
        else:
            rays.A = columns_of_factors(F)

    def exit_columns(self, rays: Rays, idx, phi_exit_rad: float, k_exit, out, compact=None) -> None:
        """Write the columns of the rays idx (all when None), re-expressed in the exit frame
        s = z x k, into `out` (4, K, m): the exit record's slot, filled row by row without a
        temporary (`np.take` into each contiguous row); k_exit (m, 3) their directions.  Rays that
        hold the factors of their first interaction: `exit_columns_of_factors`; in one pass,
        `kernels.exit_columns` (exits along z by `_exit_columns_numpy`), and where the record has flags
        (compact, (m,) uint8: `exits.Exits.compact`) the columns from factors are written compactly (6
        factors and the exit rotation, flag 1) for the binning to expand."""
        if rays.F is None and rays.A is None:       # the identity columns (no interaction yet)
            self._exit_columns_numpy(rays, idx, phi_exit_rad, k_exit, out)
            if compact is not None:
                compact[:] = 0
            return
        if kernels.exit_columns(rays.F, rays.A, rays.s, k_exit, idx, out, ALONG_Z_XY2, compact):
            zi = np.flatnonzero(k_exit[:, 0] * k_exit[:, 0] + k_exit[:, 1] * k_exit[:, 1] < ALONG_Z_XY2)
            cols = np.empty((4, self.K, zi.size), F32)
            self._exit_columns_numpy(rays, zi if idx is None else idx[zi], phi_exit_rad, k_exit[zi], cols)
            out[:, :, zi] = cols
            if compact is not None:
                compact[zi] = 0

    def _exit_columns_numpy(self, rays: Rays, idx, phi_exit_rad: float, k_exit, out) -> None:
        """`exit_columns` written whole in numpy, the fallback azimuth's frame along z included (the rows
        `kernels.exit_columns` leaves, and rays without an interaction)."""
        F = None
        if rays.F is not None:
            F = rays.F if idx is None else take_factors(rays.F, idx)
        elif rays.A is None:
            out[...] = identity_columns(self.K, k_exit.shape[0])
        elif idx is None:
            out[...] = rays.A
        else:
            for i in range(4):
                for j in range(self.K):
                    np.take(rays.A[i, j], idx, out=out[i, j], mode="clip")
        s = rays.s if idx is None else take_rows(rays.s, idx)
        k = k_exit
        # exit basis s' = z x k / |z x k|: with u = z x k = (-k_y, k_x, 0), s . u = s_y k_x - s_x k_y and
        # p . u = (s x k) . (z x k) = s_z (as in `reflectance`); along z the fallback azimuth, generically
        kx, ky = k[:, 0], k[:, 1]
        c = s[:, 1] * kx
        c -= s[:, 0] * ky
        d = s[:, 2].copy()
        h = kx * kx
        h += ky * ky
        along_z = h < ALONG_Z_XY2
        if along_z.any():
            zi = np.flatnonzero(along_z)
            s_to = s_axis_rows(k[zi], phi_exit_rad)
            c[zi] = dot_rows(s[zi], s_to)
            d[zi] = dot_rows(cross_rows(s[zi], k[zi]), s_to)
        if F is not None:
            exit_columns_of_factors(F, c, d, out)
        else:
            rotate_stokes_columns_cd(out, c, d)


def carrier_for(K: int):
    """The carrier of K Stokes columns per ray (0: unpolarised intensity)."""
    return StokesCarrier(K) if K else IntensityCarrier()


# ----------------------------------------------------------------------------- the loop


@dataclass
class _Chunk:
    """What every step of one chunk's loop shares: the scene, the exit record, the carrier, the
    media, the settings, the chunk's generator and its number of input rays."""

    tracer: object
    ex: Exits
    carrier: object
    media: Media
    settings: TraceSettings
    rng: np.random.Generator
    n0: int
    group: np.ndarray | None = None
    key: np.uint32 = np.uint32(0)


def trace_chunk(tracer, rays: Rays, carrier, media: Media, settings: TraceSettings, rng,
                s_init=None) -> Exits:
    """Trace `rays` through `tracer`'s relief layer until every ray has ended; the chunk's `Exits`.

    Phase 1 (split_first): every ray's first interaction, both branches; phase 2: roulette.
    With settings.subtiles, `Exits.first_group` holds the sub-tile of each input ray's first hit
    (its entry point if it never hit), rays.ids being 0..n-1.
    """
    keep_freed_heap()
    with np.errstate(divide="ignore", invalid="ignore"):      # once per chunk (errstate is not free)
        carrier.start(rays, s_init)
        n0 = rays.size
        ex = Exits(2 * n0 if settings.split_first else n0, carrier.K)
        ch = _Chunk(tracer, ex, carrier, media, settings, rng, n0)
        ch.key = np.uint32(rng.integers(0, 2**32))
        if settings.subtiles is not None:
            ch.group = np.empty(n0, np.int32)
            ch.group[rays.ids] = tracer.subtile_of(rays.o, settings.subtiles)
            ex.first_group = ch.group
        # Rounds of batches.  Phase 1: the first interactions (the rays, then those re-entering through a
        # tile side), whose outputs wait.  Phase 2 starts with the waiting outputs traced batch by batch as
        # they are (no concatenation of the two big branches); each later round is one batch, the rays that
        # hit in the round before and then those re-entering, in the order of the batches (the order one
        # concatenated batch would have given: the same records in the same order).
        batches, waiting, pending, segments = [rays] if rays.size else [], [], settings.split_first, 0
        while batches:
            continuing, wrapped_all = [], []
            for cur in batches:
                segments += cur.size
                q = tracer.query(cur.o, cur.k)
                if pending and q.n_hit < cur.size:     # re-entries through the tile's sides traced in place
                    q, more = _reenter_in_place(ch, cur, q)
                    segments += more
                wrapped = _misses(ch, cur, q) if q.n_hit < cur.size else None
                parts = _hits(ch, cur, q, pending) if q.n_hit else []
                if wrapped is not None:
                    wrapped_all.append(wrapped)
                (waiting if pending else continuing).extend(parts)
            if pending:
                batches = wrapped_all
                if not batches:
                    pending, batches, waiting = False, waiting, []
            else:
                rest = [b for b in continuing + wrapped_all if b.size]
                batches = [Rays.concat(rest)] if rest else []
        ex.segments, ex.n_paths = segments, n0
        return ex


def _record(ch: _Chunk, rays: Rays, idx, state) -> None:
    """Record the rays idx (None: all) as ended in `state` (one code or one per ray): direction,
    weight, bounces and id in the exit record, and the Stokes columns (exit frame) in its slot."""
    ex = ch.ex
    sl = ex.put(rays.k, idx, rays.w, rays.nb, rays.ids, state)
    if ex.A is not None:
        ch.carrier.exit_columns(rays, idx, ch.settings.phi_exit_rad, ex.k[sl], ex.A[:, :, sl],
                                None if ex.compact is None else ex.compact[sl])


def _exit_state(up: np.ndarray, below: np.ndarray) -> np.ndarray:
    """ABOVE for an upward exit from above, BELOW for a downward one from below, else a leak."""
    st = np.where(up, np.int8(ABOVE), np.int8(BELOW))
    bad = up == below
    if bad.any():
        st[bad] = LOST_LEAK
    return st


def _misses(ch: _Chunk, cur: Rays, q) -> Rays | None:
    """Rays that hit nothing: those that reached the slab's faces leave; those that reached a tile side
    re-enter from the opposite side (returned).  The exits, their states and the re-entering rays sorted in
    one pass (`kernels.classify_misses`)."""
    n = cur.size
    ei, st, wi = np.empty(n, np.int64), np.empty(n, np.int8), np.empty(n, np.int64)
    ne, nw = kernels.classify_misses(q.hit.view(np.uint8), q.lat_first, cur.k, cur.below.view(np.uint8), ABOVE,
                                     BELOW, LOST_LEAK, ei, st, wi)
    wrapped = None
    if nw:
        wi = wi[:nw]
        wrapped = cur.take(wi)
        wrapped.o = ch.tracer.reentry_points(wrapped.o, wrapped.k)
    if ne == n:                                     # every ray left (the usual end of a phase): no gathers
        _record(ch, cur, None, st)
    elif ne:
        _record(ch, cur, ei[:ne], st[:ne])
    return wrapped


def _reenter_in_place(ch: _Chunk, cur: Rays, q) -> tuple:
    """Rays of a first-interaction batch that reached a tile side before the relief re-enter from the
    opposite side and are queried again, in place, until each hits or leaves: (the batch's query with
    their results merged in, the segments they added).  Their origins in `cur` become the re-entry
    points (the points a separate batch of re-entering rays would start from); the batch then goes on
    whole, without gathering the rays that hit (most of a first batch: a few of its rays re-enter)."""
    more = 0
    while True:
        lat = q.lat_first.astype(bool)
        wi = np.flatnonzero(~q.hit & lat)
        if not wi.size:
            return q, more
        o, k = np.take(cur.o, wi, axis=0), np.take(cur.k, wi, axis=0)
        o = ch.tracer.reentry_points(o, k)
        cur.o[wi] = o
        q2 = ch.tracer.query(o, k)
        more += wi.size
        for name in ("hit", "ng", "t_hit", "lat_first"):
            getattr(q, name)[wi] = getattr(q2, name)
        q.n_hit = int(np.count_nonzero(q.hit))


def _hits(ch: _Chunk, cur: Rays, q, pending: bool) -> list:
    """Gather the rays that hit, drop numerical leaks (a ray on the wrong side of its facet), and let them
    interact; the facets from Embree's normals in one pass (`kernels.facet_geometry`)."""
    if q.n_hit == cur.size:
        h, ng, th = cur, q.ng, q.t_hit
    else:
        hi = np.flatnonzero(q.hit)
        h, ng, th = cur.take(hi), np.take(q.ng, hi, axis=0), q.t_hit[hi]
    n, media = h.size, ch.media
    out = padded_rows((12,), n)
    tir, leak = np.empty(n, bool), np.empty(n, bool)
    na, nb = (F32(0), F32(0)) if media.is_complex else (F32(media.n_above), F32(media.n_below))
    kernels.facet_geometry(ng, h.k, h.below.view(np.uint8), media.eta_up, media.eta_dn, na, nb, out,
                           tir.view(np.uint8), leak.view(np.uint8))
    if leak.any():
        li = np.flatnonzero(leak)
        _record(ch, h, li, LOST_LEAK)
        g = np.flatnonzero(~leak)
        h, th, out, tir = h.take(g), th[g], np.take(out, g, axis=1), tir[g]
        if h.size == 0:
            return []
    kx, ky, kz, nfx, nfy, nfz, ci, ct, eta, _, n1, n2 = out
    f = Facet(nfx, nfy, nfz, ci, ct, eta, tir, (kx, ky, kz))
    f.n_pair = None if media.is_complex else (n1, n2)
    return _interact(ch, h, f, th, pending)


def _interact(ch: _Chunk, h: Rays, f: Facet, th, pending: bool) -> list:
    """One interaction for rays that all hit: the continuing rays (and, pending, the split copies:
    `_first_interaction`); otherwise Russian roulette on P_R (module doc)."""
    carrier, eps = ch.carrier, ch.tracer.eps
    pR = carrier.reflectance(h, f, ch.media, split=pending)
    if pending:
        return _first_interaction(ch, h, f, th, pR)
    p = np.empty(h.k.shape, F32)                     # hit point (`core.frames.scale_rows` of k, th)
    for i in range(3):
        np.multiply(f.k3[i], th, out=p[:, i])
    p += h.o
    if ch.group is not None:
        _tag_first_hits(ch, h, p)
    h.nb = h.nb + np.int16(1)
    bt = f.eta * f.ci
    bt -= f.ct                                        # k_t = eta k + (eta ci - ct) nf; k_r = k + 2 ci nf
    absorbed = None
    refl = path_uniforms(ch.key, h.ids, h.nb) < pR
    carrier.chosen(h, refl, pR)
    a = np.where(refl, F32(1), f.eta)
    b = np.where(refl, 2 * f.ci, bt)
    off = np.where(refl, eps, -eps)
    if ch.media.absorbing_below:
        absorbed = ~refl & ~h.below                   # refracted into the absorbing medium
    h.below = h.below ^ ~refl
    h.k = _new_directions(f, a, b)
    p[:, 0] += off * f.nfx
    p[:, 1] += off * f.nfy
    p[:, 2] += off * f.nfz
    h.o = p
    return _still_tracing(ch, h, absorbed, [])


def _still_tracing(ch: _Chunk, h: Rays, absorbed, parts: list) -> list:
    """[the rays of h still tracing] + parts, the ended ones recorded (`_end_rays`)."""
    end = _end_rays(ch, h, absorbed)
    if end is not None:
        g = np.flatnonzero(~end)
        if g.size == 0:
            return parts
        h = h.take(g)
    return [h] + parts


def _first_interaction(ch: _Chunk, h: Rays, f: Facet, th, pR) -> list:
    """Every ray's first interaction, both branches (the first-hit split): the reflected one (weight w P_R,
    direction k + 2 ci nf) goes on in h, the transmitted copy (id + n0, weight w (1 - P_R), direction
    eta k + (eta ci - ct) nf renormalised) is returned beside it; points and directions in one pass
    (`kernels.split_rays`, which also tags the first hits' sub-tiles), the scalars in another
    (`kernels.split_weights`)."""
    n = h.size
    o_r, k_r, o_t, k_t = (np.empty((n, 3), F32) for _ in range(4))
    tag = ch.group is not None                      # the first hits' sub-tiles tagged in the same pass
    kernels.split_rays(*f.k3, f.nfx, f.nfy, f.nfz, f.eta, f.ci, f.ct, th, h.o, ch.tracer.eps, None, o_r, k_r, o_t,
                       k_t, ch.tracer.subtile_grid(ch.settings.subtiles) if tag else None, h.ids if tag else None,
                       ch.group if tag else None)
    w_r, w_t, below_t = np.empty(n, F32), np.empty(n, F32), np.empty(n, bool)
    ids_t, nb_next = np.empty(n, np.int64), np.empty(n, np.int16)
    n_t = kernels.split_weights(h.w, pR, h.below.view(np.uint8), h.ids, h.nb, ch.n0, w_r, w_t,
                                below_t.view(np.uint8), ids_t, nb_next)
    h.nb = nb_next
    tr = _split_copies(ch, h, pR, (o_t, k_t, below_t, w_t, ids_t), n_t)
    h.w = w_r
    ch.carrier.reflected(h, pR)
    h.k, h.o = k_r, o_r
    return _still_tracing(ch, h, None, [] if tr is None else [tr])


def path_uniforms(key: np.uint32, ids: np.ndarray, nb: np.ndarray) -> np.ndarray:
    """Uniform float32 numbers in [0, 1) per path, a pure function of (key, id, interaction count).

    An integer hash of the three (multiplicative mixing, then the xor-shift-multiply finaliser
    of a 32-bit avalanche hash: every input bit flips each output bit with probability ~1/2),
    whose top 24 bits make the float.  Module doc: common random numbers.
    """
    x = ids.astype(np.uint32)
    x *= np.uint32(0x9E3779B1)
    y = nb.astype(np.uint32)
    y *= np.uint32(0x85EBCA77)
    x ^= y
    x ^= key
    for shift, mul in ((16, 0x7FEB352D), (15, 0x846CA68B)):
        x ^= x >> np.uint32(shift)
        x *= np.uint32(mul)
    x ^= x >> np.uint32(16)
    x >>= np.uint32(8)
    u = x.astype(F32)
    u *= F32(2.0**-24)
    return u


def _tag_first_hits(ch: _Chunk, h: Rays, p) -> None:
    """Record the sub-tile of the first hit of rays hitting for the first time (nb == 0) without the
    first-hit split (with it, `kernels.split_rays` tags them)."""
    if not ch.settings.split_first:
        fi = np.flatnonzero(h.nb == 0)
        if fi.size:
            ch.group[h.ids[fi]] = ch.tracer.subtile_of(np.take(p, fi, axis=0), ch.settings.subtiles)


def _split_copies(ch: _Chunk, h: Rays, pR, made: tuple, n_t: int) -> Rays | None:
    """Transmitted branch of every ray's first interaction (id + n0, weight w (1 - P_R)); none where
    nothing is transmitted (P_R = 1: TIR).  made: the origins, directions, sides, weights and ids of
    every ray's refracted branch (`_first_interaction`, n_t of them with P_R < 1)."""
    if n_t == 0:
        return None
    j = None if n_t == h.size else np.flatnonzero(pR < 1)
    if j is not None and j.size == h.size:
        j = None                                    # usually every ray transmits something: no gathers
    if j is not None and not j.size:
        return None
    full = j is None
    sel = (lambda a: a) if full else (lambda a: a[j])
    ot, kt = made[:2] if full else (np.take(made[0], j, axis=0), np.take(made[1], j, axis=0))
    A, s, F = ch.carrier.transmitted_copy(h, j, sel(pR))
    tr = Rays(ot, kt, sel(made[2]), sel(made[3]), sel(h.nb), sel(made[4]), A, s, F)
    if ch.media.absorbing_below:
        gone = ~sel(h.below)                        # copies from above went into the absorbing medium
        if gone.any():
            gi = np.flatnonzero(gone)
            _record(ch, tr, gi, LOST_ABSORBED)
            tr = tr.take(np.flatnonzero(~gone))
    return tr


def _unit_rows(v3) -> np.ndarray:
    """(n, 3) rows v / |v| from the components v3 (contiguous): the operations of
    `divide_rows(v, np.sqrt(dot_rows(v, v)))` on the rows written from v3, read from v3."""
    x, y, z = v3
    nr = x * x
    nr += y * y
    nr += z * z
    np.sqrt(nr, out=nr)
    out = np.empty((x.size, 3), F32)
    for i, vi in enumerate(v3):
        np.divide(vi, nr, out=out[:, i])
    return out


def _new_directions(f: Facet, a, b) -> np.ndarray:
    """(a k + b nf) / |a k + b nf| per ray; k the rays' directions (f.k3)."""
    nf = (f.nfx, f.nfy, f.nfz)
    return _unit_rows([a * ki + b * ni for ki, ni in zip(f.k3, nf)])


def _end_rays(ch: _Chunk, h: Rays, absorbed):
    """Record the rays absorbed or past max_bounces; the mask of ended rays (None: none ended)."""
    settings = ch.settings
    end = None
    if absorbed is not None and absorbed.any():
        ai = np.flatnonzero(absorbed)
        _record(ch, h, ai, LOST_ABSORBED)
        end = absorbed
    over = h.nb >= settings.max_bounces
    if over.any():
        sel = over if end is None else over & ~end
        oi = np.flatnonzero(sel)
        _record(ch, h, oi, LOST_BOUNCES)
        end = over if end is None else end | over
    return end
