"""Photon transport through a solid plate with a rough face, polarisation tracked (Stokes).

This is the photon engine shared by the diagnosis forward model (`effects.py`) and the
concealed-data generator (`conceal.py`).  What differs between the two is the *rough-face
interaction*, passed in as an object with one method

    face.interact(d, S, e, inside, n_glass, rng) -> (d, S, e, inside, alive)

which moves a batch of photons that arrive at the rough face (propagation directions `d`,
Stokes vectors `S` in the frame whose s-axis is `e`, medium flag `inside` = in the glass)
until each has left the face region: going up in air (reflected side) or down in the
glass.  Two implementations exist:

- `NormalsFace` (here): random bump mapping over the *measured facet normals* of the relief
  (paper sec. 2.2, "density of normals"): each hit picks one facet with probability
  proportional to its projected visible area; no shadowing, no lateral correlation.
- `conceal.HeightFieldFace`: exact ray tracing through the triangulated height field
  (Embree), with shadowing and interreflection on the relief (paper sec. 2.3).

Plate (geometric optics, lateral extent infinite, so lateral offsets do not matter for
a BSDF): front face at z = 0 (the relief, thin compared to the thickness t), back face at
z = -t, flat or a Beckmann microfacet surface (roughness alpha, Walter et al. 2007 eq. 25
slope distribution).  Bulk: Beer-Lambert absorption exp(-a L) along each path in the
glass (weights), optional volume scattering with free paths ~ Exp(mu_s) and a
Henyey-Greenstein phase function (Henyey & Greenstein 1941; polarisation carried over
unchanged, a scalar approximation of the volume phase matrix).  Every interface event is a
Fresnel Mueller matrix in the local s/p basis (`optics.mueller_interface`, Born & Wolf
1.5.20-21) with the Stokes frame rotated onto the local plane of incidence (Chandrasekhar
rotation), and the reflect/transmit choice drawn with the probability (M S)_0 / S_0, so the
photon keeps S_0 = 1 and its weight changes only by absorption.

Detection (formats.md): f = P_detector / (P_incident Omega cos theta_s), with a uniform
detector cone of half-angle a around each row direction (`detect`), or that cone convolved
with a Gaussian angular blur (`detect(..., blur_sigma_deg=s)`, second-moment matched).

Assumptions / validity: geometric optics (relief lateral scales >> wavelength), plate
thickness >> relief height, incoherent sum of paths (no thin-film fringes), air outside
(n = 1), real glass index.
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from relief_bsdf.core.optics import cos_transmitted, fresnel_amplitudes, refract

# ------------------------------------------------------------------ small vector helpers


def _dot(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    return np.einsum("ij,ij->i", a, b)


def _normalize(v: np.ndarray) -> np.ndarray:
    return v / np.linalg.norm(v, axis=1, keepdims=True)


def _perp_any(d: np.ndarray) -> np.ndarray:
    """A unit vector perpendicular to each row of d."""
    a = np.where(np.abs(d[:, :1]) < 0.9, np.array([[1.0, 0, 0]]), np.array([[0, 1.0, 0]]))
    return _normalize(np.cross(d, a))


def direction(theta_deg, phi_deg, down: bool = False) -> np.ndarray:
    """Unit vectors w(theta, phi) of formats.md; `down` mirrors z (T side)."""
    t = np.radians(np.asarray(theta_deg, float))
    p = np.radians(np.asarray(phi_deg, float))
    z = np.cos(t) * (-1.0 if down else 1.0)
    return np.stack([np.sin(t) * np.cos(p), np.sin(t) * np.sin(p), z], axis=-1)


def rot_y(tau_rad: float) -> np.ndarray:
    """Rotation matrix about the y axis (a sample tilted in the plane of incidence)."""
    c, s = np.cos(tau_rad), np.sin(tau_rad)
    return np.array([[c, 0.0, s], [0.0, 1.0, 0.0], [-s, 0.0, c]])


# ------------------------------------------------------------------ one interface event


def _apply_mueller(a, b, S, scale):
    """M S for the interface Mueller matrix with amplitudes a (s) and b (p), as
    optics.mueller_interface (Born & Wolf 1.5.27 power factor in `scale`)."""
    A = np.abs(a) ** 2
    B = np.abs(b) ** 2
    C = a * np.conj(b)
    out = np.empty_like(S)
    out[:, 0] = 0.5 * (A + B) * S[:, 0] + 0.5 * (A - B) * S[:, 1]
    out[:, 1] = 0.5 * (A - B) * S[:, 0] + 0.5 * (A + B) * S[:, 1]
    out[:, 2] = np.real(C) * S[:, 2] + np.imag(C) * S[:, 3]
    out[:, 3] = -np.imag(C) * S[:, 2] + np.real(C) * S[:, 3]
    return out * np.asarray(scale)[..., None] if np.ndim(scale) else out * scale


def interface_event(d, S, e, nf, n1, n2, u):
    """Fresnel reflection or refraction of photons with Stokes tracking.

    d: (n,3) propagation directions; nf: (n,3) facet normals facing the incident medium
    (d . nf < 0); n1, n2: indices (scalars or (n,)) of the incident and other medium;
    S: (n,4) Stokes vectors with S0 = 1 in the frame whose s-axis is e (n,3);
    u: (n,) uniform numbers.  Returns (d_new, S_new, e_new, reflected).
    """
    wi = -d
    cos_i = np.clip(_dot(wi, nf), 1e-9, 1.0)
    s_vec = np.cross(d, nf)
    ns = np.linalg.norm(s_vec, axis=1)
    degenerate = ns < 1e-9
    s_vec = np.where(degenerate[:, None], e, s_vec / np.where(degenerate, 1.0, ns)[:, None])
    # rotate Stokes from frame e to frame s_vec (angle psi about d)
    cpsi = _dot(e, s_vec)
    spsi = _dot(d, np.cross(e, s_vec))
    c2 = cpsi * cpsi - spsi * spsi
    s2 = 2 * cpsi * spsi
    S1 = c2 * S[:, 1] + s2 * S[:, 2]
    S2 = -s2 * S[:, 1] + c2 * S[:, 2]
    Sr = np.stack([S[:, 0], S1, S2, S[:, 3]], axis=1)
    # Mueller matrices of reflection / transmission applied without forming 4x4 arrays
    rs, rp, ts, tp = fresnel_amplitudes(cos_i, n1, n2)
    ct = cos_transmitted(cos_i, n1, n2)
    scale_t = np.real(np.asarray(n2, dtype=complex) * ct) / np.real(np.asarray(n1, dtype=complex) * cos_i)
    SR = _apply_mueller(rs, rp, Sr, 1.0)
    ST = _apply_mueller(ts, tp, Sr, scale_t)
    pR = np.clip(SR[:, 0] / np.maximum(SR[:, 0] + ST[:, 0], 1e-300), 0.0, 1.0)
    refl = u < pR
    eta = np.broadcast_to(np.real(np.asarray(n1, dtype=complex) / np.asarray(n2, dtype=complex)), cos_i.shape)
    wt, ok = refract(wi, nf, eta)
    refl = refl | ~ok
    d_ref = d - 2.0 * _dot(d, nf)[:, None] * nf
    d_new = np.where(refl[:, None], d_ref, wt)
    Snew = np.where(refl[:, None], SR, ST)
    Snew = Snew / np.maximum(Snew[:, :1], 1e-300)
    return _normalize(d_new), Snew, s_vec, refl


# ------------------------------------------------------------------ rough-face models


@dataclass
class NormalsFace:
    """Random bump mapping over a set of facet normals (the measured relief's, by default).

    normals: (m, 3) unit normals pointing up (+z), one per relief pixel; the probability of
    hitting facet k from direction d is proportional to its area (1/m_z per unit projected
    area) times |d . m_k| on the facing side (projected visible area).  A photon leaving a
    facet on the wrong side of the mean plane hits another facet (up to `max_hits`); the
    rare remainder is dropped.  Single-scatter in spirit: no shadowing, no correlation
    between successive facets.
    """

    normals: np.ndarray
    max_hits: int = 6

    def __post_init__(self) -> None:
        m = np.asarray(self.normals, float).reshape(-1, 3)
        m = m[m[:, 2] > 1e-3]
        self.normals = _normalize(m)
        self._area = 1.0 / self.normals[:, 2]
        self._amax = float(self._area.max())

    @staticmethod
    def from_heights(heights_m: np.ndarray, dx_m: float, dy_m: float, periodic: bool = True) -> "NormalsFace":
        """Facet normals of the triangulated height map (two triangles per grid cell, split
        along the a-d diagonal, the same triangulation the ray tracer uses); cells touching a
        NaN point are skipped; periodic maps wrap around."""
        h = np.asarray(heights_m, float)
        if periodic:
            a, b = h, np.roll(h, -1, 1)
            c, d = np.roll(h, -1, 0), np.roll(np.roll(h, -1, 0), -1, 1)
        else:
            a, b, c, d = h[:-1, :-1], h[:-1, 1:], h[1:, :-1], h[1:, 1:]
        gx = np.concatenate([((b - a) / dx_m).ravel(), ((d - c) / dx_m).ravel()])
        gy = np.concatenate([((d - b) / dy_m).ravel(), ((c - a) / dy_m).ravel()])
        ok = np.isfinite(gx) & np.isfinite(gy)
        n = np.stack([-gx[ok], -gy[ok], np.ones(int(ok.sum()))], axis=1)
        return NormalsFace(_normalize(n))

    def _pick(self, d: np.ndarray, rng: np.random.Generator) -> np.ndarray:
        """Sample visible facets for each direction by rejection (vectorised)."""
        n = len(d)
        out = np.empty((n, 3))
        todo = np.arange(n)
        up = d[:, 2] > 0
        for _ in range(200):
            if todo.size == 0:
                break
            k = rng.integers(0, len(self.normals), todo.size)
            m = self.normals[k]
            dm = _dot(d[todo], m)
            vis = np.where(up[todo], dm, -dm)
            acc = rng.random(todo.size) * self._amax < self._area[k] * np.maximum(vis, 0.0)
            out[todo[acc]] = m[acc]
            todo = todo[~acc]
        if todo.size:  # pathological grazing directions: use the mean normal
            out[todo] = np.array([0.0, 0.0, 1.0])
        return out

    def interact(self, d, S, e, inside, n_glass, rng):
        alive = np.ones(len(d), bool)
        pending = np.ones(len(d), bool)
        for _ in range(self.max_hits):
            idx = np.nonzero(pending)[0]
            if idx.size == 0:
                break
            dd = d[idx]
            m = self._pick(dd, rng)
            up = dd[:, 2] > 0
            nf = np.where(up[:, None], -m, m)           # normal facing the incident medium
            ins = inside[idx]
            n1 = np.where(ins, n_glass, 1.0)
            n2 = np.where(ins, 1.0, n_glass)
            dn, Sn, en, refl = interface_event(dd, S[idx], e[idx], nf, n1, n2, rng.random(idx.size))
            ins_new = np.where(refl, ins, ~ins)
            d[idx], S[idx], e[idx], inside[idx] = dn, Sn, en, ins_new
            # done when travelling away from the face on the side of its medium
            done = np.where(ins_new, dn[:, 2] < 0, dn[:, 2] > 0)
            pending[idx[done]] = False
        alive &= ~pending
        return d, S, e, inside, alive


@dataclass
class KirchhoffFace:
    """Scalar Kirchhoff (Beckmann) rough face, event by event, for the wave-optics candidates.

    Each photon arriving at the face is reflected or transmitted at the MEAN plane (Fresnel with
    Stokes, `interface_event` with the normal +-z), which sets the specular direction.  The
    relief's phase variance for that event is g = (a sigma)^2, a = 2 k0 n1 cos(theta1) in
    reflection and k0 |n1 cos(theta1) - n2 cos(theta2)| in transmission (the Debye-Waller
    exponent).  With probability s exp(-g) (s = `coherent_scale`, 1 = Kirchhoff) the photon stays
    specular (the coherent part); otherwise it takes the incoherent part of the Beckmann series
    for a Gaussian-correlated surface (Beckmann & Spizzichino 1963, ch. 5, eq. for a Gaussian
    correlation coefficient exp(-r^2 / T^2)):

        sum over m >= 1 of  exp(-g) g^m / m!  x  Gaussian in the transverse wave-vector change q
        with variance 2 m / T^2 per axis,

    i.e. m ~ Poisson(g) conditioned on m >= 1, then q ~ N(0, 2 m / T^2) per axis.  For g >> 1
    this is the geometric-optics lobe of Gaussian slopes with per-axis variance 2 sigma^2 / T^2;
    T is therefore taken as sqrt(2) sigma / m_axis from the measured rms height and per-axis rms
    slope, so the rough limit has the measured slope width.  A partially coherent source
    (Gaussian Schell model, coherence length l_c; van Cittert-Zernike) adds q ~ N(0, 1 / l_c^2)
    per axis to photons arriving from outside (the source's beam; later events keep the beam's
    coherence, an approximation).  Transverse wave vectors beyond the outgoing medium's k are
    evanescent and redrawn (the propagating orders share the event's Fresnel power); after
    `max_tries` the photon is lost.  The Stokes vector is kept (near-specular scattering) and
    its s-axis re-orthogonalised.

    Assumptions / validity: Gaussian height statistics and correlation, no shadowing, no
    obliquity factor, slopes << 1, lateral scales >~ lambda.  `wavelength_nm` is set per run.
    """

    sigma_m: float
    corr_m: float
    wavelength_nm: float = 550.0
    coherent_scale: float = 1.0
    coherence_length_m: float = 0.0
    max_tries: int = 32

    @staticmethod
    def from_heights(heights_m: np.ndarray, dx_m: float, dy_m: float, **kw) -> "KirchhoffFace":
        h = np.asarray(heights_m, float)
        h = np.nan_to_num(h - np.nanmean(h), nan=0.0)
        gx = (np.roll(h, -1, 1) - h) / dx_m
        gy = (np.roll(h, -1, 0) - h) / dy_m
        sigma = float(np.sqrt(np.mean(h**2)))
        m_axis = float(np.sqrt(0.5 * (np.mean(gx**2) + np.mean(gy**2))))
        return KirchhoffFace(sigma, np.sqrt(2.0) * sigma / max(m_axis, 1e-12), **kw)

    def interact(self, d, S, e, inside, n_glass, rng):
        from scipy.stats import poisson
        n = len(d)
        down = d[:, 2] < 0
        nf = np.zeros((n, 3))
        nf[:, 2] = np.where(down, 1.0, -1.0)                 # mean-plane normal facing the incident medium
        n1 = np.where(inside, n_glass, 1.0)
        n2 = np.where(inside, 1.0, n_glass)
        dn, Sn, en, refl = interface_event(d, S, e, nf, n1, n2, rng.random(n))
        k0 = 2 * np.pi / (self.wavelength_nm * 1e-9)
        c1 = np.abs(d[:, 2])
        a = np.where(refl, 2 * k0 * n1 * c1, k0 * np.abs(n1 * c1 - n2 * np.abs(dn[:, 2])))
        g = (a * self.sigma_m) ** 2
        p0 = np.exp(-g)                                      # Debye-Waller factor of the event
        coh = rng.random(n) < np.clip(self.coherent_scale * p0, 0.0, 1.0)
        m = np.maximum(poisson.ppf(p0 + rng.random(n) * (1 - p0), g), 1.0)    # Poisson(g) given m >= 1
        q_sd = np.where(coh, 0.0, np.sqrt(2 * m) / self.corr_m)
        if self.coherence_length_m > 0:
            q_sd = np.where(inside, q_sd, np.sqrt(q_sd**2 + 1.0 / self.coherence_length_m**2))
        n_out = np.where(refl, n1, n2)
        kt = dn[:, :2] * (n_out * k0)[:, None]
        out = dn.copy()
        todo = np.nonzero(q_sd > 0)[0]
        alive = np.ones(n, bool)
        for _ in range(self.max_tries):
            if todo.size == 0:
                break
            st = (kt[todo] + q_sd[todo, None] * rng.standard_normal((todo.size, 2))) / (n_out[todo] * k0)[:, None]
            s2 = np.sum(st**2, axis=1)
            ok = s2 < 1.0
            j = todo[ok]
            out[j, :2] = st[ok]
            out[j, 2] = np.sign(dn[j, 2]) * np.sqrt(1.0 - s2[ok])
            todo = todo[~ok]
        alive[todo] = False
        en = en - _dot(en, out)[:, None] * out
        en = _normalize(np.where(np.linalg.norm(en, axis=1, keepdims=True) > 1e-9, en, _perp_any(out)))
        inside_new = np.where(refl, inside, ~inside)
        return out, Sn, en, inside_new, alive


def beckmann_normals(alpha: float, n: int, rng: np.random.Generator) -> np.ndarray:
    """Normals of a Beckmann surface: slopes Gaussian with per-axis std alpha / sqrt(2)."""
    sl = rng.normal(0.0, alpha / np.sqrt(2.0), (n, 2))
    return _normalize(np.concatenate([-sl, np.ones((n, 1))], axis=1))


# ------------------------------------------------------------------ the plate


@dataclass
class PlatePhysics:
    """Everything about the plate and source that the photon run needs.

    thickness_mm, n_glass: plate; absorption_per_mm: Beer-Lambert coefficient applied to
    the weights (0 = none; path lengths are recorded anyway so a caller can reweight);
    scatter_per_mm, hg_g: volume scattering; back_alpha: Beckmann roughness of the back
    face (0 = flat); tilt_deg: rotation of the sample about y (plane of incidence);
    beam_sigma_deg: Gaussian divergence of the incident beam (per axis).
    """

    thickness_mm: float = 2.0
    n_glass: float = 1.5
    absorption_per_mm: float = 0.0
    scatter_per_mm: float = 0.0
    hg_g: float = 0.0
    back_alpha: float = 0.0
    tilt_deg: float = 0.0
    beam_sigma_deg: float = 0.0
    max_events: int = 40


@dataclass
class Exits:
    """Photons that left the plate: lab directions, weights, glass path (mm), launches."""

    d: np.ndarray
    w: np.ndarray
    path_mm: np.ndarray
    n_launched: int
    lost: int = 0
    extra: dict = field(default_factory=dict)


def _hg_cos(g: float, u: np.ndarray) -> np.ndarray:
    """Sample cos(theta) of the Henyey-Greenstein phase function (inverse CDF)."""
    if abs(g) < 1e-6:
        return 2 * u - 1
    t = (1 - g * g) / (1 - g + 2 * g * u)
    return np.clip((1 + g * g - t * t) / (2 * g), -1.0, 1.0)


def run_photons(face, phys: PlatePhysics, theta_i_deg: float, phi_i_deg: float, source_stokes,
                n_photons: int, rng: np.random.Generator) -> Exits:
    """Trace `n_photons` photons from the source direction through the plate.

    source_stokes: (S0, S1, S2, S3) with S1 = I_s - I_p relative to the plane of incidence.
    Returns the exits in the lab frame (tilt undone).
    """
    n = int(n_photons)
    R = rot_y(np.radians(phys.tilt_deg))
    wi = direction(theta_i_deg, phi_i_deg)
    d = np.tile(-wi, (n, 1))
    ph = np.radians(phi_i_deg)
    e = np.tile(np.array([-np.sin(ph), np.cos(ph), 0.0]), (n, 1))
    if phys.beam_sigma_deg > 0:
        sig = np.radians(phys.beam_sigma_deg)
        b1 = e
        b2 = np.cross(d, e)
        d = _normalize(d + sig * (rng.normal(size=(n, 1)) * b1 + rng.normal(size=(n, 1)) * b2))
        e = _normalize(e - _dot(e, d)[:, None] * d)
    # into the sample frame
    d = d @ R
    e = e @ R
    S = np.tile(np.asarray(source_stokes, float) / float(source_stokes[0]), (n, 1))
    w = np.ones(n)
    L = np.zeros(n)
    z = np.zeros(n)
    inside = np.zeros(n, bool)
    # state: 0 at front face (from its medium), 1 in bulk, 2 exited, 3 lost
    state = np.zeros(n, np.int8)
    t = float(phys.thickness_mm)
    ng = float(phys.n_glass)
    for _ in range(phys.max_events):
        f = np.nonzero(state == 0)[0]
        if f.size:
            dn, Sn, en, insn, alive = face.interact(d[f], S[f], e[f], inside[f], ng, rng)
            d[f], S[f], e[f], inside[f] = dn, Sn, en, insn
            st = np.where(~alive, 3, np.where(insn, 1, 2))
            state[f] = st
            z[f[st == 1]] = 0.0
        b = np.nonzero(state == 1)[0]
        if b.size == 0 and f.size == 0:
            break
        if b.size:
            db = d[b]
            dist = np.where(db[:, 2] < 0, (z[b] + t) / np.maximum(-db[:, 2], 1e-12),
                            -z[b] / np.maximum(db[:, 2], 1e-12))
            if phys.scatter_per_mm > 0:
                free = rng.exponential(1.0 / phys.scatter_per_mm, b.size)
                scat = free < dist
            else:
                free = dist
                scat = np.zeros(b.size, bool)
            step = np.where(scat, free, dist)
            L[b] += step
            if phys.absorption_per_mm > 0:
                w[b] *= np.exp(-phys.absorption_per_mm * step)
            z[b] += step * db[:, 2]
            if scat.any():
                s = b[scat]
                ds = d[s]
                ct = _hg_cos(phys.hg_g, rng.random(s.size))
                st_ = np.sqrt(np.maximum(0.0, 1 - ct * ct))
                psi = 2 * np.pi * rng.random(s.size)
                u1 = _perp_any(ds)
                u2 = np.cross(ds, u1)
                dnew = _normalize(ct[:, None] * ds + st_[:, None] * (np.cos(psi)[:, None] * u1 + np.sin(psi)[:, None] * u2))
                d[s] = dnew
                e[s] = _normalize(e[s] - _dot(e[s], dnew)[:, None] * dnew)
            # boundary hits
            hit = b[~scat]
            if hit.size:
                up = d[hit, 2] > 0
                top = hit[up]
                state[top] = 0                      # back at the rough front face, from inside
                bot = hit[~up]
                if bot.size:
                    if phys.back_alpha > 0:
                        m = beckmann_normals(phys.back_alpha, bot.size, rng)
                    else:
                        m = np.tile(np.array([0.0, 0.0, 1.0]), (bot.size, 1))
                    # only facets facing the photon (d . m < 0); flip the rest (symmetric)
                    m = np.where((_dot(d[bot], m) > 0)[:, None], m * np.array([-1.0, -1.0, 1.0]), m)
                    dn, Sn, en, refl = interface_event(d[bot], S[bot], e[bot], m, ng, 1.0, rng.random(bot.size))
                    # a path that ends up on the wrong side of a rough back face stays in the glass
                    refl = refl | (~refl & (dn[:, 2] > 0))
                    dn[:, 2] = np.where(refl, np.abs(dn[:, 2]), -np.abs(dn[:, 2]))
                    d[bot], S[bot], e[bot] = dn, Sn, en
                    z[bot[refl]] = -t
                    state[bot[~refl]] = 2
                    inside[bot[~refl]] = False
    lost = int(np.sum((state == 3) | (state == 0) | (state == 1)))
    ex = state == 2
    dl = d[ex] @ R.T
    return Exits(d=dl, w=w[ex], path_mm=L[ex], n_launched=n, lost=lost)


# ------------------------------------------------------------------ detection


def detect(exits: Exits, side, theta_s_deg, phi_s_deg, half_angle_deg: float,
           weights: np.ndarray | None = None, blur_sigma_deg: float = 0.0):
    """BSDF (1/sr) and its Monte-Carlo 1-sigma at each row direction.

    Uniform cone of half-angle a (solid angle 2 pi (1 - cos a)); with a blur sigma > 0 the
    cone is replaced by a 2-D Gaussian of variance a^2/4 + sigma^2 per axis (the cone's
    own second moment plus the blur).  f = sum(w in kernel) / (N Omega cos theta_s).
    """
    side = np.asarray(side)
    th = np.asarray(theta_s_deg, float)
    ph = np.asarray(phi_s_deg, float)
    w = exits.w if weights is None else weights
    d = exits.d
    a = np.radians(half_angle_deg)
    s2 = a * a / 4 + np.radians(blur_sigma_deg) ** 2
    reach = a if blur_sigma_deg <= 0 else 3.5 * np.sqrt(s2)
    out = np.zeros(th.size)
    var = np.zeros(th.size)
    # pre-sort photons by polar angle from +z / -z for a window search
    for sd, sgn in (("R", 1.0), ("T", -1.0)):
        rows = np.nonzero(side == sd)[0]
        if rows.size == 0:
            continue
        sel = (d[:, 2] * sgn) > 0
        dd = d[sel] * np.array([1.0, 1.0, sgn])
        ww = w[sel]
        tp = np.arccos(np.clip(dd[:, 2], -1, 1))
        order = np.argsort(tp)
        tp, dd, ww = tp[order], dd[order], ww[order]
        for r in rows:
            t0 = np.radians(th[r])
            lo, hi = np.searchsorted(tp, [t0 - reach, t0 + reach])
            if hi <= lo:
                continue
            v = direction(th[r], ph[r])
            c = dd[lo:hi] @ v
            psi = np.arccos(np.clip(c, -1, 1))
            if blur_sigma_deg <= 0:
                k = (psi <= a) / (2 * np.pi * (1 - np.cos(a)))
            else:
                k = np.exp(-psi * psi / (2 * s2)) / (2 * np.pi * s2)
            cos_s = max(np.cos(t0), 1e-3)
            contrib = ww[lo:hi] * k
            out[r] = contrib.sum() / (exits.n_launched * cos_s)
            var[r] = (contrib * contrib).sum() / (exits.n_launched * cos_s) ** 2
    return out, np.sqrt(var)
