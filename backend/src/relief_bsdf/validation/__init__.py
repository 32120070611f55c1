"""Validation that users run to check the tool: `relief conceal` (concealed-effect cases).

Independent of the forward model it checks (plate/, methods/, diagnose/): its own photon engine
(`photon`), its own ray-traced relief face (`conceal.HeightFieldFace`) and wave-optics face
(`phase_screen.PhaseScreenFace`), its own detector.  It shares only the physics core, the
surface (Relief, the one random-field generator, the one triangulation, the one relief
operation) and io/.

- `conceal`: seeded case folders (relief, recording, sample) with one hidden effect + the key;
- `photon`: Monte-Carlo photon transport through a plate with a pluggable rough face (Stokes);
- `phase_screen`: the scalar Kirchhoff thin phase screen of a real relief as a photon face;
- `record`: an independent recording (photon run + detector through the ray-traced relief) and the
  goniophotometer noise model (the demo's and the forward-accuracy benchmark's truth).
"""
from relief_bsdf.validation.conceal import (EFFECTS_CONCEALABLE, CaseSpec, HeightFieldFace, default_cases, generate,
                                            make_case)
from relief_bsdf.validation.phase_screen import PhaseScreenFace, ScreenSampling
from relief_bsdf.validation.photon import Exits, NormalsFace, PlatePhysics, detect, run_photons
from relief_bsdf.validation.record import Goniophotometer, instrument_noise, trace_recording

__all__ = ["EFFECTS_CONCEALABLE", "CaseSpec", "Exits", "Goniophotometer", "HeightFieldFace", "NormalsFace",
           "PhaseScreenFace", "PlatePhysics", "ScreenSampling", "default_cases", "detect", "generate",
           "instrument_noise", "make_case", "run_photons", "trace_recording"]
