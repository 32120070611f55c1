"""Presets: a ready-to-render plate scene in one click (no measurement needed).

Each preset is a synthetic relief from the backend's generators (`relief_bsdf.surface.synth`),
a material and a plate; `preset_plate` derives the boundary tables and bakes them exactly as a
measured relief is (`plate_scene._tables` with the relief's own physics, method `auto`,
`relief_bsdf.plate.choice.DEFAULT_METHOD`: ray tracing for these reliefs; the Gaussian-statistics
surrogate `microfacet+dw` would spread the flat 69 % between light-guide dots into one wide lobe,
haze 0.80 instead of the dots' 0.34; `relief_bsdf.bake.bake_lut`), and the scene is
`plate_scene.build_scene`: the plate over a checkerboard under diffuse light, camera set, so
F12 (or `bpy.ops.render.render`) renders it.  The numbers are typical of each kind of surface,
chosen for a recognisable look, not measurements of a product:

- frosted acrylic: PMMA (n 1.49), 3 mm, sand-blasted face: Gaussian random relief, rms height
  1 um, correlation length 6 um (rms slope ~0.24): strong haze;
- anti-glare film: hard-coated film (n 1.50), 0.2 mm, gentle relief: rms 0.25 um, correlation
  5 um (rms slope ~0.07): a moderate haze, the board stays readable;
- light-guide dots: PMMA (n 1.49), 4 mm, spherical-cap dots (radius 10 um, height 3 um) on a
  32 um jittered grid on the back face, as printed or moulded on light-guide plates.
"""
from __future__ import annotations

from dataclasses import dataclass


@dataclass(frozen=True)
class Preset:
    key: str
    label: str
    description: str
    ior: float
    thickness_m: float
    rough_face: str
    relief: str                        # "random" or "dots"
    params: tuple                      # generator arguments (see `_relief`)


PRESETS = {p.key: p for p in (
    Preset("frosted_acrylic", "Frosted acrylic", "Sand-blasted PMMA plate, 3 mm: strong haze",
           1.49, 3e-3, "front", "random", (128, 1e-6, 1.0e-6, 6e-6)),
    Preset("anti_glare_film", "Anti-glare film", "Hard-coated film, 0.2 mm: moderate haze",
           1.50, 0.2e-3, "front", "random", (128, 1e-6, 0.25e-6, 5e-6)),
    Preset("light_guide_dots", "Light-guide dots", "PMMA light-guide plate, 4 mm, dots on the back face",
           1.49, 4e-3, "back", "dots", (128, 2e-6, 32e-6, 10e-6, 3e-6)),
)}

ITEMS = [(p.key, p.label, p.description) for p in PRESETS.values()]


def _relief(p: Preset):
    from relief_bsdf.surface.synth import DotPattern, lgp_dots, random_relief
    if p.relief == "random":
        n, pitch, rms, corr = p.params
        return random_relief(n, pitch, rms, corr, seed=0)
    n, pitch, dot_pitch, radius, height = p.params
    return lgp_dots(n, pitch, DotPattern(dot_pitch, radius, height), seed=0)


def preset_plate(key: str, albedo=None, closure: str = "metallic", progress=None) -> dict:
    """The plate of preset `key` as `plate_scene.build_scene` takes it (no bpy)."""
    from relief_bsdf.bake import bake_lut
    from relief_bsdf.core.index import ConstantIndex, Material
    from relief_bsdf.errors import InputError
    from .plate_scene import _tables
    p = PRESETS.get(key)
    if p is None:
        raise InputError("preset", f"unknown preset {key!r}; choose from {', '.join(PRESETS)}")
    from relief_bsdf.plate.choice import DEFAULT_METHOD
    tables = _tables(_relief(p), Material(ConstantIndex(p.ior)), DEFAULT_METHOD, progress)
    lut = bake_lut(tables, p.label, albedo=albedo, reflection_closure=closure)
    return {"label": p.label, "lut": lut, "thickness_m": p.thickness_m, "rough_face": p.rough_face, "ior": lut.ior}
