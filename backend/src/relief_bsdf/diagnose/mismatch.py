"""Where a simulation misses a recording, and what the miss looks like.

Input: recording rows (a `recording.Recording`: geometry, measured values y = bsdf_sr and
sigmas sigma_sr, all finite, see `Recording.with_sigma_fallback`), simulated values m and the
model's own sigma.  Everything works on the noise-normalised residual
z = (y - m) / s with s^2 = sigma_recording^2 + sigma_model^2, so a region "matters" when it
carries a large share of chi^2 = sum z^2, not when its raw values are large.

Localisation (`locate`): rows are grouped into scans (wavelength, side, theta_i, phi_i,
phi_s) ordered by theta_s; inside a scan, rows with |z| above a threshold (default 2, with
one-row gaps bridged) form contiguous regions; each region reports its theta_s range and
its share of the total chi^2.  Regions come largest share first (the `mismatch` list of
diagnosis.json, formats.md).

Shape (`classify`): the residual of a set of rows is projected, one template at a time, on
physically meaningful templates built from the simulated curve m(theta_s):
- offset:       r = b                        (additive background)
- gain:         r = c m                      (a level error)
- shift:        r = c dm/dtheta_s            (a lobe displaced: tilt, index)
- broadening:   r = c d2m/dtheta_s^2         (a lobe wider/narrower: blur, roughness)
- path_deficit: r = -c m / cos(theta_glass)  (loss growing with the path length in the glass,
                                              theta_glass from Snell for the scan's angle)
- asymmetry:    r = c m sign(phi_s)          (+ at phi_s = 0, - at 180: left/right imbalance)
- colour_trend: r = c m (l - l_mean)         (spectral recordings only)
Each template's explained fraction is 1 - chi2(after the 1-parameter weighted fit)/chi2;
templates are reported best first.  This is description, not selection: the effect is
chosen by `diagnose` with the full forward model.
"""
from __future__ import annotations

import numpy as np

SHAPES = ("offset", "gain", "shift", "broadening", "path_deficit", "asymmetry", "colour_trend")


def _scans(rows) -> dict:
    keys = {}
    for k in range(len(rows.bsdf_sr)):
        key = (float(rows.wavelength_nm[k]), str(rows.side[k]), float(rows.theta_i_deg[k]),
               float(rows.phi_i_deg[k]), float(rows.phi_s_deg[k]))
        keys.setdefault(key, []).append(k)
    out = {}
    for key, idx in keys.items():
        idx = np.asarray(idx)
        out[key] = idx[np.argsort(rows.theta_s_deg[idx])]
    return out


def residual_z(rows, model: np.ndarray, model_sigma: np.ndarray | None = None) -> np.ndarray:
    """Noise-normalised residual (y - m) / sqrt(sigma^2 + sigma_model^2)."""
    ms = np.zeros_like(model) if model_sigma is None else model_sigma
    return (rows.bsdf_sr - model) / np.sqrt(rows.sigma_sr**2 + ms**2)


def templates(rows, model: np.ndarray, n_glass: float = 1.5) -> dict[str, np.ndarray]:
    """The shape templates of the module docstring, evaluated on every row."""
    n = len(model)
    t = {name: np.zeros(n) for name in SHAPES}
    t["offset"][:] = 1.0
    t["gain"][:] = model
    for key, idx in _scans(rows).items():
        th = np.radians(rows.theta_s_deg[idx])
        m = model[idx]
        if idx.size >= 3:
            d1 = np.gradient(m, th)
            d2 = np.gradient(d1, th)
        else:
            d1 = d2 = np.zeros(idx.size)
        # mirror the phi_s = 180 half so the derivative is along one continuous in-plane angle
        sgn = 1.0 if abs(((key[4] - key[3]) % 360.0)) < 90 or abs(((key[4] - key[3]) % 360.0)) > 270 else -1.0
        t["shift"][idx] = sgn * d1
        t["broadening"][idx] = d2
        sin_g = np.sin(th) / n_glass if key[1] == "T" else np.sin(np.radians(key[2])) / n_glass
        t["path_deficit"][idx] = -m / np.sqrt(np.clip(1 - sin_g**2, 1e-6, 1))
        t["asymmetry"][idx] = m * sgn
    wl = np.asarray(rows.wavelength_nm, float)
    if np.ptp(wl) > 0:
        t["colour_trend"][:] = model * (wl - wl.mean()) / np.ptp(wl)
    return t


def classify(rows, model: np.ndarray, model_sigma: np.ndarray | None = None, n_glass: float = 1.5,
             subset: np.ndarray | None = None) -> list[dict]:
    """Explained chi^2 fraction of each shape template (best first), on `subset` rows if given."""
    s = np.sqrt(rows.sigma_sr**2 + (0 if model_sigma is None else model_sigma) ** 2)
    r = rows.bsdf_sr - model
    sel = np.arange(len(r)) if subset is None else np.asarray(subset)
    c0 = float(np.sum((r[sel] / s[sel]) ** 2))
    out = []
    if c0 <= 0:
        return out
    for name, tv in templates(rows, model, n_glass).items():
        a = tv[sel] / s[sel]
        b = r[sel] / s[sel]
        aa = float(a @ a)
        if aa <= 0:
            continue
        c = float(a @ b) / aa
        if name in ("offset", "path_deficit") and c < 0:
            c = 0.0    # a background cannot be negative; a path loss cannot be a gain
        frac = 1 - float(np.sum((b - c * a) ** 2)) / c0
        out.append({"shape": name, "explained": round(max(frac, 0.0), 4), "coefficient": c})
    out.sort(key=lambda d: -d["explained"])
    return out


def locate(rows, model: np.ndarray, model_sigma: np.ndarray | None = None, *, threshold: float = 2.0,
           max_regions: int = 8, n_glass: float = 1.5) -> list[dict]:
    """Contiguous regions of large residual, largest share of chi^2 first (formats.md entries)."""
    return [e for e, _ in regions(rows, model, model_sigma, threshold=threshold, max_regions=max_regions,
                                  n_glass=n_glass)]


def regions(rows, model: np.ndarray, model_sigma: np.ndarray | None = None, *, threshold: float = 2.0,
            max_regions: int = 8, n_glass: float = 1.5) -> list[tuple[dict, np.ndarray]]:
    """`locate`'s entries with the row indices of each region: [(entry, rows), ...]."""
    z = residual_z(rows, model, model_sigma)
    c = z**2
    total = float(c.sum())
    if total <= 0:
        return []
    multi_wl = np.ptp(np.asarray(rows.wavelength_nm, float)) > 0
    found = []
    for key, idx in _scans(rows).items():
        hot = np.abs(z[idx]) > threshold
        # bridge single-row gaps
        if hot.size >= 3:
            gap = ~hot[1:-1] & hot[:-2] & hot[2:]
            hot[1:-1] |= gap
        k = 0
        while k < hot.size:
            if not hot[k]:
                k += 1
                continue
            j = k
            while j + 1 < hot.size and hot[j + 1]:
                j += 1
            sel = idx[k:j + 1]
            share = float(c[sel].sum() / total)
            entry = {"side": key[1], "theta_i_deg": key[2], "phi_s_deg": key[4],
                     "theta_s_deg": [float(rows.theta_s_deg[sel].min()), float(rows.theta_s_deg[sel].max())],
                     "share": round(share, 4),
                     "sign": "excess" if float(np.sum(z[sel])) > 0 else "deficit"}
            if multi_wl:
                entry["wavelength_nm"] = key[0]
            if key[3] != 0.0:
                entry["phi_i_deg"] = key[3]
            shapes = classify(rows, model, model_sigma, n_glass, subset=idx)
            if shapes and shapes[0]["explained"] > 0.3:
                entry["shape"] = shapes[0]["shape"]
            found.append((entry, sel))
            k = j + 1
    found.sort(key=lambda d: -d[0]["share"])
    return found[:max_regions]


# what a residual of each shape resembles physically (a description for the "nothing fits" account)
SHAPE_PHYSICS = {
    "offset": "a constant background (stray light, a detector offset)",
    "gain": "a level error (source or detector calibration, a loss that does not depend on the path)",
    "shift": "a displaced lobe (a tilted sample, a different refractive index)",
    "broadening": "a wider or narrower lobe (beam divergence, relief heights or smoothing, back-face roughness)",
    "path_deficit": "a loss growing with the path in the glass (bulk absorption, volume scattering)",
    "asymmetry": "a left/right imbalance (a tilted sample, a polarised source, an anisotropic relief)",
    "colour_trend": "a trend with wavelength (dispersion)",
}


def attribute(rows, found: list[tuple[dict, np.ndarray]], models: list[tuple[str, np.ndarray, np.ndarray]]
              ) -> list[dict]:
    """Which effect explains which region: `found` = regions of the baseline residual with their rows,
    `models` = [(effect added, values, model sigma), ...] along the stepwise path, the baseline first
    (effect "none").  Each entry gains `explained_by` (the effect whose step removed most of the
    region's chi^2, or "unexplained" when the final model still leaves over half of it) and
    `explained_share` {effect: fraction of the region's baseline chi^2 removed by its step}."""
    out = []
    for entry, sel in found:
        c = [float(np.sum(residual_z(rows, v, s)[sel] ** 2)) for _, v, s in models]
        shares = {}
        for j in range(1, len(models)):
            shares[models[j][0]] = round(max(c[j - 1] - c[j], 0.0) / c[0], 4) if c[0] > 0 else 0.0
        e = dict(entry)
        left = c[-1] / c[0] if c[0] > 0 else 0.0
        e["explained_share"] = shares
        e["explained_by"] = ("unexplained" if left > 0.5 or not shares
                             else max(shares, key=lambda k: shares[k]))
        out.append(e)
    return out
