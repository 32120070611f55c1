"""Reusable BSDF plots (matplotlib, Agg backend, PNG written atomically).

- `plot_in_plane(ax, table, side, style=CurveStyle(...))`: in-plane BSDF curves, one per incidence
  angle, against the signed scatter angle (negative: the phi_i + 180 half-plane, where the
  specular / refracted direction lies), log scale, like the paper's figures 4 and 9.  Several
  tables can be overlaid on one axis; `theta_i_deg` evaluates a table at another table's
  incidence angles (`BsdfTable.eval` interpolates), so a Klems file can be laid over a fine table.
  The delta parts (specular_R/T, a power fraction, not a curve) are marked by a triangle at the
  mirror / refracted direction, labelled with their power.
- `plot_polar_map(ax, table, side, ii)`: the scatter hemisphere of one incidence as a polar map
  of f (log colour scale; radius theta_s, angle phi_s).
- `table_figure(table)`: both together for one table; `compare_figure(tables, labels)`;
  `save_figure(fig, path)`.
"""
from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
from matplotlib.colors import LogNorm  # noqa: E402

from relief_bsdf.bsdf.table import BsdfTable  # noqa: E402
from relief_bsdf.errors import InputError  # noqa: E402
from relief_bsdf.io.atomic import atomic_path  # noqa: E402

SIDE_NAME = {"R": "reflection (BRDF)", "T": "transmission (BTDF)"}
BSDF_LABEL = "BSDF f (1/sr, not cosine-corrected)"
SIGNED_LABEL = "signed scatter angle theta_s (deg)\n< 0: phi_i + 180 half-plane (specular side)"


def _floor(values: np.ndarray) -> float:
    pos = values[np.isfinite(values) & (values > 0)]
    return float(pos.max() * 1e-6) if pos.size else 1e-6


def sides_with_data(tables: list, sides) -> list:
    """The sides (R, T) on which some table has a value or a delta part above zero: a BTDF-only file
    gets no empty reflection panel (all of `sides` when none has data, so a figure is never empty)."""
    def has(t: BsdfTable, side: str) -> bool:
        k = 0 if side == "R" else 1
        spec = t.specular_R if side == "R" else t.specular_T
        return bool(np.any(np.asarray(t.values_per_sr[..., k]) > 0) or np.any(np.asarray(spec) > 0))
    keep = [sd for sd in sides if any(has(t, sd) for t in tables)]
    return keep or list(sides)


@dataclass(frozen=True)
class CurveStyle:
    """How one table's in-plane curves are drawn: line style, a label prefix (e.g. the method),
    one colour per incidence (None: viridis), and whether the delta parts are marked."""

    linestyle: str = "-"
    label_prefix: str = ""
    colors: tuple | None = None
    show_specular: bool = True


def delta_angles_deg(table: BsdfTable, side: str, theta_i_deg: np.ndarray, iw: int = 0) -> np.ndarray:
    """Polar angle of the delta part's direction: the mirror (R) or the refracted direction (T;
    the undeviated one when the table does not state its indices); NaN past the critical angle."""
    th = np.asarray(theta_i_deg, float)
    if side == "R":
        return th
    from relief_bsdf.io.isbsdf import refracted_theta_deg, table_indices
    try:
        return refracted_theta_deg(th, *table_indices(table, iw), past_critical=np.nan)
    except (InputError, KeyError, TypeError, ValueError):
        return th


def _in_plane(table: BsdfTable, side: str, theta_i: np.ndarray, iw: int, ip: int) -> tuple[np.ndarray, np.ndarray]:
    ts = table.theta_s_deg
    phi0 = table.phi_i_deg[ip]
    wl = table.wavelength_nm[iw]
    ang = np.concatenate([-ts[::-1], ts])
    vals = np.stack([np.concatenate([table.eval(wl, t, phi0, side, ts[::-1], phi0 + 180.0),
                                     table.eval(wl, t, phi0, side, ts, phi0)]) for t in theta_i])
    return ang, vals


def plot_in_plane(ax, table: BsdfTable, side: str, iw: int = 0, ip: int = 0, style: CurveStyle = CurveStyle(),
                  theta_i_deg=None):
    """In-plane curves of `table` for every incidence angle (or those given) on `ax` (log y); returns the lines."""
    theta_i = table.theta_i_deg if theta_i_deg is None else np.atleast_1d(np.asarray(theta_i_deg, float))
    ang, vals = _in_plane(table, side, theta_i, iw, ip)
    cmap = plt.get_cmap("viridis")
    n = len(theta_i)
    lines = []
    floor = _floor(vals)
    spec_tab = (table.specular_R if side == "R" else table.specular_T)[iw, :, ip]
    spec = np.interp(theta_i, table.theta_i_deg, spec_tab) if table.theta_i_deg.size > 1 else np.full(n, spec_tab[0])
    where = delta_angles_deg(table, side, theta_i, iw)
    top = float(np.nanmax(vals)) if np.any(np.isfinite(vals)) else 1.0
    for k, ti in enumerate(theta_i):
        c = style.colors[k] if style.colors is not None else cmap(k / max(n - 1, 1))
        v = np.where(vals[k] > floor, vals[k], np.nan)
        lab = f"{style.label_prefix}{ti:g} deg"
        if style.show_specular and spec[k] > 0 and np.isfinite(where[k]):
            lab += f" (delta {spec[k]:.3g} at theta_s {where[k]:.0f})"
            ax.plot([-where[k]], [top * 2.0], marker="v", color=c, markersize=7, linestyle="none")
            ax.axvline(-where[k], color=c, linestyle=":", linewidth=0.8)
        lines += ax.plot(ang, v, linestyle=style.linestyle, color=c, label=lab)
    ax.set_yscale("log")
    ax.set_xlim(-90, 90)
    ax.set_xlabel(SIGNED_LABEL, fontsize=8)
    ax.set_ylabel(BSDF_LABEL, fontsize=8)
    wl = table.wavelength_nm[iw]
    ax.set_title(f"{SIDE_NAME.get(side, side)}, light from {table.incident_from}, {wl:g} nm\n"
                 "triangles: delta (specular) parts, power fraction in the legend", fontsize=8)
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
    ax.set_xticks(np.radians([0, 90, 180, 270]))
    ax.set_xticklabels(["0", "90", "180", "270"], fontsize=6)
    ax.set_title(f"{side}, theta_i = {table.theta_i_deg[ii]:g} deg", fontsize=8, pad=16)
    return mesh


def table_figure(table: BsdfTable, sides=("R", "T"), iw: int = 0, ip: int = 0, max_maps: int = 5):
    """A figure with the in-plane curves per side (top) and polar maps per incidence (below),
    one shared, labelled log colour bar per side; a side the table has no data on is left out."""
    sides = sides_with_data([table], sides)
    I = len(table.theta_i_deg)
    pick = np.unique(np.linspace(0, I - 1, min(I, max_maps)).round().astype(int))
    ncol = max(len(pick), 2)
    fig = plt.figure(figsize=(max(3.2 * ncol + 1.2, 7.0 * len(sides)), 5.2 + 3.4 * len(sides)))
    gs = fig.add_gridspec(1 + len(sides), 1, height_ratios=[1.8] + [1.0] * len(sides), hspace=0.55)
    top = gs[0].subgridspec(1, len(sides), wspace=0.75)
    for s, side in enumerate(sides):
        ax = fig.add_subplot(top[0, s])
        plot_in_plane(ax, table, side, iw, ip)
        ax.legend(fontsize=6, title="theta_i", title_fontsize=7, loc="upper left", bbox_to_anchor=(1.01, 1.0))
        k = 0 if side == "R" else 1
        allv = table.values_per_sr[iw, pick, ip, k]
        pos = allv[allv > 0]
        vmax = float(pos.max()) if pos.size else 1.0
        row = gs[1 + s].subgridspec(1, ncol + 1, width_ratios=[1.0] * ncol + [0.08], wspace=0.45)
        for j, ii in enumerate(pick):
            pax = fig.add_subplot(row[0, j], projection="polar")
            mesh = plot_polar_map(pax, table, side, int(ii), iw, ip, vmin=vmax * 1e-5, vmax=vmax)
        cax = fig.add_subplot(row[0, ncol])
        fig.colorbar(mesh, cax=cax).set_label(f"f_{side} (1/sr)", fontsize=7)
        cax.tick_params(labelsize=6)
    h = table.hemispherical()
    fig.suptitle(f"method {table.method}, light from {table.incident_from}: hemispherical R = "
                 f"{', '.join(f'{x:.3f}' for x in h['R'][iw, :, ip])}; T = "
                 f"{', '.join(f'{x:.3f}' for x in h['T'][iw, :, ip])} (theta_i = "
                 f"{', '.join(f'{x:g}' for x in table.theta_i_deg)} deg; polar maps: radius theta_s, "
                 "angle phi_s in deg)", fontsize=8)
    return fig


def compare_figure(tables: list, labels: list, sides=("R", "T"), iw: int = 0, ip: int = 0):
    """In-plane curves of several tables overlaid (one line style per table, one colour per
    incidence), every table evaluated at the first table's incidence angles and wavelength, each
    only at those within its own incidence range (+- 0.5 deg).

    E.g. `ray`, `normals` and `microfacet` tables of one relief, or a reconstruction against a
    measured IS-BSDF / XML file read by io.tables.  A side no table has data on is left out."""
    styles = ["-", "--", ":", "-."]
    sides = sides_with_data(tables, sides)
    ref = tables[0]
    fig, axs = plt.subplots(1, len(sides), figsize=(7.0 * len(sides), 5.6 + 0.12 * len(ref.theta_i_deg)),
                            squeeze=False)
    cmap = plt.get_cmap("viridis")
    n_ref = len(ref.theta_i_deg)
    colors = [cmap(j / max(n_ref - 1, 1)) for j in range(n_ref)]
    for s, side in enumerate(sides):
        ax = axs[0, s]
        for k, (t, lab) in enumerate(zip(tables, labels)):
            # a table is drawn only at the incidences it covers (within 0.5 deg): no curve held from
            # another incidence (e.g. a measured file of one incidence beside a table of several)
            cover = (ref.theta_i_deg >= t.theta_i_deg.min() - 0.5) & (ref.theta_i_deg <= t.theta_i_deg.max() + 0.5)
            if not cover.any():
                continue
            style = CurveStyle(linestyle=styles[k % len(styles)], label_prefix=f"{lab} ", show_specular=(k == 0),
                               colors=tuple(c for c, keep in zip(colors, cover) if keep))
            plot_in_plane(ax, t.select(ref.wavelength_nm[iw]), side, 0, min(ip, t.phi_i_deg.size - 1), style,
                          theta_i_deg=ref.theta_i_deg[cover])
        ax.legend(fontsize=6, ncol=len(tables), loc="upper center", bbox_to_anchor=(0.5, -0.2))
    fig.suptitle(" vs ".join(f"{lab} ({st})" for lab, st in zip(labels, styles * 4))
                 + f"  at theta_i of {labels[0]}", fontsize=9)
    fig.tight_layout()
    return fig


def save_figure(fig, path: str | Path, dpi: int = 110) -> Path:
    """Write `fig` to `path` (PNG) atomically and close it; the saved area holds every artist (a
    legend beside or below the axes is inside the file, not clipped)."""
    path = Path(path)
    with atomic_path(path) as tmp:
        fig.savefig(tmp, dpi=dpi, format=path.suffix.lstrip(".").lower() or "png", bbox_inches="tight")
    plt.close(fig)
    return path


def boundary_haze(table: BsdfTable, iw: int = 0) -> float:
    """The table's haze as ASTM D1003 defines it on the plate (`bsdf.haze.haze_astm_d1003`, the one
    definition shown everywhere) at wavelength index iw; NaN without a normal incidence."""
    from relief_bsdf.bsdf.haze import haze_astm_d1003
    return haze_astm_d1003(table, wavelength_nm=float(table.wavelength_nm[iw]))


def before_after_figure(tables: list, labels: list, theta_i_deg=(0.0, 30.0), width_px: int = 640,
                        height_px: int = 300, dpi: int = 100):
    """The boundary BSDF curves that a fit changed, side by side: in-plane transmission (left) and
    reflection (right) for light from outside, one line style per table (e.g. the relief as
    measured and as fitted), one colour per incidence; each label carries the table's haze
    (`boundary_haze`).  Sized in pixels to sit under a render of the same width."""
    styles = ["-", "--", ":", "-."]
    fig, axs = plt.subplots(1, 2, figsize=(width_px / dpi, height_px / dpi), dpi=dpi, squeeze=False)
    colors = ("tab:blue", "tab:orange", "tab:green", "tab:red")
    th = np.atleast_1d(np.asarray(theta_i_deg, float))
    short = {"T": "BTDF", "R": "BRDF"}
    hazes = [boundary_haze(t) for t in tables]
    for j, side in enumerate(("T", "R")):
        ax = axs[0, j]
        lines = []
        for k, (t, lab, haze) in enumerate(zip(tables, labels, hazes)):
            name = f"{lab}" + (f" (haze {100 * haze:.0f} %)" if side == "T" and np.isfinite(haze) else "")
            lines += plot_in_plane(ax, t, side, 0, 0, CurveStyle(linestyle=styles[k % 4], label_prefix=f"{name}: ",
                                                                colors=colors[:th.size], show_specular=False),
                                   theta_i_deg=th)
        _zoom_to_curves(ax, lines)
        ax.set_title(f"boundary {short[side]}, light from {tables[0].incident_from}, "
                     f"{tables[0].wavelength_nm[0]:g} nm", fontsize=7)
        ax.set_xlabel("signed scatter angle (deg), < 0: specular side", fontsize=6)
        ax.set_ylabel("BSDF (1/sr)", fontsize=6)
        ax.tick_params(labelsize=6)
        ax.legend(fontsize=5, loc="lower center", ncol=1, framealpha=0.8)
    fig.tight_layout(pad=0.4)
    return fig


def _zoom_to_curves(ax, lines, floor: float = 1e-3) -> None:
    """x limits around where the curves exceed `floor` x their peak (a narrow transmitted lobe
    fills the axis instead of a sliver of it), at least +-20 deg."""
    if not lines:
        return
    x = np.concatenate([np.asarray(ln.get_xdata(), float) for ln in lines])
    y = np.concatenate([np.asarray(ln.get_ydata(), float) for ln in lines])
    ok = np.isfinite(y)
    if not ok.any():
        return
    top = np.nanmax(y)
    sel = x[ok & (y > floor * top)]
    half = float(np.clip(np.max(np.abs(sel)) + 5.0, 20.0, 90.0)) if sel.size else 90.0
    ax.set_xlim(-half, half)


def figure_rgb(fig) -> np.ndarray:
    """The figure's pixels as float RGB in [0, 1] (display-encoded, top row first); closes it."""
    fig.canvas.draw()
    rgba = np.asarray(fig.canvas.buffer_rgba(), dtype=np.float32) / 255.0
    plt.close(fig)
    return np.ascontiguousarray(rgba[..., :3])
