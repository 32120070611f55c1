"""Exchange files checked by their consumers' own code: what Radiance (pyradiance 1.3.1: SDdirectHemi,
checkBSDF) reads from the XML the project writes, an IS-BSDF file parsed here from the format's
description (not the project's parser), and every written file read back.

Tables are analytic and small (fast): a lossless boundary of glass n = 1.5 seen from both sides, a
Fresnel split between R and T at every incidence (R + T = 1), shaped as a narrow lobe (rms radius
~0.7 deg, far below a Klems patch), a broad one (~10 deg), or delta parts (specular) plus a faint
haze, as Kirchhoff and Rayleigh-Rice tables have.  Totals are the tables' own (cell sums), so the
checks are of the file and its reader, never of a formula shared with the writer.
"""
from __future__ import annotations

import json
import re
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from relief_bsdf.bsdf.table import BsdfTable
from relief_bsdf.core.frames import direction
from relief_bsdf.io.hdf5 import load_tables, save_tables
from relief_bsdf.io.isbsdf import export_isbsdf, import_isbsdf
from relief_bsdf.io.radiance_xml import read_radiance_xml, write_radiance_xml

sys.path.insert(0, str(Path(__file__).resolve().parent))
from test_radiance_xml import CHECKBSDF, load_bsdf  # noqa: E402
from pyradiance import bsdf as rb  # noqa: E402  (test-only oracle, requirements/test.txt)

N = 1.5
MAT = {"inside": {"model": "constant", "n": N, "k": 0.0}, "outside": {"model": "constant", "n": 1.0, "k": 0.0}}
TE = np.concatenate([np.linspace(0.0, 12.0, 25), np.linspace(14.0, 90.0, 39)])   # 0.5 deg cells near the normal
PE = np.linspace(0.0, 360.0, 73)
THETA_I = np.array([0.0, 30.0, 60.0])


def fresnel(cos_i, n1, n2):
    """Unpolarised reflectance of a flat boundary (textbook formula; 1 past the critical angle)."""
    sin_t = n1 / n2 * np.sqrt(np.clip(1 - cos_i ** 2, 0, 1))
    if sin_t >= 1:
        return 1.0
    cos_t = np.sqrt(1 - sin_t ** 2)
    rs = (n1 * cos_i - n2 * cos_t) / (n1 * cos_i + n2 * cos_t)
    rp = (n1 * cos_t - n2 * cos_i) / (n1 * cos_t + n2 * cos_i)
    return 0.5 * (rs ** 2 + rp ** 2)


def lossless(frm: str, kind: str, theta_i=THETA_I, phi_i=(0.0,), aniso: float = 0.0) -> BsdfTable:
    """Fresnel split R = F, T = 1 - F per incidence; lobes about the mirror / refracted directions.
    kind: 'narrow' (Gaussian, rms radius 0.7 deg), 'broad' (10 deg) or 'delta' (90 % of each side in
    the delta part, the rest a 3 deg haze).  aniso: T scaled by 1 + aniso cos(2 phi_i), R takes the rest."""
    n1, n2 = (1.0, N) if frm == "outside" else (N, 1.0)
    width = {"narrow": 0.7, "broad": 10.0, "delta": 3.0}[kind]
    tc, pc = 0.5 * (TE[1:] + TE[:-1]), 0.5 * (PE[1:] + PE[:-1])
    d = direction(tc[:, None], pc[None, :])
    psa = (np.sin(np.radians(TE[1:])) ** 2 - np.sin(np.radians(TE[:-1])) ** 2)[:, None] / 2 * np.radians(np.diff(PE))
    v = np.zeros((1, len(theta_i), len(phi_i), 2, tc.size, pc.size))
    sR = np.zeros((1, len(theta_i), len(phi_i)))
    sT = np.zeros_like(sR)
    for i, t in enumerate(theta_i):
        F = fresnel(np.cos(np.radians(t)), n1, n2)
        for p, ph in enumerate(phi_i):
            T = (1 - F) * (1 + aniso * np.cos(np.radians(2 * ph))) if F < 1 else 0.0
            T = min(T, 1.0)
            parts = {0: (t, 1 - T), 1: (None, T)}
            for k, (centre, power) in parts.items():
                if power <= 0:
                    continue
                if k == 1:
                    st = n1 * np.sin(np.radians(t)) / n2
                    centre = np.degrees(np.arcsin(st))
                c = d @ direction(centre, ph + 180.0)
                ang = np.degrees(np.arccos(np.clip(c, -1, 1)))
                lobe = np.exp(-0.5 * (ang / width) ** 2)
                share = 0.1 if kind == "delta" else 1.0
                v[0, i, p, k] = lobe / np.sum(lobe * psa) * power * share
                if kind == "delta":
                    (sR if k == 0 else sT)[0, i, p] = power * (1 - share)
    return BsdfTable(wavelength_nm=[550.0], theta_i_deg=theta_i, phi_i_deg=phi_i, theta_s_edges_deg=TE,
                     phi_s_edges_deg=PE, values_per_sr=v, incident_from=frm, specular_R=sR, specular_T=sT,
                     material=MAT, method=f"test-{kind}")


def radiance_RT(sd, frm: str, theta: float, table_phi: float = 0.0) -> tuple[float, float]:
    """Radiance's directional-hemispherical R and T (delta parts included) for light from `frm` at
    (theta, table azimuth).  WINDOW front = outside = Radiance's -z hemisphere; azimuth negated."""
    th = 180.0 - theta if frm == "outside" else theta
    ph = (-table_phi) % 360.0
    return tuple(rb.direct_hemi(sd, th, ph, f | rb.SAMPLE_SP | rb.SAMPLE_DF) for f in (rb.SAMPLE_R, rb.SAMPLE_T))


def tree_cell_theta(path, theta: float) -> float:
    """Centre polar angle of the TensorTree3 incidence cell holding theta (Radiance bsdf_t.c: the
    axis is 0.5 - sin(theta) / 2 on 2^depth cells; depth from the file's comment)."""
    n = 2 ** int(re.search(r"uniform depth (\d+)", Path(path).read_text()[:3000]).group(1))
    k = int(np.ceil((0.5 - 0.5 * np.sin(np.radians(theta))) * n - 1e-9)) - 1
    return float(np.degrees(np.arcsin(1 - 2 * (k + 0.5) / n)))


def reciprocity(path) -> dict:
    """checkBSDF's 'Reciprocity Error (min avg max %)' rows: {component: (min, avg, max)}."""
    r = subprocess.run([str(CHECKBSDF), str(path)], capture_output=True, text=True, timeout=120)
    assert r.returncode == 0, r.stderr
    out = r.stdout.split("Reciprocity Error")[1]
    rows = re.findall(r"^(\w[\w ]*?)\s+([\d.]+)\s+([\d.]+)\s+([\d.]+)\s*$", out, flags=re.M)
    return {name.strip(): tuple(float(x) for x in vals) for name, *vals in rows}


@pytest.mark.parametrize("structure", ["klems", "tensor-tree"])
@pytest.mark.parametrize("kind", ["narrow", "broad", "delta"])
def test_radiance_reads_what_the_table_holds(tmp_path, kind, structure):
    """SDdirectHemi within 1 % of the table's R and T at every tabulated incidence from both sides and
    at incidences between them (linear in theta_i, the writer's stated interpolation; Klems ring
    centres, clear of the critical angle from inside); R + T never above 1 (lossless tables)."""
    tabs = [lossless("outside", kind), lossless("inside", kind)]
    notes: list = []
    path = write_radiance_xml(tmp_path / f"energy_{kind}_{structure}.xml", tabs, structure=structure, notes=notes)
    sd = load_bsdf(path)
    worst = 0.0
    for t in tabs:
        h = t.hemispherical()
        between = (10.0, 20.0, 40.0, 50.0) if t.incident_from == "outside" else (10.0, 20.0)
        for theta in (*t.theta_i_deg, *between):
            at = theta if theta in t.theta_i_deg or structure == "klems" else tree_cell_theta(path, theta)
            want = [float(np.interp(at, t.theta_i_deg, h[k][0, :, 0])) for k in ("R", "T")]
            got = radiance_RT(sd, t.incident_from, theta)
            assert sum(got) <= 1.0 + 1e-4, (t.incident_from, theta, got)
            for g, w, k in zip(got, want, "RT"):
                assert g == pytest.approx(w, rel=0.01, abs=2e-4), (t.incident_from, theta, k, g, w)
                if w > 1e-3:
                    worst = max(worst, abs(g / w - 1))
    print(f"{kind} {structure}: largest |Radiance / table - 1| = {100 * worst:.3f} %; " + " | ".join(notes))
    assert any("extrapolated" in n for n in notes)                  # 70 / 82.5 deg are beyond 0-60 and say so
    if kind == "narrow":
        assert any("below" in n or "spread over one patch" in n for n in notes)


def test_incidence_beyond_the_table_is_extrapolated_not_held(tmp_path):
    """70 deg from a 0-30-60 table: R grows as a smooth boundary's Fresnel reflectance does (not held at
    its 60 deg value), R + T stays 1."""
    tabs = [lossless("outside", "broad"), lossless("inside", "broad")]
    sd = load_bsdf(write_radiance_xml(tmp_path / "extrap_klems.xml", tabs))
    R60 = float(tabs[0].hemispherical()["R"][0, 2, 0])
    R70, T70 = radiance_RT(sd, "outside", 70.0)
    want = R60 + fresnel(np.cos(np.radians(70.0)), 1.0, N) - fresnel(np.cos(np.radians(60.0)), 1.0, N)
    assert R70 == pytest.approx(want, rel=0.01) and R70 + T70 == pytest.approx(1.0, abs=1e-3)


def _reciprocal_table(frm: str) -> BsdfTable:
    """An exactly reciprocal reflection (Beckmann-like half-vector lobe, f = rho D(h) / (4 cos_i cos_o),
    symmetric in i and o), incidences every 5 deg; a uniform transmission."""
    ti = np.arange(0.0, 90.0, 5.0)
    te, pe = np.linspace(0, 90, 46), np.linspace(0, 360, 73)
    m = 4
    u = (np.arange(m) + 0.5) / m
    s2 = np.sin(np.radians(te[:-1]))[:, None] ** 2 + u * (np.sin(np.radians(te[1:])) ** 2 - np.sin(np.radians(te[:-1])) ** 2)[:, None]
    th = np.degrees(np.arcsin(np.sqrt(s2)))
    ph = pe[:-1, None] + u * np.diff(pe)[:, None]
    d = direction(th[:, None, :, None], ph[None, :, None, :])
    v = np.zeros((1, ti.size, 1, 2, te.size - 1, pe.size - 1))
    for i, t in enumerate(ti):
        wi = direction(t, 0.0)
        hv = d + wi
        hv /= np.linalg.norm(hv, axis=-1, keepdims=True)
        ch = hv[..., 2]
        D = np.exp(-(1 - ch ** 2) / ch ** 2 / 0.3 ** 2) / (np.pi * 0.3 ** 2 * ch ** 4)
        v[0, i, 0, 0] = (0.3 * D / (4 * wi[2] * np.maximum(d[..., 2], 1e-6))).mean(axis=(-2, -1))
        v[0, i, 0, 1] = 0.2 / np.pi
    return BsdfTable(wavelength_nm=[550.0], theta_i_deg=ti, phi_i_deg=[0.0], theta_s_edges_deg=te,
                     phi_s_edges_deg=pe, values_per_sr=v, incident_from=frm, method="test")


@pytest.mark.slow
def test_checkbsdf_reciprocity_figures(tmp_path):
    """checkBSDF's reciprocity of the reflection blocks on an exactly reciprocal table (module doc of
    io/radiance_xml: the figures and why Klems cannot reach 5 %): tensor tree with cells at their
    centres <= 5 %, with tabulated incidences kept exact <= 10 %, Klems <= 7 %; printed."""
    tabs = [_reciprocal_table("outside"), _reciprocal_table("inside")]
    figs = {}
    for name, kw in (("klems", {}), ("tree", {"structure": "tensor-tree", "depth": 6}),
                     ("tree-centres", {"structure": "tensor-tree", "depth": 6, "keep_tabulated": False})):
        figs[name] = reciprocity(write_radiance_xml(tmp_path / f"recip_{name}.xml", tabs, **kw))
        print(name, figs[name])
    refl = lambda f: max(v[1] for k, v in f.items() if "Refl" in k)  # noqa: E731
    assert refl(figs["tree-centres"]) <= 5.0
    assert refl(figs["tree"]) <= 10.0
    assert refl(figs["klems"]) <= 7.0


@pytest.mark.slow
def test_anisotropic_table_keeps_its_azimuths(tmp_path, capsys):
    """Several phi_i: TensorTree4 and Klems give each azimuth's own R and T in Radiance; the IS-BSDF
    lists every azimuth in SampleRotation.  A one-azimuth table whose normal-incidence lobe is not
    round is exported with one warning line."""
    phi = tuple(np.arange(0.0, 360.0, 45.0))
    tabs = [lossless(f, "broad", theta_i=np.array([0.0, 30.0]), phi_i=phi, aniso=0.02) for f in ("outside", "inside")]
    for structure in ("klems", "tensor-tree"):
        sd = load_bsdf(write_radiance_xml(tmp_path / f"aniso_{structure}.xml", tabs, structure=structure, depth=4))
        h = tabs[0].hemispherical()
        for p, ph in enumerate(phi[:3]):
            got = radiance_RT(sd, "outside", 30.0, ph)
            tol = 0.01 if structure == "tensor-tree" else 0.02     # Klems incident patches are 18 deg wide at 30 deg
            assert got[1] == pytest.approx(h["T"][0, 1, p], rel=tol), (structure, ph, got)
    blocks = parse_isbsdf(export_isbsdf(tabs[0], tmp_path / "aniso.bsdf")[1])
    assert blocks["SampleRotation"] == list(phi)
    # read back without the writer's comments (a foreign Klems file): the azimuth dependence is seen
    text = re.sub(r"<!-- relief: (theta|phi)_i_deg[^>]*-->", "", (tmp_path / "aniso_klems.xml").read_text())
    (tmp_path / "foreign.xml").write_text(text)
    assert read_radiance_xml(tmp_path / "foreign.xml")[0].phi_i_deg.size == 8
    # one azimuth, elliptical lobe (relief slopes recorded 3x apart): the CLI says it drops the azimuths
    from relief_bsdf.cli import main
    one = [lossless(f, "broad") for f in ("outside", "inside")]
    for t in one:
        t.relief = {"rms_slope_x": 0.05, "rms_slope_y": 0.15}
    src = save_tables(tmp_path / "one.h5", one)
    capsys.readouterr()
    assert main(["export", str(src), "--format", "is-bsdf", "-o", str(tmp_path / "one.bsdf")]) == 0
    err = capsys.readouterr().err
    assert err.count("relief: warning:") == 1 and "azimuthal dependence is dropped" in err


# ---------------------------------------------------------------- an independent IS-BSDF reading


def parse_isbsdf(path) -> dict:
    """The Zemax/Radiant IS-BSDF text layout read from its description (keywords, counted lists,
    'TIS t' then n_azimuth rows of n_radial values per (rotation, incidence)), not the project's parser."""
    words = [w for line in Path(path).read_text().splitlines() if not line.lstrip().startswith("#")
             for w in line.split()]
    out: dict = {}
    i = 0
    while words[i] != "DataBegin":
        if words[i] in ("SampleRotation", "AngleOfIncidence", "ScatterAzimuth", "ScatterRadial"):
            n = int(words[i + 1])
            out[words[i]] = [float(x) for x in words[i + 2:i + 2 + n]]
            i += 2 + n
        elif words[i] in ("Source", "Symmetry", "SpectralContent", "ScatterType"):
            out[words[i]] = words[i + 1]
            i += 2
        else:
            i += 1
    i += 1
    na, nr = len(out["ScatterAzimuth"]), len(out["ScatterRadial"])
    out["TIS"], out["data"] = [], []
    for _ in out["SampleRotation"]:
        for _ in out["AngleOfIncidence"]:
            assert words[i] == "TIS"
            out["TIS"].append(float(words[i + 1]))
            out["data"].append(np.array(words[i + 2:i + 2 + na * nr], float).reshape(na, nr))
            i += 2 + na * nr
    assert words[i] == "DataEnd"
    return out


@pytest.mark.parametrize("kind", ["narrow", "broad"])
def test_isbsdf_file_read_independently(tmp_path, kind):
    """Read from its description: the BTDF's TIS lines are the table's diffuse T per incidence, and at
    normal incidence (radial = scatter angle) a trapezoid integral of the data over the hemisphere
    gives the same within 1 % (the written grid: the table's cell centres and edges, so 0.5 deg steps)."""
    t = lossless("outside", kind)
    f = parse_isbsdf(export_isbsdf(t, tmp_path / "x.bsdf")[1])
    assert f["ScatterType"] == "BTDF" and f["AngleOfIncidence"] == list(THETA_I) and f["SampleRotation"] == [0.0]
    h = t.hemispherical()
    np.testing.assert_allclose(f["TIS"], h["diffuse_T"][0, :, 0], rtol=1e-5)
    rad = np.radians(np.array(f["ScatterRadial"]))
    az = np.radians(np.array(f["ScatterAzimuth"]))
    data = f["data"][0]                                         # (azimuth, radial), normal incidence
    keep = rad <= np.pi / 2
    ring = np.trapz(data[:, keep] * (np.cos(rad) * np.sin(rad))[keep], rad[keep], axis=1)
    total = np.trapz(ring, az) * (2 if f["Symmetry"] == "PlaneSymmetrical" else 1)
    assert total == pytest.approx(f["TIS"][0], rel=0.01)


# ---------------------------------------------------------------- round trips


@pytest.mark.slow
@pytest.mark.parametrize("kind", ["narrow", "delta"])
def test_every_written_file_reads_back_within_half_a_percent(tmp_path, kind):
    """HDF5, IS-BSDF, Radiance XML (Klems and tensor tree) and recording CSV read back with R and T
    within 0.5 % at every tabulated incidence and an honest lost = 1 - R - T."""
    from relief_bsdf.io.recording import read_recording
    tabs = [lossless("outside", kind), lossless("inside", kind)]
    back = {"hdf5": load_tables(save_tables(tmp_path / "t.h5", tabs)),
            "is-bsdf": [import_isbsdf(export_isbsdf(t, tmp_path / f"{t.incident_from}.bsdf")) for t in tabs],
            "klems": read_radiance_xml(write_radiance_xml(tmp_path / "k.xml", tabs)),
            "tensor-tree": read_radiance_xml(write_radiance_xml(tmp_path / "tt.xml", tabs, structure="tensor-tree"))}
    for name, got in back.items():
        for a, b in zip(tabs, got):
            ha, hb = a.hemispherical(), b.hemispherical()
            for i, ti in enumerate(a.theta_i_deg):
                j = int(np.argmin(np.abs(b.theta_i_deg - ti)))
                assert b.theta_i_deg[j] == pytest.approx(ti)
                for k in ("R", "T"):
                    assert hb[k][0, j, 0] == pytest.approx(ha[k][0, i, 0], rel=0.005, abs=1e-5), (name, a.incident_from, ti, k)
                honest = a.lost[0, i, 0] if name == "hdf5" else 1 - hb["R"][0, j, 0] - hb["T"][0, j, 0]
                assert hb["lost"][0, j, 0] == pytest.approx(honest, abs=1e-9)    # HDF5: the table's own
    # recording CSV (`relief export --format recording-csv`): the rows are the cells, the deltas are
    # '# specular wl, theta_i, phi_i, R, T' comment lines; summed back over the grid
    from relief_bsdf.cli import main
    t = tabs[0]
    save_tables(tmp_path / "one.h5", [t])
    assert main(["export", str(tmp_path / "one.h5"), "--format", "recording-csv", "-o", str(tmp_path / "r.csv")]) == 0
    rec = read_recording(tmp_path / "r.csv")
    spec = {float(c.split(",")[1]): [float(x) for x in c.split(",")[3:5]]
            for c in rec.comments if re.match(r"specular \d", c.strip())}
    psa = t.projected_solid_angle_sr
    for i, ti in enumerate(t.theta_i_deg):
        for k in ("R", "T"):
            sel = (rec.theta_i_deg == ti) & (rec.side == k)
            total = np.sum(rec.bsdf_sr[sel].reshape(psa.shape) * psa) + spec[ti][0 if k == "R" else 1]
            assert total == pytest.approx(t.hemispherical()[k][0, i, 0], rel=0.005, abs=1e-6), ("csv", ti, k)


def test_info_prints_the_honest_loss_of_an_exchanged_file(tmp_path, capsys):
    """A file whose R + T is not 1 (here 1.1: a table outside its model's validity) shows lost = -0.1
    in `relief info`, not 0."""
    from relief_bsdf.cli import main
    tabs = [lossless(f, "broad") for f in ("outside", "inside")]
    for t in tabs:
        t.values_per_sr[:, :, :, 1] *= 1.1 / np.maximum(t.hemispherical()["T"][0][None, :, :, None, None], 1e-9)
        t.values_per_sr[:, :, :, 1] *= np.where(t.hemispherical()["T"][0] > 0, 1, 0)[None, :, :, None, None]
    write_radiance_xml(tmp_path / "lossy.xml", tabs)
    sources = {"xml": tmp_path / "lossy.xml", "bsdf": export_isbsdf(tabs[0], tmp_path / "lossy.bsdf")[1]}
    for name, src in sources.items():         # as a user does: export to the project's table, then info
        capsys.readouterr()
        assert main(["export", str(src), "--format", "hdf5", "-o", str(tmp_path / f"{name}.h5")]) == 0
        assert main(["info", str(tmp_path / f"{name}.h5"), "--json"]) == 0
        rows = json.loads(capsys.readouterr().out.split("\n", 1)[1])["albedo"]
        for r in rows:
            assert r["lost"] == pytest.approx(1 - r["R"] - r["T"], abs=1e-6)
        assert min(r["lost"] for r in rows) < -0.05
