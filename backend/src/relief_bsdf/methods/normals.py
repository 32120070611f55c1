"""`normals`: Monte Carlo on the density of facet normals (random bump mapping), paper sec. 2.2.

The relief enters only through the *distribution* of its facet normals; positions, and so
real shadowing and inter-reflection geometry, are forgotten.  It is the fast approximate
method the paper criticises, implemented honestly so it can be compared with `ray`
(same table axes, same normalisation, same delta and `lost` bookkeeping).

Model
-----
- Facets: the two triangles of every grid cell of the height map (split along the
  h00-h11 diagonal, the piecewise-linear surface), each with slope (sx, sy); every triangle
  covers the same projected area dx dy / 2, so a uniform draw over triangles samples the
  slope density P22 weighted by projected area, which is the density behind a microfacet
  D(m) (D(m) cos(theta_m) dw_m = projected-area fraction).  Triangles with an invalid
  corner are dropped.  The measured slopes are used as they are (no tilt removal, as `ray`).
- Which facet a ray meets: a ray travelling along d meets a facet with a probability
  proportional to the facet's cross-section seen along the ray, (area / m_z) * max(0, -d.m)
  for the facet normal m facing the ray's medium, i.e. proportional to
  sigma (d_x sx + d_y sy - d_z) (sigma = +1 above, -1 below the boundary) per triangle.
  The facet is drawn by rejection sampling against the exact maximum over the convex hull
  of the slope set.  For the first hit this is the Smith visible-normal density
  G1(wi) max(0, wi.m) D(m) / cos(theta_i) (Heitz 2014, eq. 38), so single scattering reproduces
  Walter's BSDF with G = G1(wi) and no masking of the exit direction
  (`microfacet.walter_bsdf(..., shadowing="incident")`) - what this method should agree
  with, for gentle slopes where rescattering is rare.
- At the facet: unpolarised Fresnel reflectance F (optics.fresnel_unpolarized) decides
  reflect or refract by Russian roulette (weights stay 1: energy is conserved ray by ray in
  a lossless medium); Snell refraction; total internal reflection is F = 1.
- Invalid directions (paper sec. 2.2): a ray whose new direction points back into the
  boundary (reflected downward above it, or refracted upward below it) meets another
  facet drawn the same way, and again, until it leaves in a proper direction.
- Grazing heuristic (paper sec. 2.2, option `grazing_heuristic`, off by default): a ray
  leaving properly but near grazing is sent to another facet with probability p(theta),
  zero along the macroscopic normal and maximal at grazing.  "smith": p = 1 - G1(theta)
  = Lambda / (1 + Lambda) with the Beckmann Lambda of the relief's rms slope (the Smith
  probability that the exit direction is masked); "cosine": p = 1 - |cos theta|.  Only
  facets that face the ray can be met (if none does, the ray leaves).
- Detector: the exit direction is binned into the request's (theta_s, phi_s) cells; f =
  count / (N * projected solid angle) as in `ray`, so `hemispherical()` gives power
  fractions; exits within `specular_tol_rad` of the flat mean plane's mirror / refraction
  direction go to `specular_R/T` (only exactly flat facets produce them).
- `lost`: transmission into an absorbing medium, rays still bouncing after `max_bounces`,
  rays that can meet no facet; the split is in metadata.  Nothing is dropped silently.
Light from inside: the frame is mirrored (+z into the medium of incidence), which negates
the slopes.  Validity: geometric optics, and the assumption that successive facets are
statistically independent of each other and of the ray position (no correlation of
heights): wrong at grazing angles and high slopes, which is the paper's point.
"""
from __future__ import annotations

import time

import numpy as np
from scipy.spatial import ConvexHull, QhullError

from relief_bsdf.bsdf.table import BsdfTable, direction, projected_solid_angle
from relief_bsdf.errors import InputError, RequestError
from relief_bsdf.core.optics import fresnel_unpolarized, refract
from relief_bsdf.parallel.tasks import map_tasks, task_rng
from relief_bsdf.methods.microfacet import smith_G1

MIN_FACETS = 64
HEURISTICS = ("smith", "cosine")


# ------------------------------------------------------------------ facets


def triangle_slopes(relief) -> tuple[np.ndarray, np.ndarray]:
    """Slopes (sx, sy) of the valid triangles of the piecewise-linear relief (2 per grid cell)."""
    h = relief.heights_m
    if relief.periodic:
        h00 = h
        h01 = np.roll(h, -1, axis=1)
        h10 = np.roll(h, -1, axis=0)
        h11 = np.roll(h10, -1, axis=1)
    else:
        h00, h01, h10, h11 = h[:-1, :-1], h[:-1, 1:], h[1:, :-1], h[1:, 1:]
    dx, dy = relief.dx_m, relief.dy_m
    # triangle (00, 01, 11) and triangle (00, 11, 10)
    sx = np.concatenate([((h01 - h00) / dx).ravel(), ((h11 - h10) / dx).ravel()])
    sy = np.concatenate([((h11 - h01) / dy).ravel(), ((h10 - h00) / dy).ravel()])
    ok = np.isfinite(sx) & np.isfinite(sy)
    return sx[ok], sy[ok]


class SlopeSet:
    """Facet slopes and the convex hull of the slope points (for exact rejection bounds)."""

    def __init__(self, sx: np.ndarray, sy: np.ndarray):
        self.sx = np.ascontiguousarray(sx, float)
        self.sy = np.ascontiguousarray(sy, float)
        if self.sx.size == 0:
            raise InputError("relief", "no valid facets (every triangle has an invalid corner)")
        pts = np.column_stack([self.sx, self.sy])
        try:
            hull = ConvexHull(pts)
            v = pts[hull.vertices]
        except (QhullError, ValueError):           # flat or collinear slopes: the bounding box bounds them
            v = np.array([[pts[:, 0].min(), pts[:, 1].min()], [pts[:, 0].min(), pts[:, 1].max()],
                          [pts[:, 0].max(), pts[:, 1].min()], [pts[:, 0].max(), pts[:, 1].max()]])
        self.hull = v                                # (H, 2)
        self.rms_slope = float(np.sqrt(np.mean(self.sx**2 + self.sy**2)))

    def cross_section(self, d: np.ndarray, sigma: np.ndarray, j: np.ndarray | None = None) -> np.ndarray:
        """sigma (d_x sx + d_y sy - d_z): relative cross-section of facet(s) j seen by rays d (or the hull max)."""
        if j is None:
            c = d[:, 0:1] * self.hull[None, :, 0] + d[:, 1:2] * self.hull[None, :, 1] - d[:, 2:3]
            return np.max(sigma[:, None] * c, axis=1)
        return sigma * (d[:, 0] * self.sx[j] + d[:, 1] * self.sy[j] - d[:, 2])


def _draw_facets(slopes: SlopeSet, d: np.ndarray, sigma: np.ndarray, rng, max_tries: int = 400,
                 same_direction: bool = False):
    """Facet index per ray by rejection; -1 where no facet faces the ray (or sampling gave up)."""
    n = d.shape[0]
    out = np.full(n, -1, np.int64)
    if same_direction:                   # first hit: one incident direction for the whole beam
        cmax = np.full(n, slopes.cross_section(d[:1], sigma[:1])[0])
    else:
        cmax = slopes.cross_section(d, sigma)
    todo = np.nonzero(cmax > 1e-15)[0]
    M = slopes.sx.size
    for _ in range(max_tries):
        if todo.size == 0:
            break
        j = rng.integers(0, M, size=todo.size)
        c = slopes.cross_section(d[todo], sigma[todo], j)
        acc = rng.random(todo.size) * cmax[todo] < c
        out[todo[acc]] = j[acc]
        todo = todo[~acc]
    return out


# ------------------------------------------------------------------ tracing


def _bin(d: np.ndarray, te_sin2: np.ndarray, pe: np.ndarray) -> np.ndarray:
    """Flat cell index (S * A) of exit directions, -1 outside the table's cells."""
    s2 = np.clip(1.0 - d[:, 2] ** 2, 0.0, 1.0)
    si = np.searchsorted(te_sin2, s2, side="right") - 1
    phi = np.degrees(np.arctan2(d[:, 1], d[:, 0]))
    phi = np.mod(phi - pe[0], 360.0) + pe[0]
    ai = np.searchsorted(pe, phi, side="right") - 1
    S, A = te_sin2.size - 1, pe.size - 1
    ok = (si >= 0) & (si < S) & (ai >= 0) & (ai < A)
    return np.where(ok, si * A + ai, -1)


def trace_normals(slopes: SlopeSet, wi: np.ndarray, n_a: complex, n_b: complex, n_rays: int, rng,
                  theta_edges_deg, phi_edges_deg, heuristic: str | None = None, max_bounces: int = 100,
                  specular_tol_rad: float = 1e-5, batch: int = 250_000) -> dict:
    """Trace `n_rays` paths arriving along wi (toward the source, z > 0, medium n_a above).

    Returns counts (2, S, A) of exits per cell (R above, T below), the delta-part counts,
    and the lost counts (absorbed, max_bounces, no_facet) and the mean number of facet
    events per path.  Vectorised over rays; the loop runs over bounce number.
    """
    te = np.asarray(theta_edges_deg, float)
    pe = np.asarray(phi_edges_deg, float)
    te_sin2 = np.sin(np.radians(te)) ** 2
    S, A = te.size - 1, pe.size - 1
    counts = np.zeros(2 * S * A)
    n_idx = (complex(n_a), complex(n_b))
    absorbing = (np.imag(n_a) > 0, np.imag(n_b) > 0)
    wi = np.asarray(wi, float)
    spec_R = np.array([-wi[0], -wi[1], wi[2]])
    wt, ok_t = refract(wi[None, :], np.array([[0.0, 0.0, 1.0]]), np.real(n_a) / np.real(n_b))
    spec_T = wt[0] if (bool(ok_t[0]) and not absorbing[1]) else None
    cos_tol = np.cos(specular_tol_rad)
    tally = {"specular_R": 0, "specular_T": 0, "absorbed": 0, "max_bounces": 0, "no_facet": 0, "events": 0}
    for lo in range(0, n_rays, batch):
        m = min(batch, n_rays - lo)
        d = np.tile(-wi, (m, 1))
        med = np.zeros(m, np.int8)                       # 0: incidence medium (above), 1: other (below)
        for bounce in range(max_bounces + 1):
            if d.shape[0] == 0:
                break
            sigma = np.where(med == 0, 1.0, -1.0)
            proper = sigma * d[:, 2] > 0                  # leaving the boundary in its own medium
            need = ~proper
            if heuristic and proper.any():
                cz = np.abs(d[proper, 2])
                p = (1.0 - smith_G1(cz, slopes.rms_slope, "beckmann")) if heuristic == "smith" else 1.0 - cz
                more = rng.random(cz.size) < p
                idx = np.nonzero(proper)[0][more]
                faces = slopes.cross_section(d[idx], sigma[idx]) > 1e-15
                need[idx[faces]] = True
            if bounce == max_bounces:
                tally["max_bounces"] += int(need.sum())
                need[:] = False
            leave = ~need
            if leave.any():
                dl, ml = d[leave], med[leave]
                for k in (0, 1):
                    sel = ml == k
                    if not sel.any():
                        continue
                    dk = dl[sel]
                    ref = spec_R if k == 0 else spec_T
                    if ref is not None:
                        sp = dk @ ref > cos_tol
                        tally["specular_R" if k == 0 else "specular_T"] += int(sp.sum())
                        dk = dk[~sp]
                    cells = _bin(dk, te_sin2, pe)
                    cells = cells[cells >= 0]
                    counts += np.bincount(cells + k * S * A, minlength=2 * S * A)
            d, med, sigma = d[need], med[need], sigma[need]
            if d.shape[0] == 0:
                break
            j = _draw_facets(slopes, d, sigma, rng, same_direction=bounce == 0)
            none = j < 0
            if none.any():
                tally["no_facet"] += int(none.sum())
                d, med, sigma, j = d[~none], med[~none], sigma[~none], j[~none]
            tally["events"] += d.shape[0]
            # facet normal facing the ray's medium
            nf = np.column_stack([-slopes.sx[j], -slopes.sy[j], np.ones(j.size)]) * sigma[:, None]
            nf /= np.linalg.norm(nf, axis=1, keepdims=True)
            cos_i = -np.einsum("ij,ij->i", d, nf)
            new_d = np.empty_like(d)
            new_med = med.copy()
            alive = np.ones(d.shape[0], bool)
            for k in (0, 1):
                sel = med == k
                if not sel.any():
                    continue
                n1, n2 = n_idx[k], n_idx[1 - k]
                F = fresnel_unpolarized(np.clip(cos_i[sel], 0.0, 1.0), n1, n2)
                refl = rng.random(F.size) < F
                ds, ns, cs = d[sel], nf[sel], cos_i[sel]
                out = ds + 2.0 * cs[:, None] * ns
                if absorbing[1 - k] and (~refl).any():
                    # transmitted into an absorbing medium (metal): absorbed, whatever Snell says
                    a = alive[sel]
                    a[~refl] = False
                    alive[sel] = a
                elif (~refl).any():
                    wt, ok = refract(-ds[~refl], ns[~refl], np.real(n1) / np.real(n2))
                    tmp = out[~refl]
                    tmp[ok] = wt[ok]                       # TIR (not ok) keeps the mirror direction
                    out[~refl] = tmp
                    moved = np.zeros(F.size, bool)
                    moved[np.nonzero(~refl)[0][ok]] = True
                    nm = new_med[sel]
                    nm[moved] = 1 - k
                    new_med[sel] = nm
                new_d[sel] = out
            tally["absorbed"] += int((~alive).sum())
            d, med = new_d[alive], new_med[alive]
            d /= np.linalg.norm(d, axis=1, keepdims=True)
    return {"counts": counts.reshape(2, S, A), "n_rays": int(n_rays), **tally,
            "events_per_path": tally["events"] / max(n_rays, 1)}


# ------------------------------------------------------------------ reconstruct


def _options(request) -> dict:
    o = dict(request.options or {})
    known = {"grazing_heuristic", "max_bounces", "specular_tol_rad", "batch"}
    unknown = set(o) - known - {"alpha", "distribution", "shadowing", "lobes", "weights", "polarized", "subsamples"}
    if unknown:
        raise RequestError(f"unknown normals option(s) {sorted(unknown)}; known: {sorted(known)}", "options")
    h = o.get("grazing_heuristic", None)
    if h in (None, False, "off", "none", ""):
        h = None
    elif h is True:
        h = "smith"
    elif h not in HEURISTICS:
        raise RequestError(f"grazing_heuristic must be off, smith or cosine, got {h!r}", "options.grazing_heuristic")
    mb = int(o.get("max_bounces", 100))
    if mb < 1:
        raise RequestError("max_bounces must be >= 1", "options.max_bounces")
    if o.get("polarized"):
        raise RequestError("the normals method is unpolarised (scalar Fresnel); use ray or microfacet for "
                           "Mueller tables", "options.polarized")
    return {"heuristic": h, "max_bounces": mb, "specular_tol_rad": float(o.get("specular_tol_rad", 1e-5)),
            "batch": int(o.get("batch", 250_000))}


def check_request(relief, material, request) -> dict:
    """Every reason to refuse, before any work."""
    request.validate()
    opts = _options(request)
    if relief is None:
        raise RequestError("the normals method needs a relief", "RELIEF")
    relief.require_valid()
    material.check_incidence(request.wavelengths_nm, request.incident_from)
    return opts


def _task(ctx: dict, task: tuple) -> dict:
    side_from, iw, ii, ip, key = task
    req = ctx["request"]
    wl = req.wavelengths_nm[iw]
    n_a, n_b = ctx["material"].n_pair(float(wl), side_from)
    slopes = ctx["slopes"][side_from]
    wi = direction(req.theta_i_deg[ii], req.phi_i_deg[ip])
    rng = task_rng(req.seed, *key)
    o = ctx["opts"]
    return trace_normals(slopes, wi, n_a, n_b, int(req.samples), rng, req.theta_s_edges_deg, req.phi_s_edges_deg,
                         o["heuristic"], o["max_bounces"], o["specular_tol_rad"], o["batch"])


def reconstruct(relief, material, request, progress=None) -> list[BsdfTable]:
    """Normal-density Monte Carlo tables for every side in `request.incident_from` (module doc).

    `request.samples` paths per incidence; options: grazing_heuristic (off | smith | cosine),
    max_bounces (100), specular_tol_rad (1e-5).  Seeds: task_rng(seed, side, w, i, p).
    """
    opts = check_request(relief, material, request)
    t0 = time.perf_counter()
    sx, sy = triangle_slopes(relief)
    if sx.size < MIN_FACETS:
        raise RequestError(f"relief {relief.source or ''} has only {sx.size} valid facets; a slope distribution "
                           f"needs at least {MIN_FACETS}", "RELIEF")
    slopes = {"outside": SlopeSet(sx, sy), "inside": SlopeSet(-sx, -sy)}
    ctx = {"request": request, "material": material, "opts": opts,
           "slopes": {k: v for k, v in slopes.items() if k in request.incident_from}}
    W, I, P = len(request.wavelengths_nm), len(request.theta_i_deg), len(request.phi_i_deg)
    tasks = [(sf, iw, ii, ip, ({"outside": 0, "inside": 1}[sf], iw, ii, ip))
             for sf in request.incident_from for iw in range(W) for ii in range(I) for ip in range(P)]
    res = map_tasks(_task, tasks, ctx, progress=progress, label="normals")
    te, pe = np.asarray(request.theta_s_edges_deg, float), np.asarray(request.phi_s_edges_deg, float)
    psa = projected_solid_angle(te, pe)
    N = float(request.samples)
    tables = []
    for sf in request.incident_from:
        vals = np.zeros((W, I, P, 2, te.size - 1, pe.size - 1))
        sig = np.zeros_like(vals)
        spR, spT, lost = np.zeros((W, I, P)), np.zeros((W, I, P)), np.zeros((W, I, P))
        detail = []
        for (tsf, iw, ii, ip, _), r in zip(tasks, res):
            if tsf != sf:
                continue
            vals[iw, ii, ip] = r["counts"] / (N * psa)
            sig[iw, ii, ip] = np.sqrt(r["counts"]) / (N * psa)
            spR[iw, ii, ip] = r["specular_R"] / N
            spT[iw, ii, ip] = r["specular_T"] / N
            lost[iw, ii, ip] = (r["absorbed"] + r["max_bounces"] + r["no_facet"]) / N
            detail.append({"wavelength_nm": float(request.wavelengths_nm[iw]),
                           "theta_i_deg": float(request.theta_i_deg[ii]), "phi_i_deg": float(request.phi_i_deg[ip]),
                           "absorbed": r["absorbed"] / N, "max_bounces": r["max_bounces"] / N,
                           "no_facet": r["no_facet"] / N, "events_per_path": r["events_per_path"]})
        desc = relief.describe()
        desc.update({"n_facets": int(sx.size), "rms_slope": slopes["outside"].rms_slope})
        tables.append(BsdfTable(request.wavelengths_nm, request.theta_i_deg, request.phi_i_deg, te, pe, vals,
                                incident_from=sf, specular_R=spR, specular_T=spT, lost=lost, sigma_per_sr=sig,
                                method="normals", material=material.describe(), relief=desc,
                                metadata={"model": "Monte Carlo on the density of facet normals (paper sec. 2.2)",
                                          "samples_per_incidence": int(request.samples), "seed": int(request.seed),
                                          "grazing_heuristic": opts["heuristic"] or "off",
                                          "max_bounces": opts["max_bounces"], "lost_detail": detail,
                                          "seconds": time.perf_counter() - t0}))
    return tables
