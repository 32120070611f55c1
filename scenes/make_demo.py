"""Generate the demo scene: a relief, a sample.toml and a plate recording (seeded, reproducible).

    python scenes/make_demo.py [--out scenes/demo] [--seed 1]

The relief is a matte (anti-glare-like) acrylic surface: Gaussian heights, rms 100 nm,
correlation length 1 um, 1024 x 1024 points at 0.125 um (a 128 um periodic tile, about 16 000
independent bumps, so a 1-degree detector cone sees the relief's statistics rather than its
individual facets); stored as float32 X3P.  At 550 nm its transmission keeps a coherent part
(Debye-Waller factor ~0.7 at normal incidence) above a ~4-degree lobe; reflection is diffuse.

The "measured" recording is the plate simulated through a *modified* relief (heights x 1.25,
Gaussian filter sigma 0.3 um) with 3 % multiplicative noise, so `relief fit` on the sample should
find height_scale ~ 1.25 and filter_sigma_um ~ 0.3.  The plate is simulated with the
deterministic model (plate.py) and the fit's default boundary method (microfacet+dw) on its
default table grid: a synthetic recording that the fit's own model can reach exactly.  The
independent check of that plate model is the photon engine of the plate (plate/photon.py) on this same
sample (tests/backend/plate/test_plate_mc.py: within 3 % in-lobe with ray-traced tables).
"""
from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np

TRUE_SCALE = 1.25
TRUE_FILTER_UM = 0.3
NOISE_REL = 0.03


def main(argv=None) -> int:
    ap = argparse.ArgumentParser()
    ap.add_argument("--out", default=str(Path(__file__).parent / "demo"))
    ap.add_argument("--seed", type=int, default=1)
    a = ap.parse_args(argv)
    from relief_bsdf.fit.optimise import Forward, TableGrid
    from relief_bsdf.core.index import ConstantIndex
    from relief_bsdf.parallel import task_rng
    from relief_bsdf.plate import Experiment, FlatFace, Instrument, Plate, ReliefFace, in_plane_rows
    from relief_bsdf.io.heightmaps import read_relief, write_relief
    from relief_bsdf.io.recording import Recording, write_recording, write_sample
    from relief_bsdf.surface.synth import random_relief
    out = Path(a.out)
    out.mkdir(parents=True, exist_ok=True)
    relief = random_relief(1024, 0.125e-6, 100e-9, 1.0e-6, "gaussian", seed=a.seed)
    write_relief(out / "relief.x3p", relief, x3p_data_type="F")
    relief = read_relief(out / "relief.x3p")      # what users (and the fit) read: float32 heights
    model = Experiment(Plate(2e-3, ConstantIndex(1.49), ReliefFace(relief), FlatFace()),
                       Instrument(detector_half_angle_deg=1.0))
    rows = in_plane_rows(550.0, [0, 15, 30, 45, 60, 75], np.arange(1.0, 89.0, 2.0))
    fwd = Forward(relief, model, rows, grid=TableGrid())
    clean = fwd.simulate(TRUE_SCALE, TRUE_FILTER_UM)
    rng = task_rng(a.seed, 7)
    sigma = NOISE_REL * clean
    noisy = np.maximum(clean + sigma * rng.standard_normal(clean.size), 0.0)
    rec = Recording(rows.wavelength_nm, rows.theta_i_deg, rows.phi_i_deg, rows.side, rows.theta_s_deg,
                    rows.phi_s_deg, noisy, sigma)
    write_recording(out / "recording.csv", rec,
                    comments=[f"demo: plate through relief x {TRUE_SCALE} filtered {TRUE_FILTER_UM} um, "
                              f"{NOISE_REL:.0%} noise, seed {a.seed}"])
    write_sample(out / "sample.toml", {
        "plate": {"thickness_mm": 2.0, "refractive_index": 1.49, "rough_face": "front", "absorption_per_mm": 0.0},
        "relief": {"file": "relief.x3p"},
        "instrument": {"detector_half_angle_deg": 1.0, "polarization": "unpolarized"},
        "recording": {"file": "recording.csv"}})
    print(f"wrote {out}/sample.toml, relief.x3p, recording.csv ({len(rec)} rows)")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
