"""`relief reconstruct` and `relief plot` through the command-line entry point."""
import json

import numpy as np
import pytest

from relief_bsdf.io.hdf5 import load_tables
from relief_bsdf.cli import main


def _write_relief(path, n=64, slope_axis=0.1, nan=False):
    rng = np.random.default_rng(0)
    k = np.fft.fftfreq(n)
    kx, ky = np.meshgrid(k, k)
    h = np.real(np.fft.ifft2(np.fft.fft2(rng.normal(size=(n, n))) * np.exp(-(np.pi * 5) ** 2 * (kx**2 + ky**2) / 2)))
    sy, sx = np.gradient(h)
    h *= slope_axis / np.sqrt(0.5 * np.mean(sx**2 + sy**2))
    if nan:
        h[:] = np.nan
    np.savez(path, heights=h * 1e-6, dx=1e-6, dy=1e-6)
    return path


COMMON = ["--theta-i-deg", "0,40", "--theta-step-deg", "5", "--phi-step-deg", "15"]


@pytest.mark.parametrize("method,extra", [("microfacet", []), ("normals", ["--samples", "20000"]),
                                          ("ray", ["--samples", "20000"])])
def test_reconstruct_info_plot_export(tmp_path, capsys, method, extra):
    relief = _write_relief(tmp_path / "r.npz")
    out = tmp_path / f"{method}.h5"
    rc = main(["reconstruct", str(relief), "--method", method, "--n", "1.5", "--from", "both", "-o", str(out)]
              + COMMON + extra)
    assert rc == 0
    printed = capsys.readouterr().out
    assert "outside" in printed and "inside" in printed          # the R/T summary per incidence
    tables = load_tables(out)
    assert [t.incident_from for t in tables] == ["outside", "inside"]
    for t in tables:
        assert t.method == method
        assert t.values_per_sr.shape == (1, 2, 1, 2, 18, 24)
        h = t.hemispherical()
        np.testing.assert_allclose(h["R"] + h["T"] + h["lost"], 1.0, atol=5e-6)   # float32 storage
        assert np.all(h["lost"] < 0.01)
    # normal incidence from outside reflects about the Fresnel 4 %
    assert tables[0].hemispherical()["R"][0, 0, 0] == pytest.approx(0.04, abs=0.006)
    assert main(["info", str(out), "--json"]) == 0
    info = json.loads(capsys.readouterr().out)
    assert info["kind"] == "bsdf" and len(info["albedo"]) >= 2
    png = tmp_path / "plot.png"
    assert main(["plot", str(out), "-o", str(png), "--from", "inside"]) == 0
    data = png.read_bytes()
    assert data[:8] == b"\x89PNG\r\n\x1a\n" and len(data) > 20_000
    assert main(["plot", str(out), "--side", "T"]) == 0
    assert (tmp_path / f"{method}.png").exists()
    csv = tmp_path / "rows.csv"
    assert main(["export", str(out), "--format", "recording-csv", "-o", str(csv)]) == 0
    assert csv.read_text().startswith("# relief-recording/1")


def test_reconstruct_options_and_cauchy(tmp_path):
    relief = _write_relief(tmp_path / "r.npz")
    out = tmp_path / "o.h5"
    rc = main(["reconstruct", str(relief), "--method", "microfacet", "--cauchy", "1.5,4200", "--wavelengths-nm",
               "450,650", "--option", "distribution=\"ggx\"", "--option", "alpha=0.3", "--polarized", "-o", str(out)]
              + COMMON)
    assert rc == 0
    t = load_tables(out)[0]
    assert t.metadata["distribution"] == "ggx" and t.relief["lobes"]["alpha"] == [0.3]
    assert t.is_polarized
    # dispersion: the blue index is higher, so normal-incidence reflectance is higher in the blue
    R = t.hemispherical()["R"][:, 0, 0]
    n = 1.5 + 4200 / np.array([450.0, 650.0]) ** 2
    assert R[0] > R[1]
    F = ((n - 1) / (n + 1)) ** 2
    assert R[0] / R[1] == pytest.approx(F[0] / F[1], rel=2e-3)       # the rough lobe scales with Fresnel


@pytest.mark.parametrize("args,fragment", [
    (["--method", "microfacet"], "--n/--cauchy"),                                        # missing index
    (["--method", "microfacet", "--n", "-1.5"], "index"),                                # unphysical index
    (["--method", "microfacet", "--n", "1.5", "--theta-i-deg", "0,90"], "--theta-i-deg"),
    (["--method", "nonsense", "--n", "1.5"], "--method"),
    (["--method", "normals", "--n", "1.5", "--theta-step-deg", "7"], "--theta-step-deg"),
    (["--method", "normals", "--n", "1.5", "--option", "grazing_heuristic=\"sometimes\""], "grazing"),
])
def test_bad_input_exit_2(tmp_path, capsys, args, fragment):
    relief = _write_relief(tmp_path / "r.npz")
    rc = main(["reconstruct", str(relief), "-o", str(tmp_path / "x.h5")] + args)
    err = capsys.readouterr().err
    assert rc == 2
    assert fragment in err and len(err.strip().splitlines()) == 1
    assert not (tmp_path / "x.h5").exists()


def test_bad_relief_exit_2(tmp_path, capsys):
    assert main(["reconstruct", str(tmp_path / "missing.npz"), "--method", "normals", "--n", "1.5",
                 "-o", str(tmp_path / "x.h5")]) == 2
    nan = _write_relief(tmp_path / "nan.npz", nan=True)
    assert main(["reconstruct", str(nan), "--method", "normals", "--n", "1.5", "-o", str(tmp_path / "x.h5")]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 2 and all("error" in e for e in err)
    assert main(["plot", str(tmp_path / "missing.h5")]) == 2


def test_plot_compare_overlays_tables(tmp_path):
    relief = _write_relief(tmp_path / "r.npz")
    a, b = tmp_path / "a.h5", tmp_path / "b.h5"
    assert main(["reconstruct", str(relief), "--method", "microfacet", "--n", "1.5", "-o", str(a)] + COMMON) == 0
    assert main(["reconstruct", str(relief), "--method", "normals", "--n", "1.5", "--samples", "20000",
                 "-o", str(b)] + COMMON) == 0
    png = tmp_path / "cmp.png"
    assert main(["plot", str(a), "--compare", str(b), "-o", str(png)]) == 0
    assert png.read_bytes()[:4] == b"\x89PNG"
    assert main(["plot", str(a), "--compare", str(tmp_path / "missing.h5"), "-o", str(png)]) == 2


def test_reconstruct_and_info_say_what_band_limiting_removed(tmp_path, capsys):
    """Issue 13 item 3: a 20 nm relief at 50 nm pitch with 3 nm of white (instrument) noise; at 550 nm
    only |f| <= (n sin t_i + n) / lambda ~ 3.6 /um scatter into propagating directions, so kirchhoff
    low-passes the heights, and both `relief reconstruct` and `relief info TABLE` say how much it
    removed (white noise keeps only ~(pi f_max^2) / (1 / dx^2) ~ 10 % of its variance in the band, so
    ~2.5-3 nm rms go)."""
    from relief_bsdf.surface.synth import random_relief
    rel = random_relief(256, 0.05e-6, 20e-9, 1e-6, seed=3)
    h = rel.heights_m + 3e-9 * np.random.default_rng(4).standard_normal(rel.shape)
    src = tmp_path / "noisy.npz"
    np.savez(src, heights=h, dx=0.05e-6, dy=0.05e-6)
    out = tmp_path / "k.h5"
    assert main(["reconstruct", str(src), "--method", "kirchhoff", "--n", "1.5", "--theta-i-deg", "0",
                 "--theta-step-deg", "5", "--phi-step-deg", "15", "--option", "backend=\"serial\"", "-o", str(out)]) == 0
    said = [ln for ln in capsys.readouterr().out.splitlines() if ln.startswith("heights")]
    assert len(said) == 1 and "band-limited to |f| <=" in said[0] and "removed" in said[0], said
    removed_nm = float(said[0].split("removed ")[1].split(" nm")[0])
    assert 2.3 < removed_nm < 3.1, said
    assert main(["info", str(out)]) == 0
    assert any(ln.strip().startswith("heights") and "removed" in ln for ln in capsys.readouterr().out.splitlines())
    assert main(["info", str(out), "--json"]) == 0
    band = json.loads(capsys.readouterr().out)["height_band_limit"]["outside"]
    assert abs(band["removed_rms_m"] * 1e9 - removed_nm) < 0.01
