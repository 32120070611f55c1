"""Concealed-effect cases: recordings in which physical effects (none, one or several) are hidden.

Each case is a folder with `relief.x3p`, `recording.csv` and `sample.toml` (nothing in it
reveals the effects: absorption is always "not known", the index is the nominal one, the
instrument is the nominal one) plus `key.json` kept apart (the effects and their true
parameters: `effects` the list, `effect` its first entry, for readers of the one-effect key).

Compound cases (`COMPOUND_CASES`) conceal two effects at once, each done as its own physics in
the same photon run (parameter names are unique across effects, so one `parameters` dict
holds both).  Reliefs (`CaseSpec.relief`): "gaussian" (default), "exponential"
(autocovariance s^2 exp(-r/L), `random_relief(kind="exponential")`), "anisotropic"
(`RandomFieldSpec`, correlation length 2.5 L along 30 deg), "dots" (light-guide-plate caps,
`surface.synth.lgp_dots`) and "measured" (`measured_tile`: the real instrument map
tests/data/topography/ST_x3p-2.x3p, levelled, central crop, heights x 3, mirrored into a
periodic tile).  The physics is an *independent* Monte-Carlo photon simulation:

- the rough face is the real relief, triangulated and ray traced with Embree
  (`HeightFieldFace`: shadowing, masking and interreflection on the relief are all there),
  not the facet-normal sampling that the diagnosis's forward model uses;
- every concealed effect is done as physics inside the photon run: Beer-Lambert weights
  along the glass path, Henyey-Greenstein scattering events, a Beckmann back face, a tilted
  sample frame, a divergent beam, a polarised source, a background added to the detector,
  a rescaled or filtered relief, a Cauchy-dispersive glass (n depends on wavelength);
- noise: Poisson shot noise on the detected counts (gain `counts_per_sr`), a relative gain
  noise per row (`gain_noise`), a noise floor (`floor_sr`), plus the Monte-Carlo's own
  variance; `sigma_sr` is the quadrature sum of those (`record.instrument_noise`, the one noise model,
  which the demo recording uses too).

`interreflection` cases need no extra physics here (the generator always traces the real
relief): they are cases on a *steep* relief (rms slope ~ 1, `STEEP_RELIEF`), where shadowing
and multiple bounces, which the diagnosis's single-scatter baseline leaves out, matter; their
key parameter is interreflection_weight = 1 (pure ray-traced relief).

`diffraction` and `partial_coherence` cases are wave optics: the rough face is the scalar
Kirchhoff thin phase screen of the real relief (`phase_screen.PhaseScreenFace`: the far field
of exp(i k0 dn h(x)) by FFT, Welch-averaged; the coherent specular part is the f = 0 order of
the relief's own phase, not a Debye-Waller formula), the whole plate still run by
`run_photons` (thick plate: faces add incoherently).  `partial_coherence` adds a Gaussian
Schell-model source (a random incident phase field of coherence length l_c, averaged over
realisations).  Key parameters: diffraction {"coherent_scale": 1.0} (the Kirchhoff value),
partial_coherence {"coherence_length_um": l_c}, l_c drawn in 0.8 - 1.5 um, so the coherent
peak's broadening lambda / (2 pi l_c) = 3.3 - 6.3 deg is wider than the detector half-angle
(2.5 deg) while the peak still stands out.  Relief of these cases (`WAVE_RELIEF`): rms
0.12 - 0.16 um, correlation length 2.5 um, pitch 0.5 um, 256 x 256 (a 128 um tile, 50
correlation lengths): rms slope 2 s / l = 0.10 - 0.13 (the thin-screen regime, and a relief
whose ray-optics lobes are the user's natural baseline); at 550 nm the transmitted coherent
fraction exp(-(k0 s (n cos t_t - cos t_i))^2) is 0.21 - 0.63 at the recorded incidences
0 / 30 / 55 deg, while reflection (phase rms 2 k0 s cos t_i = 1.6 - 3.7 rad, coherent
fraction <= 0.08) is mostly diffuse.

Independence: nothing here comes from the forward model the cases check (plate/, methods/,
diagnose/).  Shared with the rest of the project, and only these: the physics core (Fresnel,
Stokes rotation, frames, Beer-Lambert, Henyey-Greenstein and Beckmann sampling, through
validation/photon.py), the ONE random-field generator `surface.synth.random_relief`, the ONE
triangulation `surface.mesh.build_tile_mesh` (traced by this module's own loop), the ONE relief
operation `surface.operations.scale_and_filter` (so `height_scale` / `filter_sigma_um` in a key
mean what the fit's parameters mean), and io/ for the files.

Assumptions: geometric optics except the wave cases above, periodic synthetic relief tile
(Gaussian autocovariance s^2 exp(-r^2 / L^2), formats.md), in-plane goniophotometer scans
(phi_i = 0, phi_s in {0, 180}).
"""
from __future__ import annotations

import json
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from relief_bsdf.core.frames import dot, normalize
from relief_bsdf.io.atomic import write_text_atomic
from relief_bsdf.io.recording import Recording, write_recording, write_sample
from relief_bsdf.parallel import ParallelSettings, map_tasks, task_rng
from relief_bsdf.surface.mesh import build_tile_mesh
from relief_bsdf.surface.operations import scale_and_filter
from relief_bsdf.surface.relief import Relief
from relief_bsdf.surface.synth import random_relief
from relief_bsdf.validation.photon import PlatePhysics, detect, interface_event, run_photons

EFFECTS_CONCEALABLE = ("none", "bulk_absorption", "volume_scattering", "back_face_roughness", "sample_tilt",
                       "instrument_blur", "polarization", "stray_light", "relief_scale", "relief_smoothing",
                       "dispersion", "interreflection", "diffraction", "partial_coherence")
STEEP_RELIEF = {"rms_um": (1.6, 2.2), "corr_um": 2.5}   # interreflection cases: rms slope ~ 0.9 - 1.3
# wave-optics cases (module docstring): transmitted coherent fraction 0.21 - 0.63, reflection mostly diffuse
WAVE_RELIEF = {"rms_um": (0.12, 0.16), "corr_um": 2.5, "pitch_um": 0.5, "relief_n": 256}
WAVE_EFFECTS = ("diffraction", "partial_coherence")
RELIEF_KINDS = ("gaussian", "exponential", "anisotropic", "dots", "measured")
# compound cases: two effects concealed together
COMPOUND_CASES = (("bulk_absorption", "stray_light"), ("sample_tilt", "instrument_blur"),
                  ("relief_scale", "bulk_absorption"), ("polarization", "stray_light"),
                  ("relief_smoothing", "sample_tilt"))
# single-effect and clean cases on non-Gaussian reliefs: (relief kind, effect)
RELIEF_CASES = (("dots", "none"), ("dots", "bulk_absorption"), ("exponential", "none"),
                ("exponential", "sample_tilt"), ("anisotropic", "none"), ("anisotropic", "stray_light"),
                ("measured", "none"), ("measured", "instrument_blur"))
MEASURED_MAP = "ST_x3p-2.x3p"


# ------------------------------------------------------------------ height-field face


class HeightFieldFace:
    """Exact ray tracing through a periodic height field: the project's ONE triangulation
    (`surface.mesh.build_tile_mesh`: two triangles per cell, wrap-around cells included) laid
    out as 3 x 3 periodic copies in one Embree scene, traversed by this class's own loop.

    Photons enter the relief layer at a uniformly random lateral position (an extended
    beam), bounce on the triangles with Fresnel/Stokes events (`interface_event`) until
    they leave the layer (above its highest point in air, or below its lowest in glass);
    after each hit the position is wrapped back into the central tile.  Coordinates are the
    mesh's (units of the x pitch, float32 precision).  Independent of the ray method's tracer
    (methods/ray/): only the mesh is shared.
    """

    def __init__(self, heights_m: np.ndarray, dx_m: float, dy_m: float, max_hits: int = 20):
        from embreex import rtcore_scene as rtcs
        from embreex.mesh_construction import TriangleMesh

        mesh = build_tile_mesh(Relief(np.asarray(heights_m, float), dx_m, dy_m, periodic=True,
                                      source="concealed-case relief"))
        self.Lx, self.Ly = (float(v) for v in mesh.period)
        tri = mesh.vertices.astype(np.float64)[mesh.triangles]            # (T, 3 corners, 3)
        shifts = [(i * self.Lx, j * self.Ly) for j in (-1, 0, 1) for i in (-1, 0, 1)]
        tiles = [tri + np.array([sx, sy, 0.0]) for sx, sy in shifts]
        self.normals = np.tile(normalize(mesh.triangle_normals().astype(np.float64)), (len(shifts), 1))
        self.scene = rtcs.EmbreeScene()
        TriangleMesh(self.scene, np.concatenate(tiles).astype(np.float32))
        self.zmax = mesh.z_max + 1e-3
        self.zmin = mesh.z_min - 1e-3
        self.max_hits = max_hits

    def _wrap(self, p: np.ndarray) -> np.ndarray:
        """Lateral positions folded back into the central tile [-L/2, L/2)."""
        p[:, 0] = np.mod(p[:, 0] + self.Lx / 2, self.Lx) - self.Lx / 2
        p[:, 1] = np.mod(p[:, 1] + self.Ly / 2, self.Ly) - self.Ly / 2
        return p

    def interact(self, d, S, e, inside, n_glass, rng):
        n = len(d)
        o = np.empty((n, 3))
        o[:, 0] = (rng.random(n) - 0.5) * self.Lx
        o[:, 1] = (rng.random(n) - 0.5) * self.Ly
        o[:, 2] = np.where(d[:, 2] < 0, self.zmax, self.zmin)
        alive = np.ones(n, bool)
        active = np.arange(n)
        for _ in range(self.max_hits + 1):
            if active.size == 0:
                break
            r = self.scene.run(o[active].astype(np.float32), d[active].astype(np.float32), output=1)
            miss = r["primID"] < 0
            mi = active[miss]
            # a miss is an exit if the photon travels away on its medium's side, else lost
            good = np.where(inside[mi], d[mi, 2] < 0, d[mi, 2] > 0)
            alive[mi[~good]] = False
            active = active[~miss]
            if active.size:
                o[active] = self._bounce(active, r["tfar"][~miss], r["primID"][~miss], o, (d, S, e, inside),
                                         n_glass, rng)
        alive[active] = False
        return d, S, e, inside, alive

    def _bounce(self, hit, tfar, prim, o, photons, n_glass, rng) -> np.ndarray:
        """Fresnel/Stokes event of the photons `hit` on their triangles (arrays in `photons`
        updated in place); returns their new ray origins, nudged off the surface."""
        d, S, e, inside = photons
        p = o[hit] + tfar.astype(float)[:, None] * d[hit]
        m = self.normals[prim]
        ins = inside[hit]
        nf = np.where(ins[:, None], -m, m)
        bad = dot(d[hit], nf) >= 0                     # grazing numerical cases: flip
        nf[bad] = -nf[bad]
        n1 = np.where(ins, n_glass, 1.0)
        n2 = np.where(ins, 1.0, n_glass)
        dn, Sn, en, refl = interface_event(d[hit], S[hit], e[hit], nf, n1, n2, rng.random(hit.size))
        d[hit], S[hit], e[hit] = dn, Sn, en
        inside[hit] = np.where(refl, ins, ~ins)
        return self._wrap(p) + 2e-4 * dn


# ------------------------------------------------------------------ cases


@dataclass
class CaseSpec:
    """One concealed case: the effects (`effects`; `effect` = the first, or the only one), their true
    parameters, the relief kind (module docstring), geometry and noise."""

    name: str
    effect: str = ""
    parameters: dict = field(default_factory=dict)
    seed: int = 0
    n_glass: float = 1.5
    thickness_mm: float = 2.0
    half_angle_deg: float = 2.5
    theta_i_deg: tuple = (0.0, 30.0, 55.0)
    theta_s_deg: tuple = tuple(float(x) for x in range(0, 90, 5))
    wavelengths_nm: tuple = (550.0,)
    relief_n: int = 96
    pitch_um: float = 1.0
    rms_um: float = 0.4
    corr_um: float = 5.0
    photons: int = 600_000
    counts_per_sr: float = 4.0e5      # detector counts per unit BSDF (shot noise scale)
    gain_noise: float = 0.02
    floor_sr: float = 2e-3
    effects: tuple = ()
    relief: str = "gaussian"

    def __post_init__(self) -> None:
        self.effects = tuple(self.effects) or ((self.effect or "none"),)
        if self.effect and len(self.effects) == 1:
            self.effects = (self.effect,)      # the one-effect form (also `dataclasses.replace(spec, effect=...)`)
        if self.effect and self.effect != self.effects[0]:
            raise ValueError(f"case {self.name}: effect {self.effect!r} is not the first of effects {self.effects}")
        unknown = [e for e in self.effects if e not in EFFECTS_CONCEALABLE]
        if unknown or ("none" in self.effects and len(self.effects) > 1):
            raise ValueError(f"case {self.name}: cannot conceal {self.effects}")
        if self.relief not in RELIEF_KINDS:
            raise ValueError(f"case {self.name}: relief kind {self.relief!r} is not one of {RELIEF_KINDS}")
        self.effect = self.effects[0]


def _draw(effect: str, rng: np.random.Generator) -> dict:
    """True parameters of one concealed effect, drawn from ranges large enough to matter and
    within the effect's plausible physical range."""
    u = rng.random()
    if effect == "bulk_absorption":
        return {"absorption_per_mm": float(0.1 + 0.25 * u)}
    if effect == "volume_scattering":
        return {"scatter_per_mm": float(0.15 + 0.25 * u), "hg_g": float(0.6 + 0.2 * rng.random())}
    if effect == "back_face_roughness":
        return {"back_alpha": float(0.08 + 0.1 * u)}
    if effect == "sample_tilt":
        return {"tilt_deg": float((2.0 + 2.0 * u) * (1 if rng.random() < 0.5 else -1))}
    if effect == "instrument_blur":
        return {"blur_deg": float(2.0 + 1.5 * u)}
    if effect == "polarization":
        return {"polarization_q": float((0.7 + 0.3 * u) * (1 if rng.random() < 0.5 else -1))}
    if effect == "stray_light":
        return {"background_per_sr": float(0.02 + 0.03 * u)}
    if effect == "relief_scale":
        # scaled *up*: a scale-down of a Gaussian relief is degenerate with smoothing in ray optics
        return {"height_scale": float(1.2 + 0.25 * u)}
    if effect == "relief_smoothing":
        return {"filter_sigma_um": float(1.5 + 1.0 * u)}
    if effect == "dispersion":
        return {"cauchy_B_nm2": float(15000 + 10000 * u)}
    if effect == "interreflection":
        return {"interreflection_weight": 1.0}
    if effect == "diffraction":
        return {"coherent_scale": 1.0}
    if effect == "partial_coherence":
        return {"coherence_length_um": float(0.8 + 0.7 * u)}
    return {}


def _single_case(name: str, effect: str, rng: np.random.Generator, seed: int, spectral: bool) -> CaseSpec:
    spec = CaseSpec(name=name, effect=effect, parameters=_draw(effect, rng), seed=seed)
    if effect == "dispersion" or spectral:
        spec.wavelengths_nm = (450.0, 550.0, 650.0)
        spec.theta_i_deg = (0.0, 45.0)
    if effect == "interreflection":
        lo, hi = STEEP_RELIEF["rms_um"]
        spec.rms_um = float(lo + (hi - lo) * rng.random())
        spec.corr_um = STEEP_RELIEF["corr_um"]
    if effect in WAVE_EFFECTS:
        lo, hi = WAVE_RELIEF["rms_um"]
        spec.rms_um = float(lo + (hi - lo) * rng.random())
        spec.corr_um = WAVE_RELIEF["corr_um"]
        spec.pitch_um = WAVE_RELIEF["pitch_um"]
        spec.relief_n = WAVE_RELIEF["relief_n"]
    return spec


def default_cases(n_per_effect: int = 2, n_none: int = 4, seed: int = 1, n_compound: int = 1,
                  relief_cases: bool = True) -> list[CaseSpec]:
    """A seeded list of cases: `n_per_effect` per concealed effect and `n_none` clean ones (Gaussian
    reliefs), then `n_compound` per pair of `COMPOUND_CASES`, then (`relief_cases`) the single-effect
    and clean cases of `RELIEF_CASES` on non-Gaussian reliefs.  Parameter values are drawn per case
    (seeded, `_draw`); the compound and relief cases draw from their own streams, so adding them
    leaves the single-effect cases of a seed as they were."""
    rng = task_rng(seed, 99)
    cases = []
    k = 0
    for effect in EFFECTS_CONCEALABLE:
        reps = n_none if effect == "none" else n_per_effect
        for j in range(reps):
            k += 1
            cases.append(_single_case(f"case{k:02d}", effect, rng, seed * 1000 + k,
                                      effect == "none" and j == reps - 1))
    rng2 = task_rng(seed, 98)
    for pair in COMPOUND_CASES:
        for _ in range(n_compound):
            k += 1
            params = {}
            for e in pair:
                params.update(_draw(e, rng2))
            cases.append(CaseSpec(name=f"case{k:02d}", effects=pair, parameters=params, seed=seed * 1000 + k))
    rng3 = task_rng(seed, 97)
    for kind, effect in (RELIEF_CASES if relief_cases else ()):
        k += 1
        if kind == "measured" and not (_topography_dir() / MEASURED_MAP).is_file():
            import warnings
            warnings.warn(f"conceal: {_topography_dir() / MEASURED_MAP} not found: the measured-map case "
                          f"case{k:02d} is left out", RuntimeWarning, stacklevel=2)
            continue
        spec = _single_case(f"case{k:02d}", effect, rng3, seed * 1000 + k, False)
        spec.relief = kind
        cases.append(spec)
    return cases


def _topography_dir() -> Path:
    """tests/data/topography of the repository: the real instrument maps, kept with their source and
    licence (SOURCE.md there); absent from an installed package, where the measured case is left out."""
    return Path(__file__).resolve().parents[4] / "tests" / "data" / "topography"


def measured_tile(crop_n: int = 96, height_scale: float = 3.0, name: str = MEASURED_MAP) -> Relief:
    """A periodic tile of a real instrument map: `name` read by `io.heightmaps.read_relief`, plane-levelled,
    its central crop_n x crop_n crop (mean removed), heights x `height_scale` (ST_x3p-2's rms slope 0.06
    becomes 0.18, rough on the wavelength scale so that the ray-optics generator is the right physics),
    then mirrored into a 2 crop_n square tile: [[c, c flipped in x], [c flipped in y, c flipped in both]]
    (even extension: heights continuous across every tile edge, so the periodic tile adds no step; slope
    magnitudes are kept, their signs mirror).  The map's own anisotropic pitch is kept."""
    from relief_bsdf.errors import InputError
    from relief_bsdf.io.heightmaps import read_relief
    path = _topography_dir() / name
    if not path.is_file():
        raise InputError(str(path), "measured map for the concealed case not found")
    r = read_relief(path).level()
    ny, nx = r.shape
    if min(ny, nx) < crop_n:
        raise InputError(str(path), f"map {ny} x {nx} is smaller than the {crop_n} px crop")
    c = r.heights_m[(ny - crop_n) // 2:(ny - crop_n) // 2 + crop_n, (nx - crop_n) // 2:(nx - crop_n) // 2 + crop_n]
    if not np.all(np.isfinite(c)):
        raise InputError(str(path), "the central crop holds non-measured points")
    c = (c - c.mean()) * height_scale
    tile = np.block([[c, c[:, ::-1]], [c[::-1, :], c[::-1, ::-1]]])
    return Relief(tile, r.dx_m, r.dy_m, periodic=True,
                  source=f"{name} levelled, central {crop_n}^2 crop x {height_scale:g}, mirrored periodic tile")


def case_relief(spec: CaseSpec) -> Relief:
    """The relief of a case (its `relief` kind, module docstring), seeded by the case's seed."""
    from relief_bsdf.surface.synth import DotPattern, RandomFieldSpec, lgp_dots, relief_from_spec
    um = 1e-6
    if spec.relief == "measured":
        return measured_tile()
    if spec.relief == "dots":
        dots = DotPattern(24 * um, 8 * um, 2.0 * um, micro_rms_m=0.3 * um, micro_corr_m=5 * um)
        return lgp_dots(spec.relief_n, spec.pitch_um * um, dots, seed=spec.seed)
    if spec.relief == "anisotropic":
        return relief_from_spec(RandomFieldSpec(spec.relief_n, spec.relief_n, spec.pitch_um * um, spec.rms_um * um,
                                                spec.corr_um * um, anisotropy=2.5, angle_deg=30.0), spec.seed)
    return random_relief(spec.relief_n, spec.pitch_um * um, spec.rms_um * um, spec.corr_um * um,
                         kind=spec.relief, seed=spec.seed)


def _rows(spec: CaseSpec) -> Recording:
    w, ti, side, ts, ps = [], [], [], [], []
    for wl in spec.wavelengths_nm:
        for t in spec.theta_i_deg:
            for sd in ("R", "T"):
                for p in (0.0, 180.0):
                    for s in spec.theta_s_deg:
                        if s == 0.0 and p == 180.0:
                            continue
                        w.append(wl); ti.append(t); side.append(sd); ts.append(s); ps.append(p)
    n = len(w)
    return Recording(wavelength_nm=w, theta_i_deg=ti, phi_i_deg=np.zeros(n), side=side, theta_s_deg=ts,
                     phi_s_deg=ps, bsdf_sr=np.zeros(n), sigma_sr=np.full(n, np.nan))


def _true_signal(spec: CaseSpec, heights_m, rec: Recording):
    """Monte-Carlo plate signal with the concealed effects, per row: (value, mc_sigma).

    `heights_m`: the case's Relief, or its heights (then on the spec's square pitch)."""
    p = spec.parameters
    if isinstance(heights_m, Relief):
        base = Relief(heights_m.heights_m, heights_m.dx_m, heights_m.dy_m, periodic=True)
    else:
        base = Relief(np.asarray(heights_m, float), spec.pitch_um * 1e-6, spec.pitch_um * 1e-6, periodic=True)
    dx, dy = base.dx_m, base.dy_m
    # the relief effects are the project's one relief operation (surface.operations), so the key's
    # height_scale / filter_sigma_um mean what the fit's and the diagnosis's parameters mean
    relief = scale_and_filter(base, p.get("height_scale", 1.0) if "relief_scale" in spec.effects else 1.0,
                              p.get("filter_sigma_um", 0.0) * 1e-6 if "relief_smoothing" in spec.effects else 0.0)
    h = relief.heights_m
    wave = any(e in WAVE_EFFECTS for e in spec.effects)
    face = None if wave else HeightFieldFace(h, dx, dy)
    phys = PlatePhysics(thickness_mm=spec.thickness_mm, n_glass=spec.n_glass,
                        absorption_per_mm=p.get("absorption_per_mm", 0.0),
                        scatter_per_mm=p.get("scatter_per_mm", 0.0), hg_g=p.get("hg_g", 0.0),
                        back_alpha=p.get("back_alpha", 0.0), tilt_deg=p.get("tilt_deg", 0.0),
                        beam_sigma_deg=p.get("blur_deg", 0.0))
    q = p.get("polarization_q", 0.0)
    val = np.zeros(len(rec))
    sig = np.zeros(len(rec))
    for iw, wl in enumerate(spec.wavelengths_nm):
        ng = spec.n_glass
        if "dispersion" in spec.effects:
            ng = spec.n_glass + p["cauchy_B_nm2"] * (1 / wl**2 - 1 / 550.0**2)
        phys.n_glass = ng
        if wave:   # wave optics: one phase screen per wavelength (phase_screen.py)
            from relief_bsdf.validation.phase_screen import PhaseScreenFace, ScreenSampling
            face = PhaseScreenFace(h, dx, dy, wl, coherence_length_um=p.get("coherence_length_um"),
                                   sampling=ScreenSampling(n_max=max(1.6, ng)))
        for it, ti in enumerate(spec.theta_i_deg):
            rows = np.nonzero((rec.wavelength_nm == wl) & (rec.theta_i_deg == ti))[0]
            rng = task_rng(spec.seed, iw, it)
            ex = run_photons(face, phys, ti, 0.0, (1.0, q, 0.0, 0.0), spec.photons, rng)
            v, s = detect(ex, rec.side[rows], rec.theta_s_deg[rows], rec.phi_s_deg[rows], spec.half_angle_deg)
            val[rows] = v
            sig[rows] = s
    val += p.get("background_per_sr", 0.0)
    return val, sig


def make_case(spec: CaseSpec, out_dir: str | Path) -> dict:
    """Write one case folder (relief.x3p, recording.csv, sample.toml, key.json); return the key."""
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    relief = case_relief(spec)
    relief_name = _write_relief(out, relief)
    rec = _rows(spec)
    val, mc_sig = _true_signal(spec, relief, rec)
    from relief_bsdf.validation.record import Goniophotometer, instrument_noise
    noisy, sigma = instrument_noise(val, mc_sig, Goniophotometer(spec.counts_per_sr, spec.gain_noise, spec.floor_sr),
                                    task_rng(spec.seed, 12345))
    write_recording(out / "recording.csv", rec.with_values(noisy, sigma),
                    comments=[f"concealed case {spec.name} (see key file kept apart)"])
    write_sample(out / "sample.toml", {
        "plate": {"thickness_mm": spec.thickness_mm, "refractive_index": spec.n_glass, "rough_face": "front"},
        "relief": {"file": relief_name},
        "instrument": {"detector_half_angle_deg": spec.half_angle_deg, "polarization": "unpolarized"},
        "recording": {"file": "recording.csv"}})
    key = {"case": spec.name, "effect": spec.effect, "effects": list(spec.effects), "parameters": spec.parameters,
           "relief": spec.relief, "seed": spec.seed,
           "photons_per_incidence": spec.photons,
           "noise": {"counts_per_sr": spec.counts_per_sr, "gain_noise": spec.gain_noise, "floor_sr": spec.floor_sr}}
    return key


def _write_relief(out: Path, relief: Relief) -> str:
    try:
        from relief_bsdf.io.heightmaps import write_relief
        write_relief(out / "relief.x3p", relief)
        return "relief.x3p"
    except ImportError:  # readers not available: npz is a format the project reads too
        with open(out / "relief.npz", "wb") as fh:
            np.savez(fh, heights=relief.heights_m, dx=relief.dx_m, dy=relief.dy_m)
        return "relief.npz"


def _case_task(context, spec: CaseSpec) -> dict:
    root = Path(context)
    key = make_case(spec, root / spec.name)
    return key


def generate(out_root: str | Path, cases: list[CaseSpec] | None = None, progress=None,
             settings: ParallelSettings | None = None) -> Path:
    """Generate every case under out_root (one `parallel.map_tasks` task per case, run where
    `settings` say; default: the settings in force); keys go to out_root/key.json."""
    root = Path(out_root)
    root.mkdir(parents=True, exist_ok=True)
    cases = cases if cases is not None else default_cases()
    keys = map_tasks(_case_task, cases, str(root), settings=settings, progress=progress, label="concealed cases")
    write_text_atomic(root / "key.json", json.dumps({"format": "relief-conceal-key/1", "cases": keys}, indent=1))
    return root / "key.json"
