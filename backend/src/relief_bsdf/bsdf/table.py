"""`BsdfTable`: a tabulated 5-D BSDF of one boundary for light arriving from one side.

Axes (formats.md frame): wavelength_nm, theta_i_deg, phi_i_deg, side (R, T),
theta_s_deg, phi_s_deg.  `values_per_sr[w, i, p, k, s, a]` is the Nicodemus BSDF
in 1/sr, averaged over the scatter cell (s, a) in projected solid angle
cos(theta) d omega.  Cells are given by their edges; the projected solid angle of
cell (s, a) is

    Omega_proj = (sin^2 theta_hi - sin^2 theta_lo) / 2 * (phi_hi - phi_lo)

so the directional-hemispherical reflectance is exactly sum(f * Omega_proj) over
the R cells (plus the delta-like specular part, which is kept apart in
`specular_R`, not smeared into a cell).  Same for transmittance with the T cells.

Transmission values are radiance BTDFs (formats.md): f(a->b)/n_b^2 = f(b->a)/n_a^2.

Polarisation (optional): `mueller_per_sr[w, i, p, k, s, a]` is a 4x4 Mueller matrix
per cell with element [0, 0] equal to `values_per_sr`.  Stokes vectors
(S0, S1 = I_s - I_p, S2, S3) are referred to the s/p basis of the plane that holds
the direction and the macroscopic normal z: for the incident light the plane of
(w_i, z), for the scattered light the plane of (w_s, z), with s = z x w / |z x w|
(for w along z, s = (-sin phi, cos phi, 0) from the cell's azimuth), and
p = s x k with k the propagation direction of the light (k = -w_i before the
interaction, k = w_s after it), so (s, p, k) is right-handed.  `specular_mueller_R/T`
(W, I, P, 4, 4) do the same for the delta parts.  A plate model that tracks Stokes
vectors through both faces uses these; an unpolarised table leaves them None.

`incident_from` says where the light comes from: "outside" (the lit medium, usually
air) or "inside" (the dielectric).  For "inside" the frame is mirrored so +z points
into the medium of incidence; R stays in that medium, T crosses the boundary.
"""
from __future__ import annotations

from dataclasses import dataclass, field, replace
from typing import Any

import numpy as np

from relief_bsdf.core.frames import projected_solid_angle
from relief_bsdf.errors import InputError

SIDES = ("R", "T")
ROW_ARRAYS = ("values_per_sr", "specular_R", "specular_T", "lost", "sigma_per_sr", "mueller_per_sr",
              "specular_mueller_R", "specular_mueller_T")   # every array whose leading axes are (W, I, P)


def _edges_from_centres(c: np.ndarray, lo: float, hi: float) -> np.ndarray:
    c = np.asarray(c, float)
    if c.size == 1:
        return np.array([lo, hi])
    mid = 0.5 * (c[1:] + c[:-1])
    return np.concatenate([[max(lo, c[0] - (mid[0] - c[0]))], mid, [min(hi, c[-1] + (c[-1] - mid[-1]))]])


@dataclass
class BsdfTable:
    """Tabulated BSDF of one boundary, light arriving from one side (see module doc)."""

    wavelength_nm: np.ndarray
    theta_i_deg: np.ndarray
    phi_i_deg: np.ndarray
    theta_s_edges_deg: np.ndarray
    phi_s_edges_deg: np.ndarray
    values_per_sr: np.ndarray                       # (W, I, P, 2, S, A)
    incident_from: str = "outside"
    specular_R: np.ndarray | None = None            # (W, I, P) power fraction, delta part
    specular_T: np.ndarray | None = None            # (W, I, P)
    lost: np.ndarray | None = None                  # (W, I, P) absorbed / unaccounted
    sigma_per_sr: np.ndarray | None = None          # like values: 1-sigma (Monte-Carlo) error
    mueller_per_sr: np.ndarray | None = None        # (W, I, P, 2, S, A, 4, 4), see module doc
    specular_mueller_R: np.ndarray | None = None    # (W, I, P, 4, 4)
    specular_mueller_T: np.ndarray | None = None    # (W, I, P, 4, 4)
    method: str = "unknown"
    material: dict = field(default_factory=dict)    # Material.describe()
    relief: dict = field(default_factory=dict)      # relief statistics and provenance
    metadata: dict = field(default_factory=dict)    # request, versions, timings, notes

    def __post_init__(self) -> None:
        self.wavelength_nm = np.atleast_1d(np.asarray(self.wavelength_nm, float))
        self.theta_i_deg = np.atleast_1d(np.asarray(self.theta_i_deg, float))
        self.phi_i_deg = np.atleast_1d(np.asarray(self.phi_i_deg, float))
        self.theta_s_edges_deg = np.asarray(self.theta_s_edges_deg, float)
        self.phi_s_edges_deg = np.asarray(self.phi_s_edges_deg, float)
        shape = self.shape_expected
        self.values_per_sr = np.asarray(self.values_per_sr)
        if self.values_per_sr.shape != shape:
            raise InputError("BsdfTable", f"values have shape {self.values_per_sr.shape}, axes need {shape}")
        if self.incident_from not in ("outside", "inside"):
            raise InputError("BsdfTable", f"incident_from must be outside or inside, got {self.incident_from!r}")
        w = shape[:3]
        for name in ("specular_R", "specular_T", "lost"):
            v = getattr(self, name)
            setattr(self, name, np.zeros(w) if v is None else np.broadcast_to(np.asarray(v, float), w).copy())
        if self.sigma_per_sr is not None and np.shape(self.sigma_per_sr) != shape:
            raise InputError("BsdfTable", "sigma_per_sr must have the shape of values_per_sr")
        if self.mueller_per_sr is not None and np.shape(self.mueller_per_sr) != shape + (4, 4):
            raise InputError("BsdfTable", "mueller_per_sr must have shape values.shape + (4, 4)")
        for name in ("specular_mueller_R", "specular_mueller_T"):
            v = getattr(self, name)
            if v is not None and np.shape(v) != w + (4, 4):
                raise InputError("BsdfTable", f"{name} must have shape {w + (4, 4)}")

    @property
    def is_polarized(self) -> bool:
        return self.mueller_per_sr is not None

    # ----------------------------------------------------------------- axes
    @property
    def shape_expected(self) -> tuple:
        return (self.wavelength_nm.size, self.theta_i_deg.size, self.phi_i_deg.size, 2,
                self.theta_s_edges_deg.size - 1, self.phi_s_edges_deg.size - 1)

    @property
    def theta_s_deg(self) -> np.ndarray:
        e = self.theta_s_edges_deg
        return 0.5 * (e[1:] + e[:-1])

    @property
    def phi_s_deg(self) -> np.ndarray:
        e = self.phi_s_edges_deg
        return 0.5 * (e[1:] + e[:-1])

    @property
    def projected_solid_angle_sr(self) -> np.ndarray:
        return projected_solid_angle(self.theta_s_edges_deg, self.phi_s_edges_deg)

    @property
    def is_isotropic(self) -> bool:
        """One incidence azimuth: the boundary is taken to be isotropic (rotation invariant)."""
        return self.phi_i_deg.size == 1

    # ----------------------------------------------------------------- integrals
    def hemispherical(self) -> dict[str, np.ndarray]:
        """Directional-hemispherical integrals per incidence, each (W, I, P).

        R, T: total reflectance / transmittance (diffuse cells + specular part);
        diffuse_R, diffuse_T: the tabulated cells only; specular_R/T; lost.
        """
        psa = self.projected_solid_angle_sr
        d = np.einsum("wipksa,sa->wipk", self.values_per_sr.astype(float), psa)
        return {"R": d[..., 0] + self.specular_R, "T": d[..., 1] + self.specular_T,
                "diffuse_R": d[..., 0], "diffuse_T": d[..., 1],
                "specular_R": self.specular_R, "specular_T": self.specular_T, "lost": self.lost}

    def albedo_rows(self) -> list[dict]:
        """Per-incidence integrals as the list `relief info --json` prints (formats.md)."""
        h = self.hemispherical()
        rows = []
        for w, wl in enumerate(self.wavelength_nm):
            for i, ti in enumerate(self.theta_i_deg):
                for p, pi in enumerate(self.phi_i_deg):
                    rows.append({"wavelength_nm": float(wl), "theta_i_deg": float(ti), "phi_i_deg": float(pi),
                                 "from": self.incident_from, "R": float(h["R"][w, i, p]),
                                 "T": float(h["T"][w, i, p]), "specular_R": float(h["specular_R"][w, i, p]),
                                 "specular_T": float(h["specular_T"][w, i, p]), "lost": float(h["lost"][w, i, p])})
        return rows

    # ----------------------------------------------------------------- evaluation
    def eval(self, wavelength_nm: Any, theta_i_deg: Any, phi_i_deg: Any, side: Any,
             theta_s_deg: Any, phi_s_deg: Any) -> np.ndarray:
        """BSDF (1/sr) at arbitrary directions by multilinear interpolation between cell centres.

        All arguments broadcast together; `side` is 'R'/'T' (or 0/1).  Azimuths are periodic.
        Outside the tabulated theta range values are held at the nearest centre (no
        extrapolation).  An isotropic table (one phi_i) is rotated: f(phi_i, phi_s) =
        f(phi_i0, phi_s - phi_i + phi_i0).  The specular delta part is not included.
        """
        wl, ti, pi, sd, ts, ps = np.broadcast_arrays(
            np.asarray(wavelength_nm, float), np.asarray(theta_i_deg, float), np.asarray(phi_i_deg, float),
            _side_index(side), np.asarray(theta_s_deg, float), np.asarray(phi_s_deg, float))
        if self.is_isotropic:
            ps = ps - pi + self.phi_i_deg[0]
            pi = np.full_like(pi, self.phi_i_deg[0])
        axes = [
            linear_weights(self.wavelength_nm, wl),
            linear_weights(self.theta_i_deg, ti),
            periodic_weights(self.phi_i_deg, pi),
            linear_weights(self.theta_s_deg, ts),
            periodic_weights(self.phi_s_deg, ps),
        ]
        out = np.zeros(wl.shape)
        v = self.values_per_sr
        for corner in range(32):
            idx = []
            wgt = np.ones(wl.shape)
            for k, (i0, i1, f) in enumerate(axes):
                hi = (corner >> k) & 1
                idx.append(i1 if hi else i0)
                wgt = wgt * (f if hi else 1.0 - f)
            out += wgt * v[idx[0], idx[1], idx[2], sd, idx[3], idx[4]]
        return out

    def in_plane(self, side: str, iw: int = 0, ip: int = 0) -> tuple[np.ndarray, np.ndarray]:
        """In-plane curves: (signed scatter angle in degrees, values (I, n)).

        Negative angles are the phi_s = phi_i + 180 half-plane (the specular side for R,
        the undeviated side for T), positive ones the phi_s = phi_i half-plane, like the
        paper's figures 4 and 9.
        """
        ts = self.theta_s_deg
        phi0 = self.phi_i_deg[ip]
        ang = np.concatenate([-ts[::-1], ts])
        vals = []
        for ti in self.theta_i_deg:
            back = self.eval(self.wavelength_nm[iw], ti, phi0, side, ts[::-1], phi0 + 180.0)
            fwd = self.eval(self.wavelength_nm[iw], ti, phi0, side, ts, phi0)
            vals.append(np.concatenate([back, fwd]))
        return ang, np.asarray(vals)

    def select(self, wavelength_nm: float | None = None) -> "BsdfTable":
        """A copy restricted to the tabulated wavelength nearest to `wavelength_nm`."""
        if wavelength_nm is None:
            return self
        k = int(np.argmin(np.abs(self.wavelength_nm - wavelength_nm)))
        return self.at_wavelengths(self.wavelength_nm[k:k + 1], [k])

    def at_wavelengths(self, wavelength_nm: Any, rows: Any) -> "BsdfTable":
        """This table's wavelength rows `rows` (indices) relabelled as the wavelengths `wavelength_nm`: the
        tables of a method whose physics sees the wavelength only through the refractive indices
        (geometric optics, `MethodEntry.wavelength_free`) at wavelengths where the indices are the same
        are one table (plate.faces: traced once)."""
        idx = np.asarray(rows, int)
        cut = {n: (None if getattr(self, n) is None else np.take(getattr(self, n), idx, axis=0)) for n in ROW_ARRAYS}
        return replace(self, wavelength_nm=np.asarray(wavelength_nm, float), **cut)

    def same_at(self, a_nm: float, b_nm: float) -> bool:
        """Whether both wavelengths are on the table's axis with the same numbers in every array."""
        w = self.wavelength_nm
        ia, ib = np.nonzero(w == a_nm)[0], np.nonzero(w == b_nm)[0]
        if not ia.size or not ib.size:
            return False
        return all(getattr(self, n) is None or np.array_equal(getattr(self, n)[ia[0]], getattr(self, n)[ib[0]])
                   for n in ROW_ARRAYS)

    def summary(self) -> dict:
        return {"kind": "bsdf", "method": self.method, "from": self.incident_from,
                "wavelength_nm": self.wavelength_nm.tolist(), "theta_i_deg": self.theta_i_deg.tolist(),
                "phi_i_deg": self.phi_i_deg.tolist(), "theta_s_cells": int(self.theta_s_edges_deg.size - 1),
                "phi_s_cells": int(self.phi_s_edges_deg.size - 1), "material": self.material,
                "relief": self.relief, "albedo": self.albedo_rows()}


def _side_index(side: Any) -> np.ndarray:
    s = np.asarray(side)
    if s.dtype.kind in "iu":
        return s.astype(int)
    return np.where(s == "T", 1, 0) if s.dtype.kind in "US" else s.astype(int)


def linear_weights(grid: np.ndarray, x: np.ndarray):
    """Indices (i0, i1) and weight f of x between grid[i0] and grid[i1]; clamped at the ends: linear
    interpolation weights 1 - f and f (the project's one table interpolation: `BsdfTable.eval`, the plate's
    resampling of its tables, `interpolation_matrix`)."""
    n = grid.size
    if n == 1:
        z = np.zeros(x.shape, int)
        return z, z, np.zeros(x.shape)
    xc = np.clip(x, grid[0], grid[-1])
    i1 = np.clip(np.searchsorted(grid, xc, side="right"), 1, n - 1)
    i0 = i1 - 1
    f = (xc - grid[i0]) / (grid[i1] - grid[i0])
    return i0, i1, np.clip(f, 0.0, 1.0)


def periodic_weights(grid: np.ndarray, x: np.ndarray):
    """Like linear_weights for a periodic (360 degree) axis."""
    n = grid.size
    if n == 1:
        z = np.zeros(x.shape, int)
        return z, z, np.zeros(x.shape)
    g0 = grid[0]
    xr = np.mod(x - g0, 360.0) + g0
    ext = np.concatenate([grid, [grid[0] + 360.0]])
    i1 = np.clip(np.searchsorted(ext, xr, side="right"), 1, n)
    i0 = i1 - 1
    f = (xr - ext[i0]) / (ext[i1] - ext[i0])
    return i0 % n, i1 % n, np.clip(f, 0.0, 1.0)


def interpolation_matrix(grid: Any, x: Any, periodic: bool = False) -> np.ndarray:
    """(len(x), len(grid)) weights of `linear_weights` (`periodic_weights` on a 360-degree axis) as a
    matrix: row k interpolates the values on `grid` at x[k]."""
    grid = np.asarray(grid, float)
    x = np.atleast_1d(np.asarray(x, float))
    W = np.zeros((x.size, grid.size))
    if grid.size == 1:
        W[:, 0] = 1.0
        return W
    i0, i1, f = (periodic_weights if periodic else linear_weights)(grid, x)
    r = np.arange(x.size)
    if periodic:
        np.add.at(W, (r, i0), 1.0 - f)
        np.add.at(W, (r, i1), f)
    else:
        W[r, i0] += 1.0 - f
        W[r, i1] += f
    return W


def reciprocity_error(table: BsdfTable, other: BsdfTable | None = None, n_a: float = 1.0, n_b: float = 1.0,
                      side: str = "R", iw: int = 0) -> dict:
    """Helmholtz reciprocity check on the incidence grid.

    side 'R': f_R(i -> o) = f_R(o -> i) within one table.
    side 'T': `table` is light from medium a (index n_a) and `other` from medium b;
    radiance BTDFs obey f_T^a(i -> o) / n_b^2 = f_T^b(o -> i) / n_a^2  (formats.md),
    where the transmitted direction o seen from b's frame is the incidence there.
    Pairs are taken from the theta_i grid in the plane of incidence: the forward path goes
    from (a, phi=0) to (b, phi=180); the reverse path from (b, 180) to (a, 0).  Both frames
    keep x and y (the inside frame only flips z), so this pairing is exact for anisotropic
    tables too, not only rotation-invariant ones.  Returns the pairs and the largest
    relative deviation.
    """
    other = table if other is None else other
    th = table.theta_i_deg
    wl = table.wavelength_nm[iw]
    rows = []
    for a in th:
        for b in other.theta_i_deg:
            if side == "R" and b <= a:
                continue
            f_ab = float(table.eval(wl, a, 0.0, side, b, 180.0))
            f_ba = float(other.eval(wl, b, 180.0, side, a, 0.0))
            if side == "T":
                f_ab, f_ba = f_ab / n_b**2, f_ba / n_a**2
            mean = 0.5 * (f_ab + f_ba)
            rel = abs(f_ab - f_ba) / mean if mean > 0 else 0.0
            rows.append({"theta_a_deg": float(a), "theta_b_deg": float(b), "f_ab": f_ab, "f_ba": f_ba, "rel": rel})
    return {"pairs": rows, "max_rel": max((r["rel"] for r in rows), default=0.0)}
