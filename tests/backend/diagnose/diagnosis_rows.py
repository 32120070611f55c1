"""Recording rows for the diagnosis tests (imported by conftest.py and test modules by this unique name)."""
import numpy as np


def in_plane_rows(tis, wavelengths=(550.0,), step_deg=10.0, sigma=0.01):
    """Recording rows at theta_s every `step_deg` (phi_s 0 and 180, R and T), sigma `sigma`, values 0."""
    from relief_bsdf.io.recording import Recording
    g = [(wl, ti, sd, t, ps) for wl in wavelengths for ti in tis for sd in ("R", "T") for ps in (0.0, 180.0)
         for t in np.arange(0.0, 90.0, step_deg) if not (t == 0.0 and ps == 180.0)]
    W, TI, SD, TS, PS = (np.array(c) for c in zip(*g))
    n = len(W)
    return Recording(W.astype(float), TI.astype(float), np.zeros(n), SD, TS.astype(float), PS.astype(float),
                     np.zeros(n), np.full(n, sigma))
