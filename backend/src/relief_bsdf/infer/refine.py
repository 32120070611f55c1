"""Refinement of an inferred relief through the one forward model, with the fit's machinery.

What is fitted.  The relief of a candidate (infer.families: a slope density realised by infer.synth's
random crossed lenslets, seeded) carries its height scale s (heights h -> s h, every facet slope times
s: fit.optimise.process_relief, the fit's own parameter), and the plate its refractive index n when the
sample does not state it.  Both act on the transmitted lobe, differently: its width is set by
(n - 1) s (infer.slopes: u = (n - 1) s + O(s^3) at normal incidence; at the EDS10 lobe's edge, u = 0.099,
n 1.5 and n 1.6 give the same u within 1e-4 at the slopes of equal (n - 1) s), its level by the two faces'
Fresnel transmittances, which depend on n alone.  So the search runs in the coordinates
x = (w, n): the width scale w = s (n - 1) / (n0 - 1) and the index at fixed width (s = w (n0 - 1) / (n - 1)),
in which a step in n changes the level alone.  In (s, n) the two columns are nearly parallel (a step of
0.005 in n and one of 0.01 in s both widen the lobe by 1 %, and the table noise between the two
points, a few thousand of chi^2 on EDS10, decides the step), which left n at its start.  The
intervals are those of (w, n) carried to (s, n) by the map's Jacobian.

The objective.  chi^2 of the recording's transmitted rows at the inversion incidence that read the
lobe, at or above `LOBE_FRACTION` of its peak (the 99.5th percentile of the readings, as infer.slopes),
with the residuals of fit.residual.chi2 (recording sigma, censored readings), each evaluation
`plate.simulate` through fit.optimise.Forward.  Why not every row: the families describe the lobe's
facets, and the dim halo around an engineered lobe (EDS10: 0.4 1/sr at 0.15-0.2 in direction cosine from
the undeviated ray against a 24 1/sr plateau, a few per cent of the light) has sigma down to the file's
noise floor, so on every row the halo's chi^2 outweighs the lobe's a hundredfold (measured: top-hat
family at n 1.5, 1.9e5 of chi^2 inside u 0.12 against 3.2e6 beyond) and a fit of (s, n) on it moves the
index to wherever the halo is least wrong (n 1.74, transmittance 0.86 against 0.90 measured).  The lobe
rows hold the level (the index) and the width; the halo is reported in the metric over every row, not
fitted.  The evaluations run on `REFINE_GRID`: the diagnosis's screening grid (no inside sector
tables, the loop azimuth-circulant) with a tenth of the face's rays per inside incidence; both change
the light that returns from inside the glass, not the first pass that makes the lobe; the final
simulation and the tables are on the full default grid.

The search (fit.gauss_newton.polish, the fit's one Gauss-Newton): finite-difference Jacobians
(steps `STEP` in (w, n): 1 % of width, 0.05 of index, a level change of ~1 %, above the table noise),
at most `POLISH_STEPS` kept steps; the 68 % intervals from fit.covariance.parameter_covariance
(curvature widened by the reduced chi^2 and by residuals larger than the noise, HAC) on the polish's
Jacobian (a forward-difference one made at the answer when the polish returned none: two plate
evaluations instead of four; its bias, half a step times the curvature, is below the widening by the
reduced chi^2 wherever the model misses the noise).

The choice between candidates (criteria, the project's one information criterion): each candidate's
chi^2 at its slope-plane fit (s = 1, the start index), k its family's parameters plus the plate's (s, and n
when fitted); candidates in order of k, a more complex one replaces the current choice only when it wins by
more than criteria.BIC_MARGIN (QBIC: chi^2 divided by the complex model's overdispersion).  A
candidate whose fitted density coincides with one screened before it (total variation below
`SAME_DENSITY_TV`: a two-scale fit whose scales meet, dots without a flat share) takes that one's chi^2
instead of a plate evaluation of its own.  Only the
chosen candidate is polished: the screening ranks by the unpolished chi^2, which is stated.
"""
from __future__ import annotations

from dataclasses import dataclass, field, replace
from typing import Any, Callable

import time

import numpy as np

#: rows reading at least this fraction of the lobe's peak form the objective (module doc)
LOBE_FRACTION = 0.05
#: finite-difference steps of (height scale, index)
STEP = (0.01, 0.05)
LOWER = (0.3, 1.3)
UPPER = (3.0, 2.2)
POLISH_STEPS = 2
#: candidates' densities closer than this (total variation) share one screening evaluation (module doc)
SAME_DENSITY_TV = 0.01
#: the refinement's grid (module doc): no inside sector tables, a tenth of the rays per inside incidence
REFINE_INSIDE_SAMPLES_SCALE = 0.1


@dataclass
class Objective:
    """chi^2 of one candidate's plate over the refinement rows as a function of x = (s[, n]) (module doc).

    forward_at(n) -> fit.optimise.Forward of the candidate's relief in the plate of index n (cached);
    rows: the distinct refinement rows, inverse: their expansion to `measured` (the recording's rows,
    RPC files repeat the pole), sigma: those rows' recording sigma."""

    forward_at: Callable[[float], Any]
    rows: Any
    inverse: np.ndarray
    measured: Any
    n0: float
    fit_index: bool
    progress: Callable[[str], None] | None = None
    evaluations: list = field(default_factory=list)
    _cache: dict = field(default_factory=dict, repr=False)
    _seconds: dict = field(default_factory=dict, repr=False)

    def point(self, x: np.ndarray) -> tuple[float, float]:
        """(height scale s, index n) of x = (w[, n]) (module doc)."""
        x = np.asarray(x, float)
        n = float(x[1]) if self.fit_index else self.n0
        return float(x[0]) * (self.n0 - 1.0) / (n - 1.0), n

    def to_s_n(self, x: np.ndarray, cov: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(s[, n]) and its covariance from x = (w[, n]) and cov(x): the map's Jacobian."""
        s, n = self.point(x)
        if not self.fit_index:
            return np.array([s]), cov
        w = float(x[0])
        A = np.array([[(self.n0 - 1.0) / (n - 1.0), -w * (self.n0 - 1.0) / (n - 1.0) ** 2], [0.0, 1.0]])
        return np.array([s, n]), A @ cov @ A.T

    def values(self, x: np.ndarray) -> np.ndarray:
        s, n = self.point(x)
        key = (round(s, 10), round(n, 10))
        if key not in self._cache:
            if self.progress is not None:
                self.progress(f"plate at height scale {s:.4g}, n {n:.4g}")
            t0 = time.perf_counter()
            self._cache[key] = self.forward_at(n).simulate(s, 0.0)[self.inverse]
            self._seconds[key] = time.perf_counter() - t0
        return self._cache[key]

    def residuals(self, x: np.ndarray) -> tuple[float, np.ndarray]:
        from relief_bsdf.fit.residual import misfit_sigma, signed_residuals
        v = self.values(x)
        z = signed_residuals(np.asarray(self.measured.bsdf_sr, float), v, misfit_sigma(self.measured))
        f = float(z @ z)
        s, n = self.point(x)
        self.evaluations.append({"height_scale": s, "refractive_index": n, "chi2": f,
                                 "seconds": self._seconds.pop((round(s, 10), round(n, 10)), 0.0)})
        return f, z

    def jacobian(self, x: np.ndarray, central: bool) -> np.ndarray:
        x = np.asarray(x, float)
        h = np.asarray(STEP[:x.size])
        lo, hi = np.asarray(LOWER[:x.size]), np.asarray(UPPER[:x.size])
        z0 = None if central else self.residuals(x)[1]
        cols = []
        for j in range(x.size):
            e = np.zeros_like(x)
            e[j] = h[j]
            up = np.minimum(x + e, hi)
            if central:
                dn = np.maximum(x - e, lo)
                cols.append((self.residuals(up)[1] - self.residuals(dn)[1]) / (up[j] - dn[j]))
            else:
                cols.append((self.residuals(up)[1] - z0) / (up[j] - x[j]))
        return np.stack(cols, axis=1)


def refinement_rows(rec: Any, theta_i_deg: float, phi_i_deg: float, wavelength_nm: float) -> Any:
    """The recording's T rows of the inversion incidence that read the lobe (module doc)."""
    sel = ((rec.side == "T") & (rec.theta_i_deg == theta_i_deg) & (rec.phi_i_deg == phi_i_deg)
           & (rec.wavelength_nm == wavelength_nm))
    peak = float(np.percentile(rec.bsdf_sr[sel], 99.5))
    return rec.subset(sel & (rec.bsdf_sr >= LOBE_FRACTION * peak))


def refine_grid():
    """The refinement's plate grid (module doc)."""
    from relief_bsdf.plate import TableGrid
    from relief_bsdf.plate.grid import NO_SECTORS_DEG
    return TableGrid(sector_step_deg=NO_SECTORS_DEG, inside_samples_scale=REFINE_INSIDE_SAMPLES_SCALE)


def x_start(n0: float, fit_index: bool) -> np.ndarray:
    return np.array([1.0, n0]) if fit_index else np.array([1.0])


def choose(screened: list[dict], n_rows: int) -> tuple[int, list[dict]]:
    """Index of the chosen candidate and the decisions (module doc): screened[i] has "k" (all fitted
    parameters) and "chi2"; in order of k, a more complex candidate replaces the choice only when
    criteria.bic_gain (with its own overdispersion) exceeds BIC_MARGIN."""
    from relief_bsdf.criteria import BIC_MARGIN, bic, bic_gain, overdispersion
    order = sorted(range(len(screened)), key=lambda i: (screened[i]["k"], screened[i]["chi2"]))
    best = order[0]
    steps = []
    for i in order[1:]:
        a, b = screened[best], screened[i]
        if b["k"] == a["k"]:
            gain = a["chi2"] - b["chi2"]         # same k: the lower chi^2 (the BIC difference itself)
        else:
            gain = bic_gain(a["chi2"], a["k"], b["chi2"], b["k"], n_rows,
                            overdispersion(b["chi2"], b["k"], n_rows))
        won = gain > (0.0 if b["k"] == a["k"] else BIC_MARGIN)
        steps.append({"current": a["name"], "candidate": b["name"], "bic_gain": float(gain), "taken": bool(won)})
        if won:
            best = i
    for s in screened:
        s["bic"] = bic(s["chi2"], s["k"], n_rows)
    return best, steps


@dataclass
class Refined:
    """The polished point x = (w[, n]), its (s[, n]), chi^2, the 68 % intervals (+- one standard deviation
    of s[, n]) and how they were made."""

    x: np.ndarray
    s_n: np.ndarray
    chi2: float
    sd: np.ndarray
    correlation: np.ndarray
    notes: list


def polish_and_intervals(obj: Objective, x0: np.ndarray) -> Refined:
    """fit.gauss_newton.polish from x0, then fit.covariance.parameter_covariance (module doc)."""
    from relief_bsdf.fit.covariance import parameter_covariance, scans_of
    from relief_bsdf.fit.gauss_newton import polish
    k = x0.size
    res = polish(obj.residuals, obj.jacobian, x0, np.asarray(LOWER[:k]), np.asarray(UPPER[:k]),
                 np.asarray(STEP[:k]), POLISH_STEPS, central=False)
    J = res.jacobian if res.jacobian is not None else obj.jacobian(res.x, False)
    _, z = obj.residuals(res.x)
    cov = parameter_covariance(J, z, scans_of(obj.measured))
    s_n, cov_sn = obj.to_s_n(res.x, cov.cov)
    sd = np.sqrt(np.clip(np.diag(cov_sn), 0, None))
    with np.errstate(invalid="ignore", divide="ignore"):
        corr = cov_sn / np.outer(sd, sd)
    notes = [n for n in (cov.note(j) for j in range(k)) if n]
    if res.jacobian is None:
        notes.append(f"the polish stopped after {POLISH_STEPS} steps before it converged; the intervals are "
                     "made at its last point")
    return Refined(res.x, s_n, float(res.f), sd, corr, notes)


def density_distance(a: Any, b: Any) -> float:
    """Total-variation distance between two slope densities on the same bins (infer.slopes.SlopeDensity)."""
    return float(0.5 * np.sum(np.abs(a.density - b.density)) * a.cell_area)
