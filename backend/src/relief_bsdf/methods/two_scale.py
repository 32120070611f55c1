"""`two_scale`: ray tracing of the large scale combined with first-order (Rayleigh-Rice) scatter of the fine scale.

For reliefs rough at one scale and smooth at another - a lobe plus a haze, the anti-glare film of
the paper (Zhdanov et al. 2018, sec. 2.3 and fig. 6: ray tracing of the measured relief cannot
separate the specular part, because fine roughness "which really does not produce the light
scattering, or the light scattering is much narrower than the ray solution produces" becomes
facets) - the composite ("two-scale") model of Bass & Fuks (*Wave Scattering from Statistically
Rough Surfaces*, 1979, ch. 5), Valenzuela (Boundary-Layer Meteorol. 13 (1978) 61) and Brown (IEEE
Trans. Antennas Propag. 26 (1978) 472):

Split (surface.bands).  h = h_L + h_F at the cut-off |f| = f_c: h_L the relief low-passed to
|f| <= f_c, h_F the rest.  f_c is the LOWEST frequency at which the fine scale is optically smooth,
g_F = (4 pi n sigma_F / lambda)^2 <= fine_rayleigh (option, default 0.05: half of rayleigh-rice's
limit 0.1, so its neglected second order stays ~ 2.5 %), sigma_F the fine scale's rms inside the
propagating band, n the largest incident index, lambda the shortest wavelength (option f_cut_per_um
sets the cut instead).  Lowest, because the large scale is treated by geometric optics, which
needs every component it keeps rough on the wavelength scale; first-order perturbation treats the
fine scale correctly at any lateral scale while g_F is small.  Where geometric optics holds for
h_L (facets >> lambda: k R_c >= 10, l >= 10 lambda / n, no coherent part) is checked by `auto`
(its conditions for two_scale), which also says why.

Large scale: the `ray` method on h_L (inter-reflections, shadowing, Fresnel; its sigma: Monte
Carlo and the tile's realisation).  Fine scale, on every large-scale facet:
- its coherent part carries the large-scale scatter: every ray cell is multiplied by the fine
  scale's Debye-Waller factor exp(-(sigma_F nu_z)^2) with the cell's own wave-vector transfer
  nu_z = k0 (n1 cos t_i + n1 cos t_s) (R) or k0 (n1 cos t_i - n2 cos t_s) (T), averaged over the
  cell's sub-points (symmetric in the two directions, so reciprocity is kept; at the specular
  direction it is the Rayleigh-Rice specular factor); the ray's delta parts (flat facets) get the
  factor of the specular direction;
- its diffuse part is its haze: the Rayleigh-Rice BSDF of the fine scale's PSD (rayleigh_rice:
  the periodogram of h_F, annulus-averaged when isotropic) on the mean plane, spread over the large
  scale's facet orientations (option tilt_convolution): a facet tilted by t shifts the local
  specular direction by 2 t (R) or t |n2 - n1| / n2 (T) in direction cosines of the exit medium,
  i.e. the Bragg frequency of the pair of directions by 2 n1 t / lambda or |n2 - n1| t / lambda;
  the fine scale's PSD is therefore convolved with a Gaussian of that width in relief frequencies
  (`tilted_psd`, t the large scale's rms slope per axis, `tilt_width_dcos`) and the Rayleigh-Rice
  BSDF evaluated with it at the true directions (its polarisation factor Q at the mean plane).
  Convolving the PSD argument rather than the scattered direction keeps reciprocity exactly (the
  argument is symmetric in the two directions, the kernel the same for a reciprocal pair), which
  convolving each incidence's haze in the exit direction would break near the critical angle,
  where Q varies fast.  Cell averages over sub-points as the rayleigh-rice method.
Energy: to first order in g_F what the Debye-Waller factors take out of the lobe is the haze
(R + T = 1 of the ray tables, up to the first-order bookkeeping of Rayleigh-Rice); the defect
1 - R - T is stored signed in `lost` and metadata["energy_defect"] (wave_filter.energy_defect),
with a warning above 1 %.  tests/backend/methods/test_two_scale.py checks it, the flat limit,
reciprocity and the agreement with full Kirchhoff (methods.kirchhoff) on a two-scale relief
whose large scale is gentle enough for the tangent plane.

Regime of validity: the large scale as `ray` (rough on the wavelength scale, facets >> lambda, no
coherent specular part left in h_L); the fine scale as `rayleigh-rice` (g_F small, rms slope <
0.15); the fine scale's haze is computed on the mean plane and only spread by the facet
orientations (valid for moderate large-scale slopes, < ~0.3); no coupling of the fine-scale haze
with the large scale's shadowing or inter-reflections.

Uncertainty (sigma_per_sr): the ray cells' sigma times the Debye-Waller factor, combined in
quadrature with the haze's periodogram realisation uncertainty (rayleigh_rice.cell_sigma; for the
tilted PSD that of a periodogram smoothed by the combined width: an upper estimate when the fine
PSD is annulus-averaged).
Tables are unpolarised (no Mueller matrices).

Options (methods.options.TwoScaleOptions): f_cut_per_um, fine_rayleigh, tilt_convolution, and the
ray options max_bounces, threads, tile_uncertainty, backend.
"""
from __future__ import annotations

import dataclasses
from dataclasses import dataclass

import numpy as np

from relief_bsdf.bsdf.table import BsdfTable
from relief_bsdf.core.index import Material
from relief_bsdf.methods.options import TwoScaleOptions
from relief_bsdf.methods.rayleigh_rice import RoughInterface, cell_sigma, estimate_psd, rr_bsdf
from relief_bsdf.methods.realisation import cell_extents_dcos
from relief_bsdf.methods.wave_filter import cell_samples, check_sides, energy_defect, smoothing_width_dcos
from relief_bsdf.surface.bands import BandSpectrum, BandSplit, band_split, two_scale_cut
from relief_bsdf.surface.stats import propagating_f_max, rms_slope


def _band_of_request(material: Material, request) -> tuple[float, float, float]:
    """(shortest wavelength m, largest incident index, propagating f_max 1/m) of the request."""
    lam = min(request.wavelengths_nm) * 1e-9
    pairs = [material.n_pair(wl, fr) for wl in request.wavelengths_nm for fr in request.incident_from]
    n = max(float(np.real(p[0])) for p in pairs)
    n_any = max(float(np.real(v)) for p in pairs for v in p if np.imag(v) == 0)
    return lam, n, propagating_f_max(lam * 1e9, n, n_any, max(request.theta_i_deg))


def split_for(relief, material: Material, request, f_cut_per_um: float | None = None,
              fine_rayleigh: float = 0.05, spectrum: BandSpectrum | None = None) -> BandSplit:
    """The relief's split for this request (module doc: the lowest cut with g_F <= fine_rayleigh)."""
    lam, n, f_prop = _band_of_request(material, request)
    spectrum = spectrum if spectrum is not None else BandSpectrum.of(relief)
    if f_cut_per_um is not None:
        f_c = float(f_cut_per_um) * 1e6
    else:
        f_c = two_scale_cut(spectrum, lam, n, f_prop, fine_rayleigh)
    return band_split(relief, f_c, f_prop, spectrum)


def figures(relief, material: Material, request, opts: TwoScaleOptions) -> dict:
    """The numbers `auto` judges two_scale on: the split, the fine scale's Rayleigh parameter, rms slope (inside
    the propagating band) and correlation length, and the large scale's geometric-optics figures (rms height,
    correlation length, k R_c from second differences, coherent specular share at normal incidence)."""
    from relief_bsdf.surface.stats import levelled, relief_stats
    lam, n, f_prop = _band_of_request(material, request)
    spec = BandSpectrum.of(relief)
    sp = split_for(relief, material, request, opts.f_cut_per_um, opts.fine_rayleigh, spec)
    with np.errstate(invalid="ignore", divide="ignore"):
        st_l, st_f = relief_stats(sp.large), relief_stats(sp.fine)
    kappa = float(spec.large_curvature(sp.f_cut_per_m))
    lv = levelled(sp.large)
    z = lv.heights_m[lv.valid]
    k0 = 2 * np.pi / lam
    pairs = [material.n_pair(wl, fr) for wl in request.wavelengths_nm for fr in request.incident_from]
    nus = [2 * float(np.real(p[0])) * k0 for p in pairs] + [abs(float(np.real(p[0] - p[1]))) * k0 for p in pairs
                                                           if np.imag(p[1]) == 0]
    coh = max(float(abs(np.mean(np.exp(-1j * nu * z))) ** 2) for nu in nus) if z.size else 1.0
    lam_n = lam / n
    return {"f_cut_per_m": sp.f_cut_per_m, "fine_rms_m": sp.fine_rms_prop_m,
            "fine_rayleigh": (4 * np.pi * sp.fine_rms_prop_m / lam_n) ** 2,
            "fine_rms_slope": spec.fine_slope(sp.f_cut_per_m, f_prop),
            "fine_correlation_length_m": st_f.correlation_length_m, "large_rms_m": sp.large_rms_m,
            "large_correlation_length_m": st_l.correlation_length_m,
            "large_k_rc": 2 * np.pi * (1.0 / kappa if kappa > 0 else np.inf) / lam_n, "large_coherent": coh}


def _fine_psd(split: BandSplit, smoothing_df: float):
    """The fine scale's smoothed PSD (rayleigh_rice.estimate_psd of h_F), zero at |f| <= f_c."""
    psd = estimate_psd(split.fine, smoothing_df=smoothing_df)
    if psd.isotropic:
        s = np.where(psd.radial_f <= split.f_cut_per_m, 0.0, psd.radial_s)
        return dataclasses.replace(psd, radial_s=s, sigma_m=split.fine_rms_prop_m)
    ny, nx = psd.grid.shape
    fx = psd.f0[0] + psd.dfxy[0] * np.arange(nx)
    fy = psd.f0[1] + psd.dfxy[1] * np.arange(ny)
    g = np.where(np.hypot(fx[None, :], fy[:, None]) <= split.f_cut_per_m, 0.0, psd.grid)
    return dataclasses.replace(psd, grid=g, sigma_m=split.fine_rms_prop_m)


def _nu_z(side: str, k0: float, n1: float, n2: float, cos_i: float, cos_s):
    """Wave-vector transfer normal to the mean plane (module doc), R or T."""
    return k0 * (n1 * cos_i + n1 * cos_s) if side == "R" else k0 * (n1 * cos_i - n2 * cos_s)


@dataclass(frozen=True)
class _Haze:
    """What every incidence's haze shares: the cell sub-points, the cell filter width, the cells' edges and
    extents, whether to tilt, the large scale's rms slope per axis."""

    cells: object
    cell_width: float
    theta_edges: tuple
    phi_edges: tuple
    extents: tuple
    tilt: bool
    slope_axis: float             # the large scale's rms slope per axis (the facet orientations)


def tilt_width_dcos(side: str, n1: float, n2: float, slope_axis: float) -> float:
    """The spread (standard deviation per axis, direction cosines of the exit medium) of the local specular
    directions of facets with rms slope slope_axis per axis, to first order in the slope: 2 s for R, and
    s |n2 - n1| / n2 for T (Snell's law at a tilted facet).  In relief frequencies (x n_exit / lambda) both
    are 2 n1 s / lambda and |n2 - n1| s / lambda: the same for the two directions of a reciprocal pair."""
    return 2.0 * slope_axis if side == "R" else slope_axis * abs(n2 - n1) / n2


def tilted_psd(psd, kernel_per_m: float):
    """The fine scale's PSD convolved with a 2-D Gaussian of standard deviation kernel_per_m (1/m): the Bragg
    frequency of every pair of directions shifted by the facet orientations (module doc).  Returned as a grid
    PSD (rayleigh_rice.Psd, anisotropic form); its realisation statistics are those of a periodogram smoothed
    by the combined width (an upper estimate for an annulus-averaged one)."""
    from scipy import ndimage
    if kernel_per_m <= 0:
        return psd
    if psd.isotropic:
        df = psd.df
        m = int(np.ceil(psd.radial_f[-1] / df)) + 1
        f = df * np.arange(-m, m + 1)
        grid, f0, dfxy = psd.at(f[None, :], f[:, None]), (float(f[0]), float(f[0])), (df, df)
    else:
        grid, f0, dfxy = psd.grid, psd.f0, psd.dfxy
    sm = ndimage.gaussian_filter(grid, (kernel_per_m / dfxy[1], kernel_per_m / dfxy[0]), mode="constant",
                                 truncate=4.0)
    return dataclasses.replace(psd, isotropic=False, grid=sm, f0=f0, dfxy=dfxy,
                               smoothing_df=float(np.hypot(psd.smoothing_df if not psd.isotropic else psd.df,
                                                           kernel_per_m)),
                               description=psd.description + f"; convolved with the facet tilts "
                                                             f"({kernel_per_m:.4g} 1/m)")


def _haze_cells(surface: RoughInterface, side: str, ti: float, pi_: float, hz: _Haze):
    """(S, A) cell values of the fine scale's haze (Rayleigh-Rice of surface.psd, already tilted) and their
    realisation sigma (rayleigh_rice.cell_sigma)."""
    m00 = rr_bsdf(ti, pi_, hz.cells.theta, hz.cells.phi, side, surface)
    return m00.mean(axis=-1), cell_sigma(m00, ti, pi_, hz.cells, side, surface, hz.extents)


def _combine_row(ray_tab: BsdfTable, idx: tuple, n1, n2, wl_nm: float, psds: "_TiltedPsds", hz: _Haze) -> dict:
    """One incidence (idx = (iw, it, ip)) of one table: lobe x Debye-Waller + haze, both sides."""
    iw, it, ip = idx
    ti, pi_ = np.radians(ray_tab.theta_i_deg[it]), np.radians(ray_tab.phi_i_deg[ip])
    k0 = 2 * np.pi / (wl_nm * 1e-9)
    r1, r2 = float(np.real(n1)), float(np.real(n2))
    sf = psds.base.sigma_m
    te, pe = np.radians(hz.theta_edges), np.radians(hz.phi_edges)
    psa = 0.5 * (np.sin(te[1:]) ** 2 - np.sin(te[:-1]) ** 2)[:, None] * np.diff(pe)[None, :]
    out = {"info": {}}
    for k, side in enumerate(("R", "T")):
        lobe = np.asarray(ray_tab.values_per_sr[iw, it, ip, k], float)
        lobe_sig = np.asarray(ray_tab.sigma_per_sr[iw, it, ip, k], float) if ray_tab.sigma_per_sr is not None \
            else np.zeros_like(lobe)
        spec = float((ray_tab.specular_R if side == "R" else ray_tab.specular_T)[iw, it, ip])
        ns = r1 if side == "R" else r2
        if side == "T" and np.imag(n2) > 0:
            out[side] = (np.zeros_like(lobe), np.zeros_like(lobe), 0.0)
            continue
        dw = np.exp(-(sf * _nu_z(side, k0, r1, r2, np.cos(ti), np.cos(hz.cells.theta))) ** 2).mean(axis=-1)
        st = np.sqrt(max(1.0 - (r1 / ns * np.sin(ti)) ** 2, 0.0))
        dw_spec = float(np.exp(-(sf * _nu_z(side, k0, r1, r2, np.cos(ti), st)) ** 2)) if st > 0 else 0.0
        spread = tilt_width_dcos(side, r1, r2, hz.slope_axis) if hz.tilt else 0.0
        surface = RoughInterface(n1, n2, wl_nm * 1e-9, psds[(wl_nm, side, round(spread * ns, 12))])
        haze, haze_sig = _haze_cells(surface, side, ti, pi_, hz) if sf > 0 else (0.0 * lobe, 0.0 * lobe)
        out[side] = (dw * lobe + haze, np.hypot(dw * lobe_sig, haze_sig), dw_spec * spec)
        out["info"][f"haze_{side}"] = float((haze * psa).sum())
        out["info"][f"debye_waller_specular_{side}"] = dw_spec
        out["info"][f"tilt_width_dcos_{side}"] = spread
    return out


def reconstruct(relief, material: Material, request, progress=None) -> list[BsdfTable]:
    """Two-scale tables, one per side of incidence in request.incident_from (module doc)."""
    from relief_bsdf.methods.ray import reconstruct as ray_reconstruct
    request.validate()
    check_sides(material, request, "two_scale")
    opts = TwoScaleOptions.from_request(request)
    split = split_for(relief, material, request, opts.f_cut_per_um, opts.fine_rayleigh)
    ray_opts = {"polarized": False, "max_bounces": opts.max_bounces, "threads": opts.threads,
                "tile_uncertainty": opts.tile_uncertainty, "backend": opts.backend}
    ray_tabs = ray_reconstruct(split.large, material, dataclasses.replace(request, options=ray_opts), progress)
    w = smoothing_width_dcos(0.0, request.theta_s_edges_deg)
    wls = np.asarray(request.wavelengths_nm, float)
    psd = _fine_psd(split, w / (wls.min() * 1e-9))
    hz = _Haze(cells=cell_samples(request.theta_s_edges_deg, request.phi_s_edges_deg, w, max_per_axis=6),
               cell_width=w, theta_edges=tuple(request.theta_s_edges_deg), phi_edges=tuple(request.phi_s_edges_deg),
               extents=cell_extents_dcos(request.theta_s_edges_deg, request.phi_s_edges_deg),
               tilt=opts.tilt_convolution, slope_axis=rms_slope(split.large) / np.sqrt(2.0))
    return [_table(rt, material, request, split, psd, hz, relief) for rt in ray_tabs]


class _TiltedPsds(dict):
    """(wavelength_nm, side, tilt width x n_exit) -> the tilted PSD, made once (the kernel in relief frequencies
    is tilt width x n_exit / lambda)."""

    def __init__(self, base):
        super().__init__()
        self.base = base

    def __missing__(self, key):
        wl_nm, _, width_n = key
        self[key] = tilted_psd(self.base, width_n / (wl_nm * 1e-9))
        return self[key]


def _table(rt: BsdfTable, material: Material, request, split: BandSplit, psd, hz: _Haze, relief) -> BsdfTable:
    """The composite table of one side of incidence from its ray table (module doc)."""
    psds = _TiltedPsds(psd)
    W, I, P = rt.values_per_sr.shape[:3]
    vals = np.zeros(rt.values_per_sr.shape)
    sig = np.zeros(rt.values_per_sr.shape)
    sR, sT = np.zeros((W, I, P)), np.zeros((W, I, P))
    infos = []
    for iw in range(W):
        n1, n2 = material.n_pair(rt.wavelength_nm[iw], rt.incident_from)
        for it in range(I):
            for ip in range(P):
                r = _combine_row(rt, (iw, it, ip), n1, n2, float(rt.wavelength_nm[iw]), psds, hz)
                for k, side in enumerate(("R", "T")):
                    vals[iw, it, ip, k], sig[iw, it, ip, k], spec = r[side]
                    (sR if side == "R" else sT)[iw, it, ip] = spec
                infos.append({"wavelength_nm": float(rt.wavelength_nm[iw]), "theta_i_deg": float(rt.theta_i_deg[it]),
                              "phi_i_deg": float(rt.phi_i_deg[ip]), **r["info"]})
    meta = {"split": {"f_cut_per_m": split.f_cut_per_m, "fine_rms_m": split.fine_rms_m,
                      "fine_rms_propagating_m": split.fine_rms_prop_m, "large_rms_m": split.large_rms_m,
                      "statement": split.statement()},
            "fine_psd": psd.description, "incidences": infos,
            "tilt_kernels_per_m": sorted({float(k[2] / (k[0] * 1e-9)) for k in psds}),
            "large_scale": {"method": "ray", "uncertainty": rt.metadata.get("uncertainty"),
                            "warnings": rt.metadata.get("warnings", [])},
            "uncertainty": {"sigma": "ray cells' sigma (Monte Carlo and tile realisation) x Debye-Waller, and the "
                                     "fine-scale haze's periodogram realisation uncertainty, in quadrature"},
            "warnings": list(rt.metadata.get("warnings", [])),
            "validity": "large scale: geometric optics (ray); fine scale: first-order perturbation with g_F <= "
                        "fine_rayleigh; haze on the mean plane spread by the facet orientations"}
    tab = BsdfTable(wavelength_nm=rt.wavelength_nm, theta_i_deg=rt.theta_i_deg, phi_i_deg=rt.phi_i_deg,
                    theta_s_edges_deg=np.asarray(request.theta_s_edges_deg, float),
                    phi_s_edges_deg=np.asarray(request.phi_s_edges_deg, float), values_per_sr=vals,
                    sigma_per_sr=sig, incident_from=rt.incident_from, specular_R=sR, specular_T=sT,
                    method="two_scale", material=material.describe(), relief=relief.describe(), metadata=meta)
    energy_defect(tab, material, "two_scale", "two-scale composite")
    return tab
