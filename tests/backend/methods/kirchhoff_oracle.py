"""TEST-ONLY oracle: scalar Kirchhoff by direct integration at every diffraction order.

For a periodic height map h (nx x ny pixels, pitch dx, dy) lit from direction w_i in medium n1,
every propagating order (p, q) has direction cosines a = (2 pi p / Lx - k1 a_i) / k_s,
b = (2 pi q / Ly - k1 b_i) / k_s and its own wave-vector transfer nu = k1 w_i + k_s w_s
(w_s = (a, b, +-sqrt(1 - a^2 - b^2)), + for R, - for T).  Its field is the Riemann sum of the
tangent-plane integral over the pixels,

    U_pq = (1 / N) sum_r exp(-i (nu_x x + nu_y y + nu_z h(x, y))),

evaluated here term by term with that order's own nu_z (no FFT, no expansion), and its power
fraction is |U_pq|^2 K F_loc with the obliquity K = |w_i.m| |w_s.m| |nu|^2 / (nu_z^2 cos t_i cos t_s)
and the Fresnel factor of the stationary-phase facet m = nu / |nu| (R: F; T: 1 - F where w_i and
w_s lie on opposite sides of m, else 0).  The specular order's coherent part |<exp(-i nu_z h)>|^2
is that order's U; the oracle reports the total of each order (coherent + diffuse).

Deliberately slow and simple: a check of methods.kirchhoff, never used by the package.
"""
from __future__ import annotations

import numpy as np

from relief_bsdf.core.fresnel import fresnel_reflectance


def direct_orders(h_m: np.ndarray, pitch_m: float, wavelength_nm: float, theta_i_deg: float, n1: float,
                  n2: float, side: str, chunk: int = 32) -> dict:
    """alpha, beta, power (coherent + diffuse) of every propagating order of one side."""
    ny, nx = h_m.shape
    Lx, Ly = nx * pitch_m, ny * pitch_m
    k0 = 2 * np.pi / (wavelength_nm * 1e-9)
    k1, ks = k0 * n1, k0 * (n1 if side == "R" else n2)
    ti = np.radians(theta_i_deg)
    wi = np.array([np.sin(ti), 0.0, np.cos(ti)])
    p = np.arange(-(nx // 2), nx - nx // 2)
    q = np.arange(-(ny // 2), ny - ny // 2)
    P, Q = np.meshgrid(p, q)
    a = (2 * np.pi * P / Lx - k1 * wi[0]) / ks
    b = (2 * np.pi * Q / Ly - k1 * wi[1]) / ks
    prop = a * a + b * b < 1.0
    a, b = a[prop], b[prop]
    cs = np.sqrt(1.0 - a * a - b * b)
    sgn = 1.0 if side == "R" else -1.0
    ws = np.stack([a, b, sgn * cs], axis=-1)
    nu = k1 * wi[None, :] + ks * ws
    x = np.arange(nx) * pitch_m
    y = np.arange(ny) * pitch_m
    U = np.empty(a.size, complex)
    for s in range(0, a.size, chunk):
        sl = slice(s, s + chunk)
        ex = np.exp(-1j * nu[sl, 0, None] * x[None, :])                      # (K, nx)
        ey = np.exp(-1j * nu[sl, 1, None] * y[None, :])                      # (K, ny)
        eh = np.exp(-1j * nu[sl, 2, None, None] * h_m[None, :, :])          # (K, ny, nx)
        U[sl] = np.einsum("kyx,kx,ky->k", eh, ex, ey) / (nx * ny)
    m = nu / np.linalg.norm(nu, axis=-1, keepdims=True)
    im = m @ wi
    sm = np.sum(m * ws, axis=-1)
    K = np.abs(im) * np.abs(sm) * np.sum(nu * nu, axis=-1) / (nu[:, 2] ** 2 * wi[2] * cs)
    F = fresnel_reflectance(np.abs(im), n1, n2, "unpolarized")
    fac = K * F if side == "R" else np.where(im * sm < 0, K * (1.0 - F), 0.0)
    return {"alpha": a, "beta": b, "power": np.abs(U) ** 2 * fac}


def bin_orders(alpha, beta, power, theta_edges_deg, phi_edges_deg) -> np.ndarray:
    """Power of the orders summed into (theta, phi) cells (phi edges may start below 0)."""
    th = np.degrees(np.arcsin(np.clip(np.hypot(alpha, beta), 0, 1)))
    ph = np.degrees(np.arctan2(beta, alpha)) % 360.0
    pe = np.asarray(phi_edges_deg, float)
    ph = np.where(ph >= pe[-1], ph - 360.0, ph)
    ph = np.where(ph < pe[0], ph + 360.0, ph)
    out, _, _ = np.histogram2d(th, ph, bins=[np.asarray(theta_edges_deg, float), pe], weights=power)
    return out
