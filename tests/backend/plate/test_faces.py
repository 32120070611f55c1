"""Faces of the plate (plate.faces): tables and photon interactions of the same face agree; table cache."""
from types import SimpleNamespace

import numpy as np

from relief_bsdf.plate.grid import critical_angles_deg
import pytest

from relief_bsdf.core.index import ConstantIndex, Material
from relief_bsdf.plate import (current_memory, Experiment, FlatFace, Instrument, MicrofacetFace, PhotonContext, Plate,
                               ReliefFace, TableFace, TableGrid, experiment_from_sample, in_plane_rows, simulate)
from relief_bsdf.plate.faces import TableSampler
from relief_bsdf.plate.photon import hemispherical, trace
from relief_bsdf.surface.synth import random_relief


def test_table_sampler_draws_the_tables_power_and_cosine_law(lambert_table):
    t = lambert_table("outside", 0.3, 0.6, [0, 30, 60], spec_R=0.04, spec_T=0.06)
    smp = TableSampler(t, 550.0)
    rng = np.random.default_rng(0)
    n = 200_000
    S = np.tile([1.0, 0.0, 0.0, 0.0], (n, 1))
    refl, delta, th, ph, S2 = smp.sample(np.full(n, 30.0), np.zeros(n), S, rng)
    w = S2[:, 0] / n
    assert w[refl & ~delta].sum() == pytest.approx(0.3, abs=3e-3)
    assert w[~refl & ~delta].sum() == pytest.approx(0.6, abs=3e-3)
    assert w[refl & delta].sum() == pytest.approx(0.04, abs=2e-3)
    # Lambertian: sin^2 theta uniform -> mean sin^2 = 1/2
    assert np.mean(np.sin(np.radians(th[~delta])) ** 2) == pytest.approx(0.5, abs=5e-3)


@pytest.mark.slow
def test_microfacet_face_photons_agree_with_its_tables():
    """MicrofacetFace: tables from the microfacet method (Walter 2007), photons from sampled Beckmann
    facets: two codes of the same single-scattering model, on a plate with a flat back."""
    ex = Experiment(Plate(2e-3, ConstantIndex(1.5), MicrofacetFace(0.3, samples=50_000), FlatFace()),
                    Instrument(detector_half_angle_deg=3.0))
    rows = in_plane_rows(550.0, [30.0], np.arange(4.0, 80.0, 6.0))
    grid = TableGrid(1.0, 5.0, 2.0)            # the transmitted lobe is ~20 deg wide: 2-deg cells smear its peak 10 %
    det = simulate(ex, rows, grid=grid).values_per_sr
    mc = simulate(ex, rows, engine="photon", photons=300_000, seed=2, grid=grid)
    for side in ("R", "T"):
        m = rows.side == side
        lobe = m & (det > 0.3 * det[m].max())
        rel = (mc.values_per_sr[lobe] - det[lobe]) / det[lobe]
        noise = mc.sigma_per_sr[lobe] / det[lobe]
        assert lobe.sum() >= 4
        assert np.sqrt(max(np.mean(rel**2) - np.mean(noise**2), 0.0)) < 0.04, (side, rel)
        assert abs(mc.values_per_sr[lobe].sum() / det[lobe].sum() - 1) < 0.03


def test_relief_face_tables_are_cached_by_content():
    r = random_relief(32, 0.125e-6, 30e-9, 1.0e-6, "gaussian", seed=2)
    mat = Material(ConstantIndex(1.5))
    g = TableGrid(5.0, 15.0, 15.0)
    a = ReliefFace(r, method="flat").tables(mat, g, [550.0], [0.0, 30.0])
    hits = current_memory().hits
    b = ReliefFace(r.with_heights(r.heights_m.copy(), "copy"), method="flat").tables(mat, g, [550.0], [0.0, 30.0])
    assert current_memory().hits == hits + 2 and b[1] is a[1]          # same content: same tables (both sides)
    c = ReliefFace(r.scaled(1.1), method="flat").tables(mat, g, [550.0], [0.0, 30.0])
    assert c[1] is not a[1]


def test_flat_relief_traced_face_and_fresnel_face_give_the_same_plate():
    flat = random_relief(16, 1e-6, 1e-12, 4e-6, "gaussian", seed=0).scaled(0.0)
    base = Experiment(Plate(2e-3, ConstantIndex(1.5), FlatFace(), FlatFace()))
    traced = base.with_plate(back=ReliefFace(flat, method="ray"))
    h0 = hemispherical(trace(base, 550.0, 45.0, 0.0, 50_000, np.random.default_rng(1)))
    h1 = hemispherical(trace(traced, 550.0, 45.0, 0.0, 50_000, np.random.default_rng(1)))
    assert h1["R"] == pytest.approx(h0["R"], abs=4e-3)
    assert h1["T"] + h1["lost"] == pytest.approx(h0["T"], abs=4e-3)


def test_experiment_from_sample_puts_the_relief_on_its_face():
    r = random_relief(16, 1e-6, 1e-8, 4e-6, "gaussian", seed=0)
    for face in ("front", "back"):
        sample = SimpleNamespace(path="s.toml", plate=SimpleNamespace(thickness_mm=1.5, index=ConstantIndex(1.49),
                                                                      rough_face=face, absorption_per_mm=0.2),
                                 instrument=SimpleNamespace(detector_half_angle_deg=2.0, polarization="p"))
        ex = experiment_from_sample(sample, r, method="ray")
        rough = getattr(ex.plate, face)
        assert isinstance(rough, ReliefFace) and rough.method == "ray" and rough.relief is r
        assert getattr(ex.plate, "back" if face == "front" else "front").is_flat
        assert ex.plate.thickness_m == pytest.approx(1.5e-3) and ex.plate.bulk.absorption_per_m == pytest.approx(200)
        assert ex.instrument.polarization_q == -1.0 and ex.instrument.detector_half_angle_deg == 2.0


def test_a_microfacet_faces_tables_on_threads_equal_those_of_one_process(monkeypatch):
    """THREADED_METHODS: a plate derives a microfacet face's tables on this process's threads (no worker
    pool); the numbers are those of the method run serially."""
    monkeypatch.setenv("RELIEF_WORKERS", "2")      # two threads, whatever share of the cores the suite gives
    from relief_bsdf.methods import reconstruct
    from relief_bsdf.parallel import default_workers, last_run, parallel_settings
    from relief_bsdf.plate.energy import closed
    from relief_bsdf.plate.faces import face_request
    from relief_bsdf.surface.relief import Relief
    grid = TableGrid(3.0, 15.0, 15.0)
    mat = Material(ConstantIndex(1.5))
    current_memory().drop("table")
    _, inside = MicrofacetFace(0.2).tables(mat, grid, [550.0], [0.0, 30.0], need_outside=False)
    run = last_run()
    assert run["backend"] == "serial" and run["threads"] == min(default_workers(), run["total"])
    flat = Relief(np.zeros((8, 8)), 1e-6, 1e-6, periodic=True)
    face = ReliefFace(flat, method="microfacet", samples=200_000, seed=0,
                      options={"alpha": 0.2, "distribution": "beckmann"})
    req = face_request(face, mat, grid, (550.0,), grid.inside_incidences_deg(critical_angles_deg(mat, (550.0,))), "inside")
    with parallel_settings(backend="serial"):
        (ref,) = reconstruct(flat, mat, req, "microfacet")
    ref = closed(ref)
    np.testing.assert_array_equal(inside.values_per_sr, ref.values_per_sr)


def test_the_memory_owner_holds_its_byte_budget_least_recently_used_first(lambert_table):
    """ForwardMemory with tables: entries past the byte budget (or the entry count) go, least recently
    used first; a read refreshes an entry; what holds no arrays (a verdict) counts no bytes; `holds`
    and `worth_sending` answer from the same byte count."""
    from relief_bsdf.plate.memory import ForwardMemory, deep_nbytes
    tables = [lambert_table("outside", 0.1 * (k + 1), 0.2, [0.0, 30.0]) for k in range(4)]
    size = deep_nbytes(tables[0])
    assert size > 0 and all(deep_nbytes(t) == size for t in tables)
    cache = ForwardMemory(budget_bytes=2.5 * size, maxsize=10)     # room for two tables
    cache.put(("a",), tables[0])
    cache.put(("b",), tables[1])
    cache.put(("verdict",), "ray", "other")                       # no bytes: never the reason to evict
    assert cache.held_bytes == 2 * size and cache.holds([("a",), ("b",), ("verdict",)])
    assert cache.get(("a",), lambda: None) is tables[0]           # a read: "a" is now the most recent
    cache.put(("c",), tables[2])                                  # over budget: "b" (least recent) goes
    assert not cache.holds([("b",)]) and cache.holds([("a",), ("c",)]) and cache.held_bytes == 2 * size
    cache.put(("c",), tables[3])                                  # replacing an entry does not count it twice
    assert cache.held_bytes == 2 * size and cache.get(("c",), lambda: None) is tables[3]
    assert cache.worth_sending({"x": tables[0]}) is False          # a sixth of 2.5 tables: less than one
    assert ForwardMemory(budget_bytes=6 * size).worth_sending({"x": tables[0]})
    assert not cache.holds(None) and not cache.holds([])
    small = ForwardMemory(budget_bytes=1e12, maxsize=2)            # the entry count bounds it too
    for k, t in enumerate(tables[:3]):
        small.put((k,), t)
    assert list(small._d) == [(1,), (2,)] and small.held_bytes == 2 * size
    cache.clear()
    assert cache.held_bytes == 0 and not cache.holds([("a",)])


def test_nested_recordings_each_collect_their_own_keys(lambert_table):
    """ForwardMemory.recording: a block inside another (a screen's baseline inside the screen's record)
    adds its keys to both, and each block leaves by itself even when the two sets are equal."""
    from relief_bsdf.plate.memory import ForwardMemory
    cache = ForwardMemory(budget_bytes=1e12, maxsize=10)
    t = lambert_table("outside", 0.1, 0.2, [0.0])
    with cache.recording() as outer:
        with cache.recording() as inner:
            cache.get("a", lambda: t)
        assert inner == outer == {"a"}          # equal sets: list.remove would have taken the outer one
        cache.get("b", lambda: t)
    assert outer == {"a", "b"} and inner == {"a"} and cache._recorders == []
