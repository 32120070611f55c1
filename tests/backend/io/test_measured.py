"""Measured plate BSDF files as recording rows (io.measured): RPC Photonics text and measured IS-BSDF.

The frame mapping of RPC's files is proven on the vendor's own data (../shared/data/measured/eds10:
RPC Photonics' measured BTDF of their EDS10 engineered diffuser, a square top-hat about 10 deg
wide): every figure below is computed here from the rows the reader returns, with the rows'
projected solid angles built in this file from the theta_s grid (cells between mid-points,
clipped to the measured 0..85 deg; 1-degree azimuth cells), not with the module's own weights.
"""
from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest

from relief_bsdf.errors import InputError
from relief_bsdf.io.measured import (DEFAULT_RELATIVE_SIGMA, lobe_summary, read_measured, read_measured_file,
                                     read_recording_files, sniff)
from relief_bsdf.io.recording import read_recording, read_sample, write_recording

SHARED = Path(__file__).resolve().parents[3].parent / "shared" / "data" / "measured"
EDS10 = SHARED / "eds10"
ISBSDF = SHARED / "isbsdf"
RPC_FILES = {"EDS10 0-0.txt": (0.0, 0.0), "EDS10 5-0.txt": (5.0, 0.0), "EDS10 5-45.txt": (5.0, 45.0)}
ISBSDF_FILES = {  # name: (ScatterType side, wavelength stated in the header)
    "test_13_brdf_one_wavelength_BRDF_zemax_reference.bsdf": ("R", 550.0),
    "test_13_brdf_one_wavelength_BTDF_zemax_reference.bsdf": ("T", 550.0),
    "test_13_brdf_one_wavelength_speos_550.0_BTDF.bsdf": ("T", 550.0),
    "test_13_planesymmetric_brdf_zemax.bsdf": ("R", None),
    "test_13_planesymmetric_btdf_zemax.bsdf": ("T", None),
}
HALF_WIDTH = 0.095          # the top-hat's half-maximum half-width in direction cosine


def _rows(name: str):
    return read_measured(EDS10 / name, wavelength_nm=633.0)


def _weights(rec) -> np.ndarray:
    """Projected solid angle cos(theta_s) dOmega of each row of a full RPC grid (1-degree azimuths)."""
    th = np.unique(rec.theta_s_deg)
    mid = np.radians(0.5 * (th[1:] + th[:-1]))
    lo = np.concatenate([[np.radians(th[0])], mid])
    hi = np.concatenate([mid, [np.radians(th[-1])]])
    ring = 0.5 * (np.sin(hi) ** 2 - np.sin(lo) ** 2) * np.radians(1.0)
    return ring[np.searchsorted(th, rec.theta_s_deg)]


def _unit(theta_deg, phi_deg) -> np.ndarray:
    t, p = np.radians(theta_deg), np.radians(phi_deg)
    return np.stack([np.sin(t) * np.cos(p), np.sin(t) * np.sin(p), np.cos(t)], axis=-1)


def _angle_deg(a, b) -> float:
    return math.degrees(math.atan2(np.linalg.norm(np.cross(a, b)), float(np.dot(a, b))))


def _plateau(rec, w, centre_ab) -> float:
    """Projected-solid-angle mean of f over the square of half-width 0.07 (direction cosines) about
    the centre: inside the lobe's 90 % points (~0.065-0.08), where the top-hat is flat."""
    a, b = _unit(rec.theta_s_deg, rec.phi_s_deg)[:, :2].T
    m = (np.abs(a - centre_ab[0]) <= 0.07) & (np.abs(b - centre_ab[1]) <= 0.07)
    return float(np.sum((rec.bsdf_sr * w)[m]) / np.sum(w[m]))


def _centroid(rec, w, theta_phi_shift=lambda p: p):
    """Power-weighted mean direction of the rows at or above half the plateau (the lobe)."""
    f = rec.bsdf_sr
    core = f >= 0.5 * np.percentile(f, 99.5)
    d = _unit(rec.theta_s_deg[core], theta_phi_shift(rec.phi_s_deg[core]))
    c = (d * (f * w)[core][:, None]).sum(axis=0)
    return c / np.linalg.norm(c)


# ====================================================================== sniffing and reading


def test_sniff_by_content(tmp_path):
    (tmp_path / "a.dat").write_text("!!X 0-0 RPC\n!!BSDF Data\n0 0\n0 0 1\n")
    (tmp_path / "b.txt").write_text("# a comment\nSource  Measured\nScatterType BRDF\n")
    (tmp_path / "c.txt").write_text("# relief-recording/1\n")
    (tmp_path / "d.txt").write_text("hello\n")
    assert [sniff(tmp_path / n) for n in ("a.dat", "b.txt", "c.txt", "d.txt")] == ["rpc", "is-bsdf", "recording", None]


def _small_rpc(tmp_path: Path, name="s.txt", theta_i=5.0, phi_i=0.0, extra="") -> Path:
    """A 3 x 4 RPC grid: theta_s 0, 1, 2; phi_s 0, 90, 180, 270; f = 1 + theta + phi / 1000."""
    lines = ["!!S 5-0     RPC Photonics     1/1/2020", "!!BSDF Data", f"{theta_i:.3f}\t{phi_i:.3f}"]
    for t in (0, 1, 2):
        for p in (0, 90, 180, 270):
            lines.append(f"{t:.4f}\t{p:.4f}\t{1 + t + p / 1000:.4f}")
    p = tmp_path / name
    p.write_text("\n".join(lines) + "\n" + extra)
    return p


def test_rpc_rows_mapped_into_the_project_frame(tmp_path):
    rec = read_measured(_small_rpc(tmp_path), wavelength_nm=633.0)
    assert len(rec) == 12 and set(rec.side) == {"T"}
    assert np.all(rec.theta_i_deg == 5.0) and np.all(rec.phi_i_deg == 0.0) and np.all(rec.wavelength_nm == 633.0)
    # RPC's reading at (theta_s, phi_s) = (2, 90) (f = 3.09) is the row (T, 2, 270)
    k = np.nonzero((rec.theta_s_deg == 2) & (rec.phi_s_deg == 270))[0]
    assert k.size == 1 and rec.bsdf_sr[k[0]] == pytest.approx(3.09)
    k = np.nonzero((rec.theta_s_deg == 1) & (rec.phi_s_deg == 0))[0]
    assert rec.bsdf_sr[k[0]] == pytest.approx(2.18)          # RPC's phi_s 180
    # no uncertainty in the file: sqrt((0.03 f)^2 + floor^2), the floor > 0 (generic: too few dim pairs)
    mf = read_measured_file(tmp_path / "s.txt")
    assert mf.noise_floor_sr > 0
    np.testing.assert_allclose(rec.sigma_sr, np.hypot(DEFAULT_RELATIVE_SIGMA * rec.bsdf_sr, mf.noise_floor_sr))
    rec2 = read_measured(tmp_path / "s.txt", wavelength_nm=633.0, relative_sigma=0.1)
    np.testing.assert_allclose(rec2.sigma_sr, np.hypot(0.1 * rec.bsdf_sr, mf.noise_floor_sr))
    # written and read back as recording.csv: the same rows
    back = read_recording(write_recording(tmp_path / "r.csv", rec))
    np.testing.assert_array_equal(back.bsdf_sr, rec.bsdf_sr)
    np.testing.assert_array_equal(back.phi_s_deg, rec.phi_s_deg)


def test_rpc_wavelength_must_be_given(tmp_path):
    p = _small_rpc(tmp_path)
    with pytest.raises(InputError) as e:
        read_measured(p)
    msg = str(e.value)
    assert str(p) in msg and "--wavelength-nm" in msg and "\n" not in msg


@pytest.mark.parametrize("edit, where, words", [
    (lambda t: t.replace("!!BSDF Data", "BSDF Data"), ":2", "!!BSDF Data"),
    (lambda t: t.replace("5.000\t0.000", "5.000"), ":3", "theta_i phi_i"),
    (lambda t: t.rsplit("\n", 2)[0] + "\n2.0000\t270.0000\n", ":15", "expected 3 numbers"),      # cut mid-row
    (lambda t: t.rsplit("\n", 3)[0] + "\n", ":13", "not a full grid"),                  # two rows cut off
    (lambda t: t.replace("1.0000\t90.0000\t2.0900", "1.0000\t90.0000\tabc"), ":9", "expected 3 numbers"),
    (lambda t: t.replace("1.0000\t90.0000\t2.0900", "1.0000\t90.0000\t-2"), ":9", "negative"),
    (lambda t: t.replace("1.0000\t90.0000", "1.0000\t0.0000"), "s.txt", "read twice"),
])
def test_rpc_bad_file_one_line_naming_file_and_line(tmp_path, edit, where, words):
    p = _small_rpc(tmp_path)
    p.write_text(edit(p.read_text()))
    with pytest.raises(InputError) as e:
        read_measured(p, wavelength_nm=633.0)
    msg = str(e.value)
    assert where in msg and words in msg and "\n" not in msg and str(p) in msg


# ====================================================================== the EDS10 measurement


@pytest.mark.shared_data
@pytest.mark.parametrize("name", list(RPC_FILES))
def test_eds10_files_read(name):
    rec = _rows(name)
    ti, pi = RPC_FILES[name]
    assert len(rec) == 86 * 360 and set(rec.side) == {"T"}
    assert np.all(rec.theta_i_deg == ti) and np.all(rec.phi_i_deg == pi)
    assert rec.theta_s_deg.min() == 0 and rec.theta_s_deg.max() == 85
    assert np.all(np.isfinite(rec.sigma_sr)) and np.all(rec.sigma_sr > 0)
    # the floor is the file's far-field noise (1e-3 1/sr), far below the generic 1e-3 of the peak
    floor = read_measured_file(EDS10 / name).noise_floor_sr
    assert 5e-4 < floor < 2e-3
    # line 4 of every file is RPC's (theta_s, phi_s) = (0, 0): the row (T, 0, 180)
    first = (EDS10 / name).read_text().splitlines()[3].split()
    k = np.nonzero((rec.theta_s_deg == 0) & (rec.phi_s_deg == 180))[0]
    assert rec.bsdf_sr[k[0]] == float(first[2])


@pytest.mark.shared_data
@pytest.mark.parametrize("name", ["EDS10 5-0.txt", "EDS10 5-45.txt"])
def test_eds10_lobe_centroid_on_the_undeviated_direction(name):
    """The mapping proven: the lobe's power centroid lands on the contract's undeviated direction
    (T, theta_i, phi_i + 180) within 0.2 deg; RPC's frame read literally (phi_s unchanged) puts it
    10 deg away, and a mirrored azimuth (phi -> 180 - phi, as an x-flip would) misses 5-45."""
    rec = _rows(name)
    w = _weights(rec)
    ti, pi = RPC_FILES[name]
    undeviated = _unit(ti, pi + 180.0)
    c = _centroid(rec, w)
    assert _angle_deg(c, undeviated) < 0.2
    literal = _centroid(rec, w, lambda p: p - 180.0)               # RPC's own azimuths
    assert _angle_deg(literal, undeviated) > 9.0
    if pi:
        mirrored = _centroid(rec, w, lambda p: 360.0 - p)          # (180 - phi_rpc) in this frame
        assert _angle_deg(mirrored, undeviated) > 5.0
    # the module's summary (shown by `relief info`) agrees with this independent computation
    lb = lobe_summary(read_measured_file(EDS10 / name).incidences[0])
    assert _angle_deg(_unit(*lb["centroid_deg"]), c) < 0.01
    assert lb["offset_deg"] < 0.2


@pytest.mark.shared_data
@pytest.mark.parametrize("name", list(RPC_FILES))
def test_eds10_top_hat_edges_plateau_and_transmittance(name):
    """Facts of the measurement, from the rows: half-maximum edges at sin(theta_i) +- 0.095
    in direction cosine along both sample axes through the undeviated direction, plateau 22-23 /sr,
    transmittance into 0-85 deg 0.88-0.90."""
    from scipy.interpolate import LinearNDInterpolator
    rec = _rows(name)
    w = _weights(rec)
    ti, pi = RPC_FILES[name]
    T = float(np.sum(rec.bsdf_sr * w))
    assert 0.88 <= T <= 0.90
    lb = lobe_summary(read_measured_file(EDS10 / name).incidences[0])
    assert lb["integral"] == pytest.approx(T, rel=1e-9)
    centre = math.sin(math.radians(ti)) * np.array([math.cos(math.radians(pi + 180)), math.sin(math.radians(pi + 180))])
    plateau = _plateau(rec, w, centre)
    assert 22.0 <= plateau <= 23.0
    a, b = _unit(rec.theta_s_deg, rec.phi_s_deg)[:, :2].T
    # linear interpolation over the readings within 15 deg; the pole's 360 repeated readings as one point
    near = (rec.theta_s_deg > 0) & (rec.theta_s_deg < 15)
    pole = rec.theta_s_deg == 0
    interp = LinearNDInterpolator(np.concatenate([np.stack([a[near], b[near]], axis=1), [[0.0, 0.0]]]),
                                  np.concatenate([rec.bsdf_sr[near], [rec.bsdf_sr[pole].mean()]]))
    s = np.linspace(-0.2, 0.2, 4001)
    for axis in (0, 1):
        pts = (centre[0] + s, np.full_like(s, centre[1])) if axis == 0 else (np.full_like(s, centre[0]), centre[1] + s)
        cut = interp(*pts)
        above = np.nonzero(cut >= 0.5 * plateau)[0]
        lo, hi = s[above[0]], s[above[-1]]
        assert np.all(cut[above[0]:above[-1] + 1] >= 0.5 * plateau)       # one lobe, no gap
        assert abs(lo + HALF_WIDTH) < 0.004 and abs(hi - HALF_WIDTH) < 0.004, (axis, lo, hi)
        assert np.all(cut[np.abs(s) <= 0.06] >= 0.85 * plateau)           # flat inside the square


# ====================================================================== measured IS-BSDF


@pytest.mark.shared_data
@pytest.mark.parametrize("name", [pytest.param(n, marks=pytest.mark.slow) if "one_wavelength" in n else n
                                  for n in ISBSDF_FILES])
def test_measured_isbsdf_files(name, tmp_path):
    side, stated = ISBSDF_FILES[name]
    path = ISBSDF / name
    assert sniff(path) == "is-bsdf"
    if stated is None:
        with pytest.raises(InputError) as e:
            read_measured(path)
        msg = str(e.value)
        assert name in msg and "--wavelength-nm" in msg and "pass wavelength_nm" not in msg
    rec = read_measured(path, wavelength_nm=None if stated else 550.0)
    assert np.all(rec.wavelength_nm == 550.0) and set(rec.side) == {side}
    assert np.all(rec.theta_s_deg >= 0) and np.all(rec.theta_s_deg <= 90)
    assert np.all(np.isfinite(rec.sigma_sr)) and np.all(rec.sigma_sr > 0)
    if stated:
        with pytest.raises(InputError, match="states 550 nm"):
            read_measured(path, wavelength_nm=633.0)
    # one row per direction (the radial-0 points of every azimuth merged): recording.csv accepts it
    back = read_recording(write_recording(tmp_path / "m.csv", rec))
    assert len(back) == len(rec)
    # the radial-0 reading of every incidence sits on the mirror / undeviated direction (side, theta_i, phi_i + 180)
    from relief_bsdf.io.isbsdf import read_isbsdf
    block = read_isbsdf(path)
    for i, ti in enumerate(block.angle_of_incidence_deg):
        k = np.nonzero((rec.theta_i_deg == ti) & np.isclose(rec.theta_s_deg, ti) & (rec.phi_s_deg == 180.0))[0]
        assert k.size == 1
        assert rec.bsdf_sr[k[0]] == pytest.approx(block.data_per_sr[0, i, :, 0].mean())


@pytest.mark.shared_data
def test_plane_symmetric_file_mirrored_and_integral_matches_stated_tis():
    """Radiant's PlaneSymmetrical measurement: rows symmetric about the plane of incidence, and the
    hemispherical integral of the rows (radial 0..80 deg about the mirror direction) within 8 % below
    the instrument's own TIS at the incidences 15-30 deg (the part beyond radial 80 is not in the file)."""
    path = ISBSDF / "test_13_planesymmetric_brdf_zemax.bsdf"
    mf = read_measured_file(path)
    from relief_bsdf.io.isbsdf import read_isbsdf
    tis = read_isbsdf(path).tis[0]
    for i, inc in enumerate(mf.incidences):
        key = {(round(t, 6), round(p, 6)): f for t, p, f in zip(inc.theta_s_deg, inc.phi_s_deg, inc.bsdf_sr)}
        for (t, p), f in key.items():
            mirror = (t, round((360.0 - p) % 360.0, 6))
            if mirror in key:
                assert key[mirror] == pytest.approx(f)
        if inc.theta_i_deg <= 30:
            ratio = lobe_summary(inc)["integral"] / tis[i]
            assert 0.92 <= ratio <= 1.0, (inc.theta_i_deg, ratio)


# ====================================================================== several files, sample.toml


def _sample_toml(tmp_path: Path, recording: str, extra: str = "") -> Path:
    np.savez(tmp_path / "relief.npz", heights=np.zeros((8, 8)), dx=1e-6, dy=1e-6)
    p = tmp_path / "sample.toml"
    p.write_text(f'''format = "relief-sample/1"
[plate]
thickness_mm = 2.0
refractive_index = 1.5
rough_face = "front"
[relief]
file = "relief.npz"
[instrument]
detector_half_angle_deg = 1.0
[recording]
file = {recording}
{extra}''')
    return p


def test_sample_with_a_list_of_rpc_files(tmp_path):
    _small_rpc(tmp_path, "a 0-0.txt", 0.0, 0.0)
    _small_rpc(tmp_path, "a 5-0.txt", 5.0, 0.0)
    p = _sample_toml(tmp_path, '["a 0-0.txt", "a 5-0.txt"]', "relative_sigma = 0.05\nwavelength_nm = 633.0\n")
    s = read_sample(p)
    assert [q.name for q in s.recording_paths] == ["a 0-0.txt", "a 5-0.txt"] and s.recording_path.name == "a 0-0.txt"
    assert s.relative_sigma == 0.05 and s.recording_wavelength_nm == 633.0
    rec = s.load_recording()
    assert len(rec) == 24 and rec.incidences() == [(0.0, 0.0), (5.0, 0.0)]
    floor = read_measured_file(tmp_path / "a 0-0.txt").noise_floor_sr
    np.testing.assert_allclose(rec.sigma_sr, np.hypot(0.05 * rec.bsdf_sr, floor))
    d = s.summary()
    assert d["recording"] == [str(tmp_path / "a 0-0.txt"), str(tmp_path / "a 5-0.txt")]
    assert [f["kind"] for f in d["recording_files"]] == ["RPC Photonics text"] * 2
    # written back and read again: the same list and keys
    from relief_bsdf.io.recording import write_sample
    back = read_sample(write_sample(tmp_path / "again.toml", s))
    assert back.recording_paths == s.recording_paths and back.relative_sigma == 0.05


def test_sample_recording_errors(tmp_path):
    _small_rpc(tmp_path, "a.txt")
    # the wavelength of an RPC file is the sample's to give: its key named, not a Python name
    s = read_sample(_sample_toml(tmp_path, '["a.txt"]'))
    with pytest.raises(InputError) as e:
        s.load_recording()
    assert "a.txt" in str(e.value) and "[recording] wavelength_nm" in str(e.value)
    for rec, extra, words in [('"a.txt"', "relative_sigma = 0\n", "relative_sigma"),
                              ('"a.txt"', "relative_sigma = 2\n", "relative_sigma"),
                              ('"a.txt"', "wavelength_nm = 5\n", "wavelength_nm"),
                              ('"a.txt"', "sigma = 0.1\n", "recording.sigma"),
                              ("[]", "", "recording.file"),
                              ('["a.txt", 3]', "", "recording.file"),
                              ('["a.txt", "missing.txt"]', "", "missing.txt")]:
        with pytest.raises(InputError) as e:
            read_sample(_sample_toml(tmp_path, rec, extra))
        assert words in str(e.value) and "sample.toml" in str(e.value), (rec, extra, str(e.value))
    # the same file twice: the duplicate rows are named with both files
    s = read_sample(_sample_toml(tmp_path, '["a.txt", "a.txt"]', "wavelength_nm = 633.0\n"))
    with pytest.raises(InputError, match="is in a.txt and a.txt"):
        s.load_recording()


def test_recording_files_mix_csv_and_measured(tmp_path):
    rpc = read_measured(_small_rpc(tmp_path, "a.txt", 0.0), wavelength_nm=633.0)
    csv = write_recording(tmp_path / "r.csv", rpc.subset(rpc.theta_s_deg == 2).with_values(np.ones(4)))
    # the csv rows collide with the RPC rows at theta_s 2: an error naming both
    with pytest.raises(InputError, match="r.csv"):
        read_recording_files([tmp_path / "a.txt", csv], wavelength_nm=633.0)
    _small_rpc(tmp_path, "b.txt", 5.0)
    both = read_recording_files([csv, tmp_path / "b.txt"], wavelength_nm=633.0)
    assert len(both) == 4 + 12
    assert np.all(np.isnan(both.sigma_sr[:4])) and np.all(both.sigma_sr[4:] > 0)   # csv: unknown stays unknown
    both = read_recording_files([csv, tmp_path / "b.txt"], wavelength_nm=633.0, relative_sigma=0.1)
    assert np.all(both.sigma_sr[:4] > 0.1 * 0.99)
    # an IS-BSDF file this project wrote is a boundary table, not a plate's measurement
    tagged = tmp_path / "t.bsdf"
    tagged.write_text("# relief: written by relief_bsdf.io.isbsdf\nSource  Measured\nScatterType BRDF\n")
    with pytest.raises(InputError, match="boundary table"):
        read_recording_files([tagged])
