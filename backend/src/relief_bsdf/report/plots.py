"""Reusable BSDF plots (matplotlib, Agg backend, PNG written atomically).

- `plot_in_plane(ax, table, side, style=CurveStyle(...))`: in-plane BSDF curves, one per incidence angle, against
  the signed scatter angle (negative: the phi_i + 180 half-plane, where the specular /
  undeviated direction lies), log scale, like the paper's figures 4 and 9.  Several tables
  can be overlaid on one axis (e.g. a measurement and a simulation with `linestyle`).
- `plot_polar_map(ax, table, side, ii)`: the whole scatter hemisphere of one incidence as
  a polar map of log10 f (radius theta_s, angle phi_s).
- `table_figure(table)`: both together for one table; `save_figure(fig, path)`.
Delta parts (specular_R/T) are not curves; they are listed in the legend text.
"""
from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
from matplotlib.colors import LogNorm  # noqa: E402

from relief_bsdf.io.atomic import atomic_path  # noqa: E402
from relief_bsdf.bsdf.table import BsdfTable  # noqa: E402

SIDE_NAME = {"R": "reflection (BRDF)", "T": "transmission (BTDF)"}


def _floor(values: np.ndarray) -> float:
    pos = values[values > 0]
    return float(pos.max() * 1e-6) if pos.size else 1e-6


@dataclass(frozen=True)
class CurveStyle:
    """How one table's in-plane curves are drawn: line style, a label prefix (e.g. the method),
    one colour per incidence (None: viridis), and whether the legend lists the delta parts."""

    linestyle: str = "-"
    label_prefix: str = ""
    colors: tuple | None = None
    show_specular: bool = True


def plot_in_plane(ax, table: BsdfTable, side: str, iw: int = 0, ip: int = 0, style: CurveStyle = CurveStyle()):
    """In-plane curves of `table` for every incidence angle on `ax` (log y); returns the lines."""
    ang, vals = table.in_plane(side, iw, ip)
    cmap = plt.get_cmap("viridis")
    n = len(table.theta_i_deg)
    lines = []
    floor = _floor(vals)
    spec = table.specular_R if side == "R" else table.specular_T
    for k, ti in enumerate(table.theta_i_deg):
        c = style.colors[k] if style.colors is not None else cmap(k / max(n - 1, 1))
        v = np.where(vals[k] > floor, vals[k], np.nan)
        lab = f"{style.label_prefix}{ti:g} deg"
        if style.show_specular and spec[iw, k, ip] > 0:
            lab += f" (+ delta {spec[iw, k, ip]:.3g})"
        lines += ax.plot(ang, v, linestyle=style.linestyle, color=c, label=lab)
    ax.set_yscale("log")
    ax.set_xlim(-90, 90)
    ax.set_xlabel("signed theta_s (deg); < 0: phi_i + 180 half-plane")
    ax.set_ylabel("BSDF (1/sr)")
    wl = table.wavelength_nm[iw]
    ax.set_title(f"{SIDE_NAME.get(side, side)}\nlight from {table.incident_from}, {wl:g} nm", fontsize=9)
    ax.grid(True, which="both", alpha=0.3)
    return lines


def plot_polar_map(ax, table: BsdfTable, side: str, ii: int, iw: int = 0, ip: int = 0, vmin: float | None = None,
                   vmax: float | None = None):
    """Polar map of the cell values for incidence ii on a polar `ax`; returns the mesh artist."""
    k = 0 if side == "R" else 1
    v = table.values_per_sr[iw, ii, ip, k]
    te = table.theta_s_edges_deg
    pe = np.radians(table.phi_s_edges_deg)
    pos = v[v > 0]
    vmax = vmax if vmax is not None else (float(pos.max()) if pos.size else 1.0)
    vmin = vmin if vmin is not None else max(vmax * 1e-5, float(pos.min()) if pos.size else vmax * 1e-5)
    P, T = np.meshgrid(pe, te)
    mesh = ax.pcolormesh(P, T, np.where(v > 0, v, np.nan), norm=LogNorm(vmin=vmin, vmax=vmax), cmap="magma",
                         shading="flat")
    ax.set_ylim(0, te[-1])
    ax.set_yticks([30, 60, 90])
    ax.set_yticklabels(["30", "60", "90"], fontsize=6)
    ax.tick_params(axis="x", labelsize=6)
    ax.set_title(f"{side}, theta_i {table.theta_i_deg[ii]:g}", fontsize=8, pad=14)
    return mesh


def table_figure(table: BsdfTable, sides=("R", "T"), iw: int = 0, ip: int = 0, max_maps: int = 6):
    """A figure with the in-plane curves per side (top) and polar maps per incidence (below)."""
    sides = list(sides)
    I = len(table.theta_i_deg)
    pick = np.unique(np.linspace(0, I - 1, min(I, max_maps)).round().astype(int))
    ncol = max(len(pick), 2)
    fig = plt.figure(figsize=(max(3.0 * ncol, 6.5 * len(sides)), 4.6 + 2.8 * len(sides)))
    gs = fig.add_gridspec(1 + len(sides), 1, height_ratios=[1.7] + [1.0] * len(sides), hspace=0.5)
    top = gs[0].subgridspec(1, len(sides), wspace=0.3)
    for s, side in enumerate(sides):
        ax = fig.add_subplot(top[0, s])
        plot_in_plane(ax, table, side, iw, ip)
        ax.legend(fontsize=7, title="theta_i", title_fontsize=7)
        row = gs[1 + s].subgridspec(1, ncol)
        for j, ii in enumerate(pick):
            pax = fig.add_subplot(row[0, j], projection="polar")
            mesh = plot_polar_map(pax, table, side, int(ii), iw, ip)
        fig.colorbar(mesh, ax=pax, fraction=0.046, pad=0.12).ax.tick_params(labelsize=6)
    h = table.hemispherical()
    fig.suptitle(f"method {table.method}: R = {np.round(h['R'][iw, :, ip], 4).tolist()}, "
                 f"T = {np.round(h['T'][iw, :, ip], 4).tolist()}", fontsize=8)
    return fig


def compare_figure(tables: list, labels: list, sides=("R", "T"), iw: int = 0, ip: int = 0):
    """In-plane curves of several tables overlaid (one line style per table, one colour per incidence).

    Tables are matched by incidence angle index; e.g. `ray`, `normals` and `microfacet` tables of
    one relief, or a simulation against a measurement converted to a table.
    """
    styles = ["-", "--", ":", "-."]
    sides = list(sides)
    fig, axs = plt.subplots(1, len(sides), figsize=(6.5 * len(sides), 5.0), squeeze=False)
    for s, side in enumerate(sides):
        ax = axs[0, s]
        for k, (t, lab) in enumerate(zip(tables, labels)):
            style = CurveStyle(linestyle=styles[k % len(styles)], label_prefix=f"{lab} ", show_specular=False)
            plot_in_plane(ax, t.select(tables[0].wavelength_nm[iw]), side, 0, ip, style)
        ax.legend(fontsize=6, ncol=len(tables))
    fig.suptitle(" vs ".join(f"{lab} ({st})" for lab, st in zip(labels, styles * 4)), fontsize=9)
    return fig


def save_figure(fig, path: str | Path, dpi: int = 110) -> Path:
    """Write `fig` to `path` (PNG) atomically and close it."""
    path = Path(path)
    with atomic_path(path) as tmp:
        fig.savefig(tmp, dpi=dpi, format=path.suffix.lstrip(".").lower() or "png")
    plt.close(fig)
    return path
