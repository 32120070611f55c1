"""The validation's own photon engine: transport through a solid plate with a rough face, Stokes tracked.

This engine is the physics of `relief conceal` (validation/conceal.py) and is deliberately
independent of the forward model it checks (plate/, methods/, diagnose/): its own transport
loop, its own faces and its own detector.  It shares only the physics core (`core.fresnel`
amplitudes and refraction, `core.stokes` frame rotation and interface Mueller product,
`core.frames` directions and the sample tilt `rot_y`, `core.bulk` Beer-Lambert and
Henyey-Greenstein sampling, `core.microfacet` Beckmann slope sampling), which every part of
the project uses.  The rough-face interaction is an object with one method

    face.interact(d, S, e, inside, n_glass, rng) -> (d, S, e, inside, alive)

which moves a batch of photons that arrive at the rough face (propagation directions `d`,
Stokes vectors `S` in the frame whose s-axis is `e`, medium flag `inside` = in the glass)
until each has left the face region: going up in air (reflected side) or down in the
glass.  Implementations:

- `NormalsFace` (here): random bump mapping over the *measured facet normals* of the relief
  (paper sec. 2.2, "density of normals"): each hit picks one facet with probability
  proportional to its projected visible area; no shadowing, no lateral correlation (the
  simple facet face of the validation's own checks);
- `conceal.HeightFieldFace`: exact ray tracing through the triangulated height field
  (`surface.mesh.build_tile_mesh`, Embree), with shadowing and interreflection (paper sec. 2.3);
- `phase_screen.PhaseScreenFace`: the scalar Kirchhoff thin phase screen of the real relief.

Plate (geometric optics, lateral extent infinite, so lateral offsets do not matter for
a BSDF): front face at z = 0 (the relief, thin compared to the thickness t), back face at
z = -t, flat or a Beckmann microfacet surface (roughness alpha, Walter et al. 2007 eq. 25
slope distribution).  Bulk: Beer-Lambert absorption exp(-a L) along each path in the
glass (weights), optional volume scattering with free paths ~ Exp(mu_s) and a
Henyey-Greenstein phase function (Henyey & Greenstein 1941; polarisation carried over
unchanged, a scalar approximation of the volume phase matrix).  Every interface event is a
Fresnel Mueller matrix in the local s/p basis (Born & Wolf 1.5.20-21) with the Stokes frame
rotated onto the local plane of incidence (Chandrasekhar rotation, `core.stokes`), and the
reflect/transmit choice drawn with the probability (M S)_0 / S_0, so the photon keeps
S_0 = 1 and its weight changes only by absorption.

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

from relief_bsdf.core.bulk import beer_lambert, sample_hg_cos, scatter_directions
from relief_bsdf.core.frames import direction, dot, normalize, rot_y
from relief_bsdf.core.fresnel import cos_transmitted, fresnel_amplitudes, refract
from relief_bsdf.core.microfacet import sample_normals
from relief_bsdf.core.stokes import apply_interface_mueller, rotate_stokes

__all__ = ["Exits", "NormalsFace", "PlatePhysics", "detect", "direction", "interface_event",
           "run_photons"]


# ------------------------------------------------------------------ one interface event


def _apply_mueller(a, b, S, scale):
    """M S for the interface Mueller matrix with amplitudes a (s) and b (p) (core.fresnel's
    `mueller_interface` form, applied by `core.stokes.apply_interface_mueller`; the Born & Wolf
    1.5.27 power factor in `scale`)."""
    A = np.abs(a) ** 2
    B = np.abs(b) ** 2
    C = a * np.conj(b)
    scale = np.asarray(scale, float)
    return apply_interface_mueller(S, 0.5 * (A + B) * scale, 0.5 * (A - B) * scale, np.real(C) * scale,
                                   np.imag(C) * scale)


def interface_event(d, S, e, nf, n1, n2, u):
    """Fresnel reflection or refraction of photons with Stokes tracking.

    d: (n,3) propagation directions; nf: (n,3) facet normals facing the incident medium
    (d . nf < 0); n1, n2: indices (scalars or (n,)) of the incident and other medium;
    S: (n,4) Stokes vectors with S0 = 1 in the frame whose s-axis is e (n,3);
    u: (n,) uniform numbers.  Returns (d_new, S_new, e_new, reflected).
    """
    wi = -d
    cos_i = np.clip(dot(wi, nf), 1e-9, 1.0)
    s_vec = np.cross(d, nf)
    ns = np.linalg.norm(s_vec, axis=1)
    degenerate = ns < 1e-9
    s_vec = np.where(degenerate[:, None], e, s_vec / np.where(degenerate, 1.0, ns)[:, None])
    # re-express the Stokes vector from frame e in the plane-of-incidence frame s_vec (core.stokes)
    Sr = rotate_stokes(S, d, e, s_vec)
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
    d_ref = d - 2.0 * dot(d, nf)[:, None] * nf
    d_new = np.where(refl[:, None], d_ref, wt)
    Snew = np.where(refl[:, None], SR, ST)
    Snew = Snew / np.maximum(Snew[:, :1], 1e-300)
    return normalize(d_new), Snew, s_vec, refl


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
        self.normals = normalize(m)
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
        return NormalsFace(normalize(n))

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
            dm = dot(d[todo], m)
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


def beckmann_normals(alpha: float, n: int, rng: np.random.Generator) -> np.ndarray:
    """Normals of a Beckmann surface (slopes Gaussian, per-axis std alpha / sqrt(2)): `core.microfacet`."""
    return sample_normals(alpha, n, rng, "beckmann")


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


_hg_cos = sample_hg_cos     # transition name (tests of the diagnosis); the sampler is core.bulk's


@dataclass
class _Photons:
    """State of a photon batch in the sample frame: direction d, Stokes S in the frame of s-axis e,
    weight w, glass path L (mm), height z (mm, front face 0, back face -t), medium flag, and
    `state` 0 at the front face (from its medium), 1 in the bulk, 2 exited, 3 lost."""

    d: np.ndarray
    e: np.ndarray
    S: np.ndarray
    w: np.ndarray
    L: np.ndarray
    z: np.ndarray
    inside: np.ndarray
    state: np.ndarray


def _launch(phys: PlatePhysics, theta_i_deg: float, phi_i_deg: float, source_stokes, n: int,
            rng: np.random.Generator, R: np.ndarray) -> _Photons:
    """Photons of the source beam (Gaussian divergence per axis), rotated into the sample frame."""
    d = np.tile(-direction(theta_i_deg, phi_i_deg), (n, 1))
    ph = np.radians(phi_i_deg)
    e = np.tile(np.array([-np.sin(ph), np.cos(ph), 0.0]), (n, 1))
    if phys.beam_sigma_deg > 0:
        sig = np.radians(phys.beam_sigma_deg)
        b2 = np.cross(d, e)
        d = normalize(d + sig * (rng.normal(size=(n, 1)) * e + rng.normal(size=(n, 1)) * b2))
        e = normalize(e - dot(e, d)[:, None] * d)
    S = np.tile(np.asarray(source_stokes, float) / float(source_stokes[0]), (n, 1))
    return _Photons(d=d @ R, e=e @ R, S=S, w=np.ones(n), L=np.zeros(n), z=np.zeros(n),
                    inside=np.zeros(n, bool), state=np.zeros(n, np.int8))


def _front_face(face, p: _Photons, f: np.ndarray, n_glass: float, rng: np.random.Generator) -> None:
    """The rough face moves the photons `f` arriving at it until they leave it (or are lost)."""
    dn, Sn, en, insn, alive = face.interact(p.d[f], p.S[f], p.e[f], p.inside[f], n_glass, rng)
    p.d[f], p.S[f], p.e[f], p.inside[f] = dn, Sn, en, insn
    st = np.where(~alive, 3, np.where(insn, 1, 2))
    p.state[f] = st
    p.z[f[st == 1]] = 0.0


def _bulk(p: _Photons, b: np.ndarray, phys: PlatePhysics, rng: np.random.Generator) -> np.ndarray:
    """Free flight of the photons `b` in the glass: Beer-Lambert weight exp(-a L) on each step
    (core.bulk's law), a volume-scattering event after an Exp(mu_s) free path (Henyey-Greenstein
    direction, `core.bulk.scatter_directions`; Stokes vector kept, s-axis re-orthogonalised).
    Returns the photons that reached a face instead."""
    db = p.d[b]
    t = float(phys.thickness_mm)
    dist = np.where(db[:, 2] < 0, (p.z[b] + t) / np.maximum(-db[:, 2], 1e-12),
                    -p.z[b] / np.maximum(db[:, 2], 1e-12))
    if phys.scatter_per_mm > 0:
        free = rng.exponential(1.0 / phys.scatter_per_mm, b.size)
        scat = free < dist
    else:
        free = dist
        scat = np.zeros(b.size, bool)
    step = np.where(scat, free, dist)
    p.L[b] += step
    if phys.absorption_per_mm > 0:
        p.w[b] *= beer_lambert(phys.absorption_per_mm, step)
    p.z[b] += step * db[:, 2]
    if scat.any():
        s = b[scat]
        dnew = normalize(scatter_directions(p.d[s], phys.hg_g, rng))
        p.d[s] = dnew
        p.e[s] = normalize(p.e[s] - dot(p.e[s], dnew)[:, None] * dnew)
    return b[~scat]


def _back_face(p: _Photons, bot: np.ndarray, phys: PlatePhysics, rng: np.random.Generator) -> None:
    """Photons `bot` at the back face (z = -t, from the glass): flat, or Beckmann facets of
    roughness `back_alpha` (core.microfacet slope sampling); Fresnel event, exit or back up."""
    if phys.back_alpha > 0:
        m = beckmann_normals(phys.back_alpha, bot.size, rng)
    else:
        m = np.tile(np.array([0.0, 0.0, 1.0]), (bot.size, 1))
    # only facets facing the photon (d . m < 0); flip the rest (symmetric)
    m = np.where((dot(p.d[bot], m) > 0)[:, None], m * np.array([-1.0, -1.0, 1.0]), m)
    dn, Sn, en, refl = interface_event(p.d[bot], p.S[bot], p.e[bot], m, float(phys.n_glass), 1.0,
                                       rng.random(bot.size))
    # a path that ends up on the wrong side of a rough back face stays in the glass
    refl = refl | (~refl & (dn[:, 2] > 0))
    dn[:, 2] = np.where(refl, np.abs(dn[:, 2]), -np.abs(dn[:, 2]))
    p.d[bot], p.S[bot], p.e[bot] = dn, Sn, en
    p.z[bot[refl]] = -float(phys.thickness_mm)
    p.state[bot[~refl]] = 2
    p.inside[bot[~refl]] = False


def run_photons(face, phys: PlatePhysics, theta_i_deg: float, phi_i_deg: float, source_stokes,
                n_photons: int, rng: np.random.Generator) -> Exits:
    """Trace `n_photons` photons from the source direction through the plate.

    source_stokes: (S0, S1, S2, S3) with S1 = I_s - I_p relative to the plane of incidence.
    The sample tilt is `core.frames.rot_y(tilt_deg)` (w_sample = w_lab @ R).  Returns the exits
    in the lab frame (tilt undone).
    """
    n = int(n_photons)
    R = rot_y(phys.tilt_deg)
    p = _launch(phys, theta_i_deg, phi_i_deg, source_stokes, n, rng, R)
    for _ in range(phys.max_events):
        f = np.nonzero(p.state == 0)[0]
        if f.size:
            _front_face(face, p, f, float(phys.n_glass), rng)
        b = np.nonzero(p.state == 1)[0]
        if b.size == 0 and f.size == 0:
            break
        if b.size:
            hit = _bulk(p, b, phys, rng)
            if hit.size:
                up = p.d[hit, 2] > 0
                p.state[hit[up]] = 0                 # back at the rough front face, from inside
                bot = hit[~up]
                if bot.size:
                    _back_face(p, bot, phys, rng)
    lost = int(np.sum((p.state == 3) | (p.state == 0) | (p.state == 1)))
    ex = p.state == 2
    return Exits(d=p.d[ex] @ R.T, w=p.w[ex], path_mm=p.L[ex], n_launched=n, lost=lost)


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
