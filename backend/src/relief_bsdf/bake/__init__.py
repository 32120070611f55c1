"""Bake a `BsdfTable` into lookup rows for a renderer's microfacet closures (bpy-free).

The Blender layer (relief_addon/bake_nodes.py) turns the rows into a packed float32 image
and a shader node group of four Cycles closures per view side:

    Glossy(roughness 0)        x w_specR(theta_v)      the table's specular (delta) reflection
    Metallic(GGX, r_R(theta_v), dielectric Fresnel of index n (front) or 1/n (back))
                               x w_diffR(theta_v)      its diffuse reflection cells
    Refraction(roughness 0)    x w_specT(theta_v)      specular (undeviated) transmission
    Refraction(GGX, r_T)       x w_diffT(theta_v)      diffuse transmission cells

Indexing by the *view* angle.  A shading node only knows the direction toward the viewer
(theta_v), not the light's.  Helmholtz reciprocity, f_R(i -> v) = f_R(v -> i), makes the
reflection lobe seen from v the table's lobe for incidence theta_i = theta_v; its cosine
integral is the directional reflectance R(theta_v).  For transmission the renderer's closure
carries the light across the boundary toward v; with Cycles' convention (a smooth refraction
closure transmits radiance unchanged) the lobe seen from v is again the table's lobe for
incidence from v's side, T(theta_v).  Only the view angle is known, so a weight cannot follow
the Fresnel factor F(i . h), which depends on the light direction and changes fast toward
grazing; the diffuse reflection lobe therefore uses a closure with the microfacet Fresnel of
the dielectric built in (Cycles' Metallic BSDF, physical-conductor Fresnel with extinction 0,
i.e. Walter et al. 2007 eq. 20 with GGX D and Smith G) and a view-indexed weight near 1; with
`reflection_closure="glossy"` (Blender < 4.3 has no Metallic BSDF) a Fresnel-free Glossy lobe
is weighted instead, exact in energy but off in shape where F varies across the lobe.  Note
also that Cycles does not scale radiance by n^2 across a refraction (a smooth refraction
closure passes radiance unchanged), i.e. it renders "basic radiance" L / n^2: a camera inside
the medium sees f_phys * n_i^2 / n_s^2.  The per-side tables ("outside", "inside") fill the
front-facing and back-facing rows.

Frame.  Every row is read in the shading point's own frame: theta_v from the shading normal, the
"outside" rows where the ray meets the face's front (the side its normal points to), the "inside"
rows where it meets its back.  So one baked material serves every face of any mesh whose normals
point out of the medium (a plate's rough face, a sphere, a lens), each face's normal standing for
the relief's z; the relief's x (an anisotropic lobe's tangent) is the object's x axis projected on
the face, undefined only where a face looks along x.  The add-on gives the material to every face of
a mesh, or to the rough face of a plate it made (relief_addon.bake_nodes.assign_to_rough_face).

Weights: w = table integral / A(closure, roughness, theta_v), where A is the closure's own
directional albedo *in the renderer* (Cycles compensates multiple scattering with internal
tables, so A is measured, see relief_addon/cycles_calibration.py; `ClosureAlbedo`).  Hence
the rendered directional R and T equal the table's by construction, up to the lookup
interpolation.  Roughness: one GGX lobe per side and incidence fitted to the table's diffuse
cells (`methods.microfacet.fit_table`, energy-weighted least squares); Cycles roughness is
sqrt(alpha).

Spectral tables: the RGB channels carry the weights at three wavelengths (default 610, 550,
465 nm, interpolated linearly between tabulated wavelengths and held outside them);
roughness and IOR are scalar in Cycles and use the green wavelength.

Anisotropy: the reflection lobe's aspect ratio alpha_x / alpha_y is read from the table's
own lobe at normal incidence (`reflection_slope_ratio`) and baked as Cycles' Anisotropy
with the tangent along the relief's x axis (`closure_anisotropy`, `_lobe_roughness`).  Cycles 5.0
has no anisotropic rough transmission: its Refraction and Glass BSDFs have no anisotropy input, the
Principled BSDF's Anisotropic and Tangent reach its specular layer only, and the closure setups
behind every transmission, SVM and OSL alike (bsdf_microfacet_ggx_refraction_setup / _glass_setup
in kernel/closure/bsdf_microfacet.h), set alpha_y = alpha_x, so even an OSL
`microfacet(..., alpha_x, alpha_y, eta, 1)` renders isotropic (measured by
tests/blender/test_bake_nodes.py::test_cycles_transmission_closures_are_isotropic and
::test_osl_microfacet_refraction_is_isotropic_too).  The transmitted lobe of an anisotropic table
is therefore built from an isotropic Refraction closure of the lobe's narrow width whose normal is
tilted, per shading point, by a random facet slope along the wide axis (`transmission_tilt`; the
node group draws it from a White Noise texture), so that the path tracer's average over samples is
the stretched lobe; the signed tilt scale per view angle is the `transmission_tilt` row.  The
closure albedo calibration is the isotropic one at the narrow roughness (the tilt changes the
rendered directional T by under 1 %, measured).

Assumptions and limits: other tables are taken as isotropic (several incidence azimuths are
averaged); lobe shapes are GGX (Walter et al. 2007, eqs. 20-21, 33) so tables of another
shape match in energy exactly and in shape approximately; a missing "inside" table is
replaced by a smooth interface seen from inside (Fresnel, total internal reflection),
an approximation stated in `info`; a closure albedo below `albedo_floor` is clamped there so
weights stay finite (grazing back-facing views past the critical angle).
"""
from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field
from typing import Callable, Sequence

import numpy as np

from relief_bsdf.bsdf.table import BsdfTable
from relief_bsdf.errors import InputError
from relief_bsdf.core.fresnel import fresnel_unpolarized
from relief_bsdf.core.index import Material

ROW_NAMES = ("specular_R", "diffuse_R", "specular_T", "diffuse_T", "roughness", "transmission_tilt")
ROWS_PER_SIDE = len(ROW_NAMES)
SIDES = ("outside", "inside")          # row block 0: front-facing view, 1: back-facing view
DEFAULT_RGB_NM = (610.0, 550.0, 465.0)

#: what the bake does with the transmitted lobes (module doc: Cycles has no anisotropic transmission)
TRANSMISSION_NOTE = ("Cycles has no anisotropic rough transmission: an anisotropic table's transmitted lobe "
                     "is an isotropic Refraction closure of the narrow width, its normal tilted per shading "
                     "point by a random facet slope along the wide axis (transmission_tilt row)")

Albedo = Callable[[str, np.ndarray, np.ndarray, float], np.ndarray]


def unit_albedo(kind: str, roughness: np.ndarray, theta_deg: np.ndarray, ior: float) -> np.ndarray:
    """Ideal closures when no renderer calibration is given: albedo 1, or for "metallic" the
    smooth-interface Fresnel reflectance (Born & Wolf 1.5.2), its albedo in the smooth limit."""
    shape = np.broadcast(roughness, theta_deg).shape
    if kind == "metallic":
        cos_i = np.cos(np.radians(np.broadcast_to(np.asarray(theta_deg, float), shape)))
        return fresnel_unpolarized(cos_i, 1.0, ior)
    return np.ones(shape)


@dataclass
class ClosureAlbedo:
    """Measured directional albedo A(kind, roughness, theta_v, ior) of a renderer's closures.

    kind: "glossy", "refraction_front" (view from the side the normal points to) or
    "refraction_back".  Multilinear interpolation on the measured grid (held at its ends).
    """

    theta_deg: np.ndarray
    roughness: np.ndarray
    ior: np.ndarray
    glossy: np.ndarray                 # (R, Th)
    refraction_front: np.ndarray       # (N, R, Th)
    refraction_back: np.ndarray        # (N, R, Th)
    ior_metallic: np.ndarray | None = None
    metallic: np.ndarray | None = None  # (Nm, R, Th)
    source: str = ""

    @staticmethod
    def load(path) -> "ClosureAlbedo":
        d = np.load(path)
        return ClosureAlbedo(d["theta_deg"], d["roughness"], d["ior"], d["glossy"], d["refraction_front"],
                             d["refraction_back"], d["ior_metallic"] if "metallic" in d else None,
                             d["metallic"] if "metallic" in d else None,
                             f"{path} (Blender {d['blender_version']})")

    def __call__(self, kind: str, roughness, theta_deg, ior: float) -> np.ndarray:
        from scipy.interpolate import RegularGridInterpolator
        r, t = np.broadcast_arrays(np.asarray(roughness, float), np.asarray(theta_deg, float))
        r = np.clip(r, self.roughness[0], self.roughness[-1])
        t = np.clip(t, self.theta_deg[0], self.theta_deg[-1])
        if kind == "glossy":
            f = RegularGridInterpolator((self.roughness, self.theta_deg), self.glossy)
            return f(np.stack([r, t], -1))
        if kind == "metallic":
            if self.metallic is None:
                raise InputError(self.source or "closure albedo", "no Metallic BSDF calibration in this file")
            grid, arr = self.ior_metallic, self.metallic
        else:
            grid = self.ior
            arr = {"refraction_front": self.refraction_front, "refraction_back": self.refraction_back}[kind]
        f = RegularGridInterpolator((grid, self.roughness, self.theta_deg), arr)
        n = np.full(r.shape, np.clip(ior, grid[0], grid[-1]))
        return f(np.stack([n, r, t], -1))


@dataclass
class BakedLut:
    """Lookup rows of one baked BSDF (see module doc).

    rows: (2 * ROWS_PER_SIDE, C, 4) float32; row block s (0 front/outside, 1 back/inside)
    holds ROW_NAMES in order; colour rows are (R, G, B, 1) weights, the roughness row is
    (r_R, r_T, anisotropy_R, 1) in Cycles' roughness (sqrt of GGX alpha) and Cycles'
    anisotropy of the reflection lobe (`closure_anisotropy`: tangent along the relief's x
    axis, turned 90 degrees where negative; 0: isotropic); the transmission_tilt row is
    (c_T, 0, 0, 1), the signed scale of the random facet slope that stretches the transmitted
    lobe (`transmission_tilt`; along the relief's x axis, along y where negative; 0: the
    transmitted lobe is isotropic and r_T its mean roughness).  Columns sample theta_v
    uniformly from 0 to 90 degrees.
    """

    name: str
    theta_deg: np.ndarray
    rows: np.ndarray
    ior: float                                   # n_inside / n_outside at the green wavelength
    rgb_nm: tuple
    ior_rgb: tuple = (1.5, 1.5, 1.5)             # n_inside / n_outside at the three wavelengths
    reflection_closure: str = "metallic"
    info: dict = field(default_factory=dict)

    @property
    def n_rows(self) -> int:
        return self.rows.shape[0]

    def row_index(self, side: str, row: str) -> int:
        return SIDES.index(side) * ROWS_PER_SIDE + ROW_NAMES.index(row)

    def image_pixels(self) -> np.ndarray:
        """Flat float32 RGBA pixels of a (C x n_rows) image, image row 0 = LUT row 0 (bottom)."""
        return np.ascontiguousarray(self.rows, dtype=np.float32).ravel()

    def lookup(self, side: str, row: str, theta_deg) -> np.ndarray:
        """Reference lookup (linear between columns, held at the ends): (..., 4)."""
        k = self.row_index(side, row)
        t = np.asarray(theta_deg, float)
        return np.stack([np.interp(t, self.theta_deg, self.rows[k, :, c]) for c in range(4)], axis=-1)

    def texture_u(self, theta_deg) -> np.ndarray:
        """Texel-centred horizontal coordinate of theta_v (what the node group computes)."""
        c = self.theta_deg.size
        x = np.asarray(theta_deg, float) / 90.0
        return x * (c - 1) / c + 0.5 / c

    @property
    def anisotropy(self) -> float:
        """Largest |anisotropy| of the reflection lobe (0 for an isotropic bake)."""
        k = self.row_index("outside", "roughness")
        return float(np.max(np.abs(self.rows[k, :, 2])))

    @property
    def transmission_tilt(self) -> float:
        """Largest |c_T| of the transmitted lobe's random facet tilt (0: isotropic transmission)."""
        k = [self.row_index(side, "transmission_tilt") for side in SIDES]
        return float(np.max(np.abs(self.rows[k, :, 0])))

    @property
    def haze(self) -> float:
        """Haze of the baked table (ASTM D1003 on the plate, `bsdf.haze.haze_astm_d1003`); NaN if unknown."""
        return float(self.info.get("haze_T", float("nan")))

    def texture_v(self, row_index: int) -> float:
        return (row_index + 0.5) / self.n_rows


def _per_incidence(table: BsdfTable) -> dict[str, np.ndarray]:
    """Hemispherical integrals (W, I), averaged over incidence azimuths (isotropy)."""
    h = table.hemispherical()
    return {k: np.asarray(h[k], float).mean(axis=2) for k in ("specular_R", "diffuse_R", "specular_T", "diffuse_T")}


def _fit_roughness(table: BsdfTable, wl_nm: float, subsamples: int | None = None) -> np.ndarray:
    """(I, P, 2) Cycles roughness of one GGX lobe per incidence, incidence azimuth and side (R, T).

    The model lobe is averaged over each cell like the table (`subsamples` per cell axis;
    default 1 for cells of at most 1 x 5 degrees, else 2: coarse cells need the average, or a
    narrow transmitted lobe at grazing incidence is fitted a few per cent too rough).
    """
    from relief_bsdf.methods.microfacet import fit_table
    if subsamples is None:
        fine = np.max(np.diff(table.theta_s_edges_deg)) <= 1.01 and np.max(np.diff(table.phi_s_edges_deg)) <= 5.01
        subsamples = 1 if fine else 2
    t = table.select(wl_nm)
    h = t.hemispherical()
    # a lobe carrying under 1e-12 of the light (a nearly flat face) is no lobe: its cells are
    # zeroed so that the fit skips it instead of dividing by an underflowed norm
    power = (t.values_per_sr * t.projected_solid_angle_sr).sum(axis=(-2, -1))
    if np.any((power > 0) & (power < 1e-12)):
        t = dataclasses.replace(t, values_per_sr=np.where((power < 1e-12)[..., None, None], 0.0, t.values_per_sr))
    fit = fit_table(t, n_lobes=1, distribution="ggx", subsamples=subsamples)
    r = np.sqrt(np.clip(fit.alpha[0, :, :, :, 0], 0.0, None))      # (I, P, 2)
    for k, key in enumerate(("diffuse_R", "diffuse_T")):
        r[np.asarray(h[key], float)[0] <= 0, k] = 0.0
    return np.clip(r, 0.0, 1.0)


def closure_anisotropy(rho: float, closure: str) -> float:
    """Cycles' Anisotropy for a GGX lobe with alpha_x / alpha_y = rho (x = the tangent), signed:
    a negative value means "use |value| with the tangent turned by 90 degrees" (the node group
    adds 0.25 to Rotation), because both closures below only stretch one way.

    Cycles 5.0 (node_metallic_bsdf.osl, node_glossy_bsdf.osl; the roughness r gives
    alpha = r^2 and alpha_x alpha_y = alpha^2 in both, so the baked r stays the geometric mean):
    - "metallic": aspect = sqrt(1 - 0.9 a), alpha_x = alpha / aspect, alpha_y = alpha aspect,
      a in [0, 1]: rho = 1 / (1 - 0.9 a), so a = (1 - 1 / rho) / 0.9 (rho >= 1, at most 10);
    - "glossy": alpha_x = alpha (1 - a), alpha_y = alpha / (1 - a) for a > 0: rho = (1 - a)^2,
      so a = 1 - sqrt(rho) (rho <= 1), held below 0.99 as Cycles clamps it.
    """
    if not np.isfinite(rho) or rho <= 0:
        return 0.0
    along = rho >= 1.0 if closure == "metallic" else rho <= 1.0       # stretch along the tangent
    q = rho if along else 1.0 / rho                                     # the ratio the closure makes
    a = (1.0 - 1.0 / q) / 0.9 if closure == "metallic" else 1.0 - np.sqrt(q)
    a = float(np.clip(a, 0.0, 1.0 if closure == "metallic" else 0.99))
    return a if along else -a


def _weighted_median(x: np.ndarray, w: np.ndarray) -> float:
    order = np.argsort(x)
    cw = np.cumsum(w[order])
    return float(x[order][np.searchsorted(cw, 0.5 * cw[-1])])


def reflection_slope_ratio(table: BsdfTable, wl_nm: float) -> float:
    """alpha_x / alpha_y of the reflection lobe at normal incidence; NaN if the table cannot say.

    At normal incidence each reflected direction w_o belongs to one facet slope, that of the
    half vector h = (z + w_o) / |z + w_o|: (s_x, s_y) = -(h_x, h_y) / h_z.  The power of each R
    cell (f x projected solid angle) is the share of light reflected by facets of that slope, and
    for a lobe whose slope density is elliptical, P(s_x / alpha_x, s_y / alpha_y), the ratio of
    the power-weighted medians of |s_x| and |s_y| is alpha_x / alpha_y whatever the shape of P
    (the Fresnel and shadowing factors depend on the tilt, which is the same for both axes at
    normal incidence; anisotropic masking is neglected).  Needs an incidence within 1 deg of the
    normal and the lobe resolved by more than one azimuth cell; azimuth phi_s = 0 is +x.
    """
    ti = np.asarray(table.theta_i_deg, float)
    i = int(np.argmin(np.abs(ti)))
    if abs(ti[i]) > 1.0 or len(table.phi_s_edges_deg) < 5:
        return float("nan")
    from relief_bsdf.core.frames import direction
    w = int(np.argmin(np.abs(np.asarray(table.wavelength_nm, float) - wl_nm)))
    p = int(np.argmin(np.abs((np.asarray(table.phi_i_deg, float) + 180.0) % 360.0 - 180.0)))
    te, pe = np.asarray(table.theta_s_edges_deg, float), np.asarray(table.phi_s_edges_deg, float)
    th, ph = np.meshgrid(0.5 * (te[:-1] + te[1:]), 0.5 * (pe[:-1] + pe[1:]), indexing="ij")
    h = direction(th, ph) + np.array([0.0, 0.0, 1.0])
    sx, sy = np.abs(h[..., 0] / h[..., 2]).ravel(), np.abs(h[..., 1] / h[..., 2]).ravel()
    power = (np.asarray(table.values_per_sr[w, i, p, 0], float) * table.projected_solid_angle_sr).ravel()
    if not np.any(power > 0):
        return float("nan")
    my, mx = _weighted_median(sy, power), _weighted_median(sx, power)
    return mx / my if my > 0 and mx > 0 else float("nan")


def _lobe_roughness(table: BsdfTable, wl_nm: float, closure: str) -> tuple[np.ndarray, np.ndarray]:
    """(I, 2) roughness per incidence and side, and (I,) signed anisotropy of the reflection lobe.

    Roughness: one isotropic GGX lobe fitted per incidence and side, azimuths averaged; for an
    anisotropic lobe this is close to the geometric mean of the two axes' roughnesses, which is
    what Cycles' (roughness, anisotropy) pair keeps.  Anisotropy: from the table's own
    reflection lobe at normal incidence (`reflection_slope_ratio`, rho = alpha_x / alpha_y,
    tangent along x) in the convention of the closure (`closure_anisotropy`), the same for every
    incidence.  A table without a normal incidence bakes isotropic.  Transmission: an
    isotropic closure plus a random facet tilt (`transmission_tilt`, module doc).
    """
    rough = _fit_roughness(table, wl_nm).mean(axis=1)
    a = closure_anisotropy(reflection_slope_ratio(table, wl_nm), closure)
    return rough, np.full(rough.shape[0], a)


#: below this aspect ratio of the lobe (alpha_wide / alpha_narrow) the transmission bakes isotropic
MIN_TILT_ASPECT = 1.1


def _ggx_x_slopes(alpha_x: float, u: np.ndarray, v: np.ndarray) -> np.ndarray:
    """x slopes of GGX facets (Walter et al. 2007 eq. 33, stretched to alpha_x along x as in Heitz
    2014 sec. 5.3; alpha_y does not enter the x marginal) from uniform (u, v): the radial CDF of
    the unit slope density 1 / (pi (1 + r^2)^2) is r^2 / (1 + r^2) = u, so r = sqrt(u / (1 - u))."""
    return alpha_x * np.sqrt(u / (1.0 - u)) * np.cos(2.0 * np.pi * v)


def tilt_slope(u: np.ndarray, scale: float) -> np.ndarray:
    """Random slope of scale `scale` from uniform u: the inverse CDF of the one-axis marginal of the
    GGX slope density, p(s) = 1 / (2 c) (1 + s^2 / c^2)^(-3/2) (a Student t with 2 degrees of
    freedom scaled by c / sqrt(2)): s = c (2u - 1) / (2 sqrt(u (1 - u))).  The node group evaluates
    the same formula with u from a White Noise texture (one facet per shading point)."""
    u = np.clip(u, 1e-9, 1.0 - 1e-9)
    return scale * (2.0 * u - 1.0) / (2.0 * np.sqrt(u * (1.0 - u)))


def tilt_scale_ratio(aspect: float, samples: int = 200_000, seed: int = 0) -> float:
    """c / alpha_narrow: the tilt scale that stretches an isotropic GGX lobe of alpha_narrow to the
    width of GGX(alpha_wide = aspect * alpha_narrow) along the tilt.

    The rendered transmission is the isotropic Refraction closure averaged over one random facet
    tilt s per shading point (`tilt_slope`), i.e. facet slopes s_iso + s along the tilt: the
    distribution of the sum is matched to the anisotropic GGX marginal by its median |slope|
    (robust where the heavy tails make the variance infinite).  Across the tilt the lobe keeps
    alpha_narrow.  Deterministic (seeded Monte Carlo; both medians scale with alpha_narrow)."""
    if not np.isfinite(aspect) or aspect < MIN_TILT_ASPECT:
        return 0.0
    rng = np.random.default_rng(seed)
    u, v, w = rng.random((3, samples))
    target = np.median(np.abs(_ggx_x_slopes(aspect, u, v)))
    base = _ggx_x_slopes(1.0, u, v)
    t = tilt_slope(w, 1.0)
    lo, hi = 0.0, aspect
    for _ in range(40):                                   # median |base + c t| grows with c
        mid = 0.5 * (lo + hi)
        lo, hi = (mid, hi) if np.median(np.abs(base + mid * t)) < target else (lo, mid)
    return 0.5 * (lo + hi)


def transmission_tilt(rough_T: np.ndarray, rho: float) -> tuple[np.ndarray, np.ndarray]:
    """(roughness of the isotropic Refraction closure, signed tilt scale c_T) per incidence.

    Cycles has no anisotropic rough transmission (module doc).  The transmitted lobe of facets
    with slope widths alpha_x = alpha sqrt(rho), alpha_y = alpha / sqrt(rho) (alpha = rough_T^2,
    the fitted mean; rho = alpha_x / alpha_y of the same facets, `reflection_slope_ratio`) is
    rendered as the isotropic closure of the narrow width, its normal tilted per shading point by
    a random slope of scale c_T along the wide axis (`tilt_scale_ratio`); c_T > 0: along the
    relief's x axis, < 0: along y.  An aspect below `MIN_TILT_ASPECT` (or unknown) keeps the
    isotropic closure of the mean roughness and c_T = 0.  Assumptions: the tilt is not weighted
    by the facet's projected area (normal-map semantics; a second-order change of the energy for
    slopes below ~0.3, checked by the goniophotometer's directional T) and the random slope adds
    to the closure's own as independent facets."""
    rough_T = np.asarray(rough_T, float)
    aspect = max(rho, 1.0 / rho) if np.isfinite(rho) and rho > 0 else float("nan")
    ratio = tilt_scale_ratio(aspect)
    if ratio == 0.0:
        return rough_T, np.zeros_like(rough_T)
    narrow = rough_T ** 2 / np.sqrt(aspect)
    return np.sqrt(narrow), np.sign(np.log(rho)) * ratio * narrow


def _interp_wl(values: np.ndarray, wl_axis: np.ndarray, targets: Sequence[float]) -> np.ndarray:
    """(W, ...) -> (3, ...) linear in wavelength, held outside the tabulated range."""
    if wl_axis.size == 1:
        return np.repeat(values[:1], len(targets), axis=0)
    out = []
    for t in targets:
        k = int(np.clip(np.searchsorted(wl_axis, t) - 1, 0, wl_axis.size - 2))
        f = float(np.clip((t - wl_axis[k]) / (wl_axis[k + 1] - wl_axis[k]), 0.0, 1.0))
        out.append((1 - f) * values[k] + f * values[k + 1])
    return np.stack(out)


@dataclass(frozen=True)
class _BakeColours:
    """What every side of the bake shares: the RGB wavelengths, relative indices and closure albedo."""

    rgb_nm: tuple
    green_nm: float
    ior: float                   # relative index inside / outside at the green wavelength
    ior_rgb: tuple               # the same per RGB wavelength
    albedo: Albedo
    floor: float                 # smallest closure albedo divided by
    reflection_closure: str


def _side_rows(table: BsdfTable, cols: np.ndarray, bc: _BakeColours, back: bool) -> tuple[np.ndarray, dict]:
    rgb_nm, green_nm, ior, albedo = bc.rgb_nm, bc.green_nm, bc.ior, bc.albedo
    floor, reflection_closure, ior_rgb = bc.floor, bc.reflection_closure, bc.ior_rgb
    integ = _per_incidence(table)
    ti = table.theta_i_deg
    rough, aniso = _lobe_roughness(table, green_nm, reflection_closure)   # (I, 2), (I,)
    r_T_closure, tilt = transmission_tilt(rough[:, 1], reflection_slope_ratio(table, green_nm))
    r_R = np.interp(cols, ti, rough[:, 0])
    r_T = np.interp(cols, ti, r_T_closure)
    rows = np.zeros((ROWS_PER_SIDE, cols.size, 4))
    rows[..., 3] = 1.0
    kinds = {"specular_R": ("glossy", np.zeros_like(cols)), "diffuse_R": (reflection_closure, r_R),
             "specular_T": ("refraction_back" if back else "refraction_front", np.zeros_like(cols)),
             "diffuse_T": ("refraction_back" if back else "refraction_front", r_T)}
    clamped = 0
    for j, name in enumerate(ROW_NAMES[:4]):
        per_wl = integ[name]                                         # (W, I)
        rgb = _interp_wl(per_wl, table.wavelength_nm, rgb_nm)        # (3, I)
        kind, r = kinds[name]
        for c in range(3):
            n_c = ior if kind != "metallic" else (1.0 / ior_rgb[c] if back else ior_rgb[c])
            a = np.asarray(albedo(kind, r, cols, n_c), float)
            clamped += int(np.sum(a < floor))
            rows[j, :, c] = np.interp(cols, ti, rgb[c]) / np.maximum(a, floor)
    rows[4, :, 0] = r_R
    rows[4, :, 1] = r_T
    rows[4, :, 2] = np.interp(cols, ti, aniso)
    rows[5, :, 0] = np.interp(cols, ti, tilt)
    return rows, {"roughness_R_at_table": rough[:, 0].tolist(), "roughness_T_at_table": rough[:, 1].tolist(),
                  "anisotropy_R": float(aniso.mean()), "transmission_tilt": tilt.tolist(),
                  "albedo_clamped_columns": clamped}


def _smooth_inside_rows(material: Material, cols: np.ndarray, rgb_nm, green_nm: float, albedo: Albedo,
                        ior: float, floor: float) -> np.ndarray:
    """Rows for a smooth interface seen from inside (used when no inside table exists)."""
    rows = np.zeros((ROWS_PER_SIDE, cols.size, 4))
    rows[..., 3] = 1.0
    cos_i = np.cos(np.radians(cols))
    for c, wl in enumerate(rgb_nm):
        n_out, n_in = material.n_pair(float(wl), "outside")
        F = fresnel_unpolarized(cos_i, np.real(n_in), np.real(n_out))
        rows[0, :, c] = F / np.maximum(albedo("glossy", np.zeros_like(cols), cols, ior), floor)
        rows[2, :, c] = (1 - F) / np.maximum(albedo("refraction_back", np.zeros_like(cols), cols, ior), floor)
    return rows


def transmission_haze(table: BsdfTable, wl_nm: float = 550.0) -> float:
    """The table's haze as ASTM D1003 defines it on the plate (`bsdf.haze.haze_astm_d1003`, the one
    definition shown everywhere), at the wavelength nearest `wl_nm`."""
    from relief_bsdf.bsdf.haze import haze_astm_d1003
    return haze_astm_d1003(table, wavelength_nm=wl_nm)


def bake_lut(tables: Sequence[BsdfTable], name: str, albedo: Albedo | None = None, n_columns: int = 91,
             rgb_nm: Sequence[float] = DEFAULT_RGB_NM, albedo_floor: float = 0.02,
             reflection_closure: str = "metallic") -> BakedLut:
    """Lookup rows for the node group of `tables` (one per side of incidence; "outside" required).

    reflection_closure: "metallic" (Fresnel-weighted GGX lobe, Blender 4.3+) or "glossy".
    """
    if reflection_closure not in ("metallic", "glossy"):
        raise InputError("reflection_closure", f"must be metallic or glossy, got {reflection_closure!r}")
    albedo = albedo or unit_albedo
    by_side = {t.incident_from: t for t in tables}
    if "outside" not in by_side:
        raise InputError("table", "the bake needs the table for light arriving from outside "
                         "(reconstruct with --from outside or both)")
    out = by_side["outside"]
    if not out.material:
        raise InputError("table", "the table records no material; the bake needs the refractive index")
    if n_columns < 2:
        raise InputError("n_columns", f"need at least 2 lookup columns, got {n_columns}")
    mat = Material.from_dict(out.material)
    rgb = tuple(float(w) for w in rgb_nm)
    green = rgb[1]
    n_out, n_in = mat.n_pair(green, "outside")
    ior = float(np.real(n_in) / np.real(n_out))
    ior_rgb = tuple(float(np.real(mat.n_pair(w, "outside")[1]) / np.real(mat.n_pair(w, "outside")[0])) for w in rgb)
    cols = np.linspace(0.0, 90.0, n_columns)
    bc = _BakeColours(rgb_nm=rgb, green_nm=green, ior=ior, ior_rgb=ior_rgb, albedo=albedo, floor=albedo_floor,
                      reflection_closure=reflection_closure)
    front, info_f = _side_rows(out, cols, bc, back=False)
    info = {"outside": info_f, "method": out.method, "closure_albedo": getattr(albedo, "source", "ideal (1)"),
            "haze_T": transmission_haze(out, green), "transmission": TRANSMISSION_NOTE}
    if "inside" in by_side:
        back, info_b = _side_rows(by_side["inside"], cols, bc, back=True)
        info["inside"] = info_b
    else:
        back = _smooth_inside_rows(mat, cols, rgb, green, albedo, ior, albedo_floor)
        info["inside"] = "no inside table: smooth interface seen from inside (Fresnel, total internal reflection)"
    rows = np.concatenate([front, back]).astype(np.float32)
    return BakedLut(name=name, theta_deg=cols, rows=rows, ior=ior, rgb_nm=rgb, ior_rgb=ior_rgb,
                    reflection_closure=reflection_closure, info=info)
