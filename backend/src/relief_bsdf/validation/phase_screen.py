"""Scalar Kirchhoff thin phase screen of a real relief: a wave-optics rough face for photon runs.

`PhaseScreenFace` has the rough-face interface of the validation's photon engine
(validation/photon.py), `interact(d, S, e, inside, n_glass, rng) -> (d, S, e, inside, alive)`,
so the whole plate is still run by `photon.run_photons`; only the front-face event is wave
optics.  It is the wave-optics generator of the concealed `diffraction` / `partial_coherence`
cases (`conceal.py`) and is independent of the forward model's model of those effects (the
diagnosis's Beckmann / Debye-Waller description built from the relief's rms height and slope
only): nothing here uses the Gaussian formulas, the coherent and diffuse parts come out of the
Fourier transform of the real relief's phase.

Physics of one event (photon arriving with propagation direction d in medium n1 at the mean
plane z = 0; exp(-i w t) convention; heights h(x) towards +z, air side):

1. Fresnel choice at the MEAN plane (normal +-z) with `photon.interface_event`: the
   reflect / transmit choice, the Stokes update (Born & Wolf 1.5.20-21 Mueller matrix) and
   the specular direction d_s in medium n_out (n1 for R, n2 for T).
2. Thin-element phase (Goodman, Introduction to Fourier Optics, sec. 5.1; Beckmann &
   Spizzichino 1963, ch. 3): the field leaving the mean plane is the specular plane wave
   times exp(i phi(x)), phi = a h(x), a = k0 (n1 d_z - n_out d_s,z) (the difference of the
   normal wave-vector components of the incident and specular waves):
   reflection a = 2 k0 n1 d_z (|a| = 2 k0 n1 cos theta1), transmission
   a = k0 sign(d_z) (n1 cos theta1 - n2 cos theta2) (theta2 by Snell).
3. Plane-wave spectrum (grating equation): the order of spatial frequency f = (fx, fy)
   (cycles per metre, numpy FFT convention: the coefficient at f multiplies exp(+2 pi i f.x))
   leaves with transverse wave vector k_s,xy + 2 pi f, i.e. the direction
   d_xy = (n1 d_in,xy + lambda f) / n_out, d_z = +-sqrt(1 - |d_xy|^2) on the side of the
   event.  Power per order: P(f) = |<u>|^2 delta(f) + D(f), u = exp(i phi):
   - the coherent (mean-field) part |<u>|^2, <u> the mean of u over the tile, is the f = 0
     order of the tile's FFT (exactly) and leaves in the specular direction.  For Gaussian
     heights it is the Debye-Waller factor exp(-a^2 sigma^2), but here it is whatever the
     real relief gives;
   - the diffuse part D(f) is the ensemble-averaged power spectrum of the fluctuation
     v = u - <u>.  A periodic tile has discrete orders whose diffuse powers are speckled
     (exponential statistics); a mm-sized spot records the ensemble average.  It is estimated
     by Welch averaging (Welch 1967): |FFT(w v_patch)|^2 over 16 half-overlapping square
     sub-patches of half the tile (periodic wrap, so every point is used equally), w a 2-D
     Hann window, summed and normalised to the diffuse energy 1 - |<u>|^2 (exact by Parseval,
     since |u| = 1).  Angular resolution lambda / patch (0.5 deg for a 64 um patch at 550 nm),
     well below a goniophotometer's detector half-angle; inside a frequency bin the order is
     drawn uniformly (the ensemble spectrum is continuous).
   Energy convention: the mean-plane Fresnel coefficients set the energy on each side; the
   screen only redistributes it over the propagating orders.  Evanescent orders are
   discarded and the rest renormalised (a photon drawing an evanescent order draws again;
   after 64 draws it is counted lost: only when nearly every order is evanescent).  No
   obliquity / Kirchhoff angular factor (near-specular approximation).
4. Sampling: per photon by inverse CDF (vectorised `searchsorted`), then uniform jitter in
   the bin.  P(f) is cached per quantised phase factor a: da = 0.04 rad / max|h|, so the
   phase error max|h| da / 2 <= 0.02 rad.  Photons of the first (illuminated) event share one
   a per side.
5. Polarisation: the Stokes vector of the mean-plane event is kept and its s-axis e is
   re-orthogonalised to the new direction (near-specular approximation: the angular kick does
   not change the polarisation state).
6. Sampling grid: the relief is Fourier-interpolated (periodic, band-limited; the Nyquist row
   and column dropped) onto a finer grid when the largest local spatial frequency of the
   phase, max|grad(phi)| / 2 pi, would exceed the grid's Nyquist frequency (no aliasing).

Partial coherence (paper, "Role of incoherence"; Mandel & Wolf 1995 sec. 5.6, Gaussian
Schell-model source): with `coherence_length_um = l_c` the incident field on events of
photons arriving FROM OUTSIDE (the source's beam) is exp(i psi(x)), psi a periodic Gaussian
random field of variance s^2 (s = 4) and autocorrelation exp(-r^2 / (2 L^2)), L = s l_c, so
that the mutual coherence <exp(i(psi(x) - psi(x + r)))> = exp(-s^2 (1 - exp(-r^2/2L^2)))
~ exp(-r^2 / (2 l_c^2)) (relative error ~ 1/(4 s^2) on the width; the floor exp(-s^2) ~ 1e-7).
The far field is then the coherent one convolved with a Gaussian angular spectrum of 1-sigma
lambda / (2 pi l_c) per axis (in air).  The average over illumination instances is a Monte
Carlo over `realisations` seeded fields per event (photons split evenly between them).  Inner
events (photons coming back from inside the plate) are taken coherent: the beam inside is
no longer the source's, and an exact treatment would need the field's memory between faces
(approximation; the plate is thick, faces add incoherently anyway).
Validity: l_c >> lambda, l_c << tile.

Validity of the whole: small slopes (rms slope <~ 0.2 rad; thin-element approximation, no
shadowing or multiple scattering), scalar theory (polarisation carried as in 5), lateral
scales of the relief >~ lambda, plate thick (faces add incoherently), periodic tile much
larger than the relief's correlation length.
"""
from __future__ import annotations

from collections import OrderedDict
from dataclasses import dataclass

import numpy as np
from scipy import fft as sp_fft

from relief_bsdf.core.frames import normalize
from relief_bsdf.validation.photon import interface_event

PSI_SIGMA = 4.0            # rms of the partial-coherence phase field psi (rad)
PHASE_QUANTUM_RAD = 0.04   # max|h| * da: phase error of the cached screens <= half of it (0.02 rad)
MAX_DRAWS = 64


def fourier_upsample(h: np.ndarray, m: int) -> np.ndarray:
    """Band-limited (periodic) interpolation of a 2-D map onto an m-times finer grid."""
    if m == 1:
        return np.asarray(h, float)
    ny, nx = h.shape
    H = np.fft.fft2(h)
    fy = np.fft.fftfreq(ny) * ny
    fx = np.fft.fftfreq(nx) * nx
    keep_y = np.abs(fy) < ny / 2       # the Nyquist row / column (even sizes) is dropped
    keep_x = np.abs(fx) < nx / 2
    out = np.zeros((ny * m, nx * m), complex)
    iy = np.where(fy >= 0, fy, fy + ny * m).astype(int)[keep_y]
    ix = np.where(fx >= 0, fx, fx + nx * m).astype(int)[keep_x]
    out[np.ix_(iy, ix)] = H[np.ix_(keep_y, keep_x)]
    return np.real(np.fft.ifft2(out)) * m * m


def _compact(coh: float, diff: np.ndarray) -> tuple:
    """(coherent weight, float32 CDF, flat bin indices) over the bins of probability > 1e-10."""
    p = diff.ravel()
    bins = np.flatnonzero(p > 1e-10).astype(np.int32)
    if bins.size == 0:
        bins = np.array([0], np.int32)
    return coh, np.cumsum(p[bins]).astype(np.float32), bins


def _hann(n: int) -> np.ndarray:
    return 0.5 - 0.5 * np.cos(2 * np.pi * np.arange(n) / n)


def gaussian_phase_field(shape: tuple, pitch_m: float, corr_m: float, sigma_rad: float,
                         rng: np.random.Generator) -> np.ndarray:
    """Periodic Gaussian random phase field with autocorrelation sigma^2 exp(-r^2 / (2 corr^2)).

    The Gaussian Schell source's convention (Mandel & Wolf 1995, sec. 5.6.4): a coherence length
    l_c = corr gives an angular spectrum of 1-sigma 1 / (k l_c), i.e. the diagnosis's blur
    lambda / (2 pi l_c).  Drawn by the project's one random-field generator
    (`surface.synth.gaussian_field`, autocovariance s^2 exp(-r^2 / L^2)) with L = sqrt(2) corr.
    """
    from relief_bsdf.surface.synth import RandomFieldSpec, gaussian_field
    ny, nx = shape
    spec = RandomFieldSpec(nx=nx, ny=ny, pitch_m=pitch_m, rms_height_m=sigma_rad,
                           corr_length_m=np.sqrt(2.0) * corr_m, kind="gaussian", exact_rms=True)
    return gaussian_field(spec, rng)


@dataclass
class _Event:
    """One screen event's photon arrays: incoming directions, outgoing directions (set in place),
    incident and outgoing indices, and which photons are still alive."""

    din: np.ndarray
    dnew: np.ndarray
    n1: np.ndarray
    n_out: np.ndarray
    alive: np.ndarray


@dataclass(frozen=True)
class ScreenSampling:
    """How a phase screen is sampled: n_max, the largest glass index the face will see (sets the
    sampling grid); realisations, illumination instances per outer event (partial coherence);
    upsample, the grid refinement factor (None = automatic, at most 4); cache_mb, memory for
    the cached P(f) tables (LRU)."""

    n_max: float = 1.6
    realisations: int = 16
    upsample: int | None = None
    cache_mb: float = 200.0


class PhaseScreenFace:
    """Rough face as a scalar Kirchhoff thin phase screen of the real relief (module docstring).

    heights_m: periodic height map (metres, finite); dx_m, dy_m: pitch; wavelength_nm: vacuum
    wavelength (one face per wavelength); coherence_length_um: None = fully coherent source,
    else the Gaussian Schell-model coherence length; sampling: `ScreenSampling` (grid, number
    of realisations, cache).  A table keeps only the bins of probability > 1e-10 (their
    indices and a float32 CDF; the dropped mass, < 1e-10 per bin, is renormalised away): photons
    trapped in the plate revisit hundreds of phase factors on every event of run_photons, and the
    cache must hold them all.
    """

    def __init__(self, heights_m: np.ndarray, dx_m: float, dy_m: float, wavelength_nm: float,
                 coherence_length_um: float | None = None, sampling: ScreenSampling = ScreenSampling()):
        n_max, realisations, upsample = sampling.n_max, sampling.realisations, sampling.upsample
        h = np.asarray(heights_m, float)
        if not np.all(np.isfinite(h)):
            raise ValueError("PhaseScreenFace needs a height map without holes (fill NaNs first)")
        if abs(dx_m - dy_m) > 1e-6 * dx_m:
            raise ValueError("PhaseScreenFace needs a square pitch (dx = dy)")
        h = h - h.mean()
        self.wavelength_m = wavelength_nm * 1e-9
        self.k0 = 2 * np.pi / self.wavelength_m
        self.n_max = float(n_max)
        self.l_c = None if coherence_length_um in (None, 0) else float(coherence_length_um) * 1e-6
        self.realisations = int(realisations)
        # largest local frequency of the phase (cycles / m): inner reflection 2 k0 n_max |grad h|,
        # outer events 2 k0 |grad h| + |grad psi| (psi per-axis gradient rms 1 / l_c, 5 sigma)
        gy, gx = np.gradient(h, dy_m, dx_m)
        gmax = float(max(np.abs(gx).max(), np.abs(gy).max()))
        f_loc = 2 * self.k0 * self.n_max * gmax / (2 * np.pi)
        if self.l_c is not None:
            f_loc = max(f_loc, (2 * self.k0 * gmax + 5.0 / self.l_c) / (2 * np.pi))
        if upsample is None:
            upsample = int(min(4, max(1, np.ceil(2 * f_loc * dx_m * 1.05))))
        self.upsample = int(upsample)
        self.h = fourier_upsample(h, self.upsample)
        self.pitch_m = dx_m / self.upsample
        ny, nx = self.h.shape
        if ny % 4 or nx % 4:
            raise ValueError(f"PhaseScreenFace needs map sizes divisible by 4 (got {ny} x {nx})")
        self.shape = (ny, nx)
        self.patch = (ny // 2, nx // 2)
        self.fy = np.fft.fftfreq(self.patch[0], d=self.pitch_m)
        self.fx = np.fft.fftfreq(self.patch[1], d=self.pitch_m)
        self.window32 = np.outer(_hann(self.patch[0]), _hann(self.patch[1])).astype(np.float32)
        self.h32 = self.h.astype(np.float32)
        hmax = float(np.abs(self.h).max())
        self.da = PHASE_QUANTUM_RAD / max(hmax, 1e-12)
        self.max_h_m = hmax
        self._cache: OrderedDict = OrderedDict()
        self.cache_bytes = int(sampling.cache_mb * 2**20)
        self._cached_bytes = 0
        self.tables_built = 0

    # ---------------------------------------------------------------- the screen's spectrum

    def spectrum(self, a: float, psi: np.ndarray | None = None) -> tuple[float, np.ndarray]:
        """(coherent weight |<u>|^2, diffuse probabilities D(f) over the patch's FFT grid, sum
        1 - |<u>|^2) of u = exp(i (a h + psi)); Welch estimate as in the module docstring."""
        ph = np.float32(a) * self.h32
        if psi is not None:
            ph += psi.astype(np.float32)
        c = np.cos(ph)
        sn = np.sin(ph)
        mean = complex(c.mean(dtype=np.float64), sn.mean(dtype=np.float64))
        coh = float(min(abs(mean) ** 2, 1.0))
        u = np.empty(ph.shape, np.complex64)
        u.real = c - np.float32(mean.real)
        u.imag = sn - np.float32(mean.imag)
        ny, nx = self.shape
        my, mx = self.patch
        big = np.pad(u, ((0, my // 2), (0, mx // 2)), mode="wrap")     # periodic tile, wrapped patches
        buf = np.empty((4, my, mx), np.complex64)
        acc = np.zeros(self.patch, np.float32)
        for oy in range(0, ny, my // 2):
            for k, ox in enumerate(range(0, nx, mx // 2)):
                np.multiply(big[oy:oy + my, ox:ox + mx], self.window32, out=buf[k])
            spec = sp_fft.fft2(buf, axes=(-2, -1), overwrite_x=True)
            acc += (spec.real ** 2 + spec.imag ** 2).sum(axis=0)
        acc = acc.astype(np.float64)
        tot = acc.sum()
        diff = acc * ((1.0 - coh) / tot) if tot > 0 else acc
        self.tables_built += 1
        return coh, diff

    def _table(self, a_q: float):
        key = round(a_q / self.da)
        t = self._cache.get(key)
        if t is None:
            coh, diff = self.spectrum(key * self.da)
            t = _compact(coh, diff)
            self._cache[key] = t
            self._cached_bytes += t[1].nbytes + t[2].nbytes
            while self._cached_bytes > self.cache_bytes and len(self._cache) > 1:
                _, old = self._cache.popitem(last=False)
                self._cached_bytes -= old[1].nbytes + old[2].nbytes
        else:
            self._cache.move_to_end(key)
        return t

    def _draw(self, coh: float, cdf: np.ndarray, bins: np.ndarray, n: int, rng: np.random.Generator):
        """n draws of (fx, fy) (cycles / m); the coherent order is f = 0 exactly."""
        u = rng.random(n)
        fx = np.zeros(n)
        fy = np.zeros(n)
        dif = u >= coh
        if dif.any():
            target = ((u[dif] - coh) / max(1.0 - coh, 1e-300) * float(cdf[-1])).astype(np.float32)
            k = np.searchsorted(cdf, target, side="right")
            k = bins[np.minimum(k, cdf.size - 1)]
            iy, ix = np.divmod(k, self.patch[1])
            dfy = 1.0 / (self.patch[0] * self.pitch_m)
            dfx = 1.0 / (self.patch[1] * self.pitch_m)
            fy[dif] = self.fy[iy] + (rng.random(k.size) - 0.5) * dfy
            fx[dif] = self.fx[ix] + (rng.random(k.size) - 0.5) * dfx
        return fx, fy

    # ---------------------------------------------------------------- the event

    def interact(self, d, S, e, inside, n_glass, rng):
        if n_glass > self.n_max:
            raise ValueError(f"glass index {n_glass} above the n_max {self.n_max} the screen was sampled for")
        n = len(d)
        nz = np.where(d[:, 2] < 0, 1.0, -1.0)                  # mean-plane normal facing the incident medium
        nf = np.zeros((n, 3))
        nf[:, 2] = nz
        n1 = np.where(inside, n_glass, 1.0)
        n2 = np.where(inside, 1.0, n_glass)
        din = d.copy()
        ds, Sn, en, refl = interface_event(d, S, e, nf, n1, n2, rng.random(n))
        n_out = np.where(refl, n1, n2)
        a = self.k0 * (n1 * din[:, 2] - n_out * ds[:, 2])
        a_q = np.round(a / self.da)
        ev = _Event(din=din, dnew=ds.copy(), n1=n1, n_out=n_out, alive=np.ones(n, bool))
        dnew, alive = ev.dnew, ev.alive
        outer = ~inside
        groups = []                                            # (photon indices, psi realisation or None)
        if self.l_c is not None and outer.any():
            idx = np.nonzero(outer)[0]
            k = max(1, min(self.realisations, idx.size // 200))
            for j, part in enumerate(np.array_split(rng.permutation(idx), k)):
                groups.append((part, j))
            inner_idx = np.nonzero(~outer)[0]
        else:
            inner_idx = np.arange(n)
        for key in np.unique(a_q[inner_idx]):
            groups.append((inner_idx[a_q[inner_idx] == key], None))
        psi_cache = {}
        for part, real in groups:
            if part.size == 0:
                continue
            if real is None:
                tables = {a_q[part[0]]: self._table(a_q[part[0]] * self.da)}
            else:
                if real not in psi_cache:
                    psi_cache[real] = gaussian_phase_field(self.shape, self.pitch_m, PSI_SIGMA * self.l_c,
                                                           PSI_SIGMA, rng)
                tables = {}
                for key in np.unique(a_q[part]):
                    coh, diff = self.spectrum(key * self.da, psi_cache[real])
                    tables[key] = _compact(coh, diff)
            for key, table in tables.items():
                self._kick(ev, part[a_q[part] == key], table, rng)
        # polarisation kept, s-axis re-orthogonalised to the new direction
        en = en - np.einsum("ij,ij->i", en, dnew)[:, None] * dnew
        bad = np.linalg.norm(en, axis=1) < 1e-9
        if bad.any():
            en[bad] = np.cross(dnew[bad], np.array([0.0, 0.0, 1.0])) + 1e-3 * np.array([1.0, 0.0, 0.0])
        en = normalize(en)
        ins_new = np.where(refl, inside, ~inside)
        return dnew, Sn, en, ins_new, alive

    def _kick(self, ev: "_Event", sel: np.ndarray, table: tuple, rng: np.random.Generator) -> None:
        """Draw propagating orders from `table` (coherent weight, CDF, bins) for photons `sel` of the
        event and set their directions in `ev.dnew` (in place); after MAX_DRAWS evanescent draws a
        photon is lost (`ev.alive`)."""
        coh, cdf, bins = table
        todo = sel
        lam = self.wavelength_m
        for _ in range(MAX_DRAWS):
            if todo.size == 0:
                break
            fx, fy = self._draw(coh, cdf, bins, todo.size, rng)
            qx = ev.n1[todo] * ev.din[todo, 0] + lam * fx
            qy = ev.n1[todo] * ev.din[todo, 1] + lam * fy
            no = ev.n_out[todo]
            sx, sy = qx / no, qy / no
            s2 = sx * sx + sy * sy
            ok = s2 < 1.0
            sg = np.sign(ev.dnew[todo, 2])
            g = todo[ok]
            ev.dnew[g, 0] = sx[ok]
            ev.dnew[g, 1] = sy[ok]
            ev.dnew[g, 2] = sg[ok] * np.sqrt(1.0 - s2[ok])
            todo = todo[~ok]
        ev.alive[todo] = False
