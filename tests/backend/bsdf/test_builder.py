"""The one table builder (bsdf.builder): exit samples -> cells in 1/sr, delta parts, lost, sigma.

Physical truths checked: a Lambertian emitter (directions uniform in projected solid angle)
gives f = 1/pi in every cell with the binomial Monte-Carlo sigma, the cells integrate back to
the emitted power fraction, flagged exits go to the delta parts, exits outside the table's
cells and named losses go to `lost`, and Mueller columns are binned with the same weights.
"""
from __future__ import annotations

import numpy as np
import pytest

from relief_bsdf.bsdf.builder import CellAccumulator, CellIndex, ExitSamples, specular_flags
from relief_bsdf.core.frames import projected_solid_angle

TE = np.linspace(0.0, 90.0, 19)
PE = np.arange(-10.0, 360.0, 20.0)


def lambertian(n: int, rng, down: bool = False) -> np.ndarray:
    """Directions uniform in projected solid angle (cos-weighted hemisphere)."""
    u, v = rng.random(n), rng.random(n)
    s = np.sqrt(u)
    phi = 2 * np.pi * v
    d = np.column_stack([s * np.cos(phi), s * np.sin(phi), np.sqrt(1 - u)])
    if down:
        d[:, 2] *= -1
    return d


@pytest.mark.parametrize("dtype", [np.float64, np.float32])
def test_lambertian_samples_give_one_over_pi_with_binomial_sigma(dtype):
    rng = np.random.default_rng(1)
    n = 400_000
    frac_R = 0.3                                            # 30 % of the paths leave on the incidence side
    side = (rng.random(n) >= frac_R).astype(np.int8)
    d = lambertian(n, rng)
    d[side == 1, 2] *= -1
    acc = CellAccumulator(CellIndex(TE, PE))
    for lo in range(0, n, 100_000):                          # batches add up
        sl = slice(lo, lo + 100_000)
        acc.add(ExitSamples(d[sl].astype(dtype), np.ones(100_000), side[sl]))
    c = acc.table_cells(n)
    psa = projected_solid_angle(TE, PE)
    for k, frac in ((0, frac_R), (1, 1 - frac_R)):
        f = c.values_per_sr[k]
        z = (f - frac / np.pi) / c.sigma_per_sr[k]
        assert np.abs(z).max() < 5.5 and abs(z.mean()) < 0.3, (k, np.abs(z).max(), z.mean())
        p = frac * psa / np.pi                               # probability of the cell per path
        want = np.sqrt(p * (1 - p) / n) / psa                  # a sample sigma: relative noise 1 / (2 sqrt(count))
        assert np.all(np.abs(c.sigma_per_sr[k] / want - 1) < 3 / np.sqrt(n * p)), k
        assert float(np.sum(f * psa)) == pytest.approx(frac, abs=3e-3)
    assert c.lost == 0 and c.specular_R == 0 and c.specular_T == 0
    assert c.values_per_sr.dtype == np.float32


def test_delta_parts_outside_cells_and_named_losses_are_accounted():
    rng = np.random.default_rng(2)
    n = 10_000
    d = lambertian(n, rng)
    mirror = np.array([np.sin(0.5), 0.0, np.cos(0.5)])
    d[:1000] = mirror                                        # coherent reflection
    side = np.zeros(n, np.int8)
    spec = specular_flags(d, side, (mirror, None), np.cos(1e-5))
    assert spec is not None and spec.sum() == 1000
    te = np.linspace(0.0, 60.0, 13)                          # the table stops at 60 degrees
    acc = CellAccumulator(CellIndex(te, PE), lost_names=("absorbed",))
    w = np.full(n, 0.5)
    acc.add(ExitSamples(d, w, side, None, spec))
    acc.lose("absorbed", 123.0)
    c = acc.table_cells(n)
    assert c.specular_R == pytest.approx(0.5 * 1000 / n)
    outside = 0.5 * np.count_nonzero(np.degrees(np.arccos(d[1000:, 2])) > 60.0) / n
    assert c.outside_table == pytest.approx(outside)
    assert c.lost_detail == {"absorbed": pytest.approx(123.0 / n)}
    assert c.lost == pytest.approx(outside + 123.0 / n)
    inside = float(np.sum(c.values_per_sr[0] * projected_solid_angle(te, PE)))
    assert inside + c.specular_R + c.outside_table == pytest.approx(0.5, rel=1e-6)


def test_mueller_columns_are_binned_with_the_weights():
    rng = np.random.default_rng(3)
    n = 50_000
    d = lambertian(n, rng, down=True)
    side = np.ones(n, np.int8)
    w = rng.random(n)
    M = np.zeros((16, n), np.float32)
    M[0] = 1.0                                               # M00 = 1: w is the exit power
    M[1] = 0.25                                              # M01 / M00 = 0.25 everywhere
    acc = CellAccumulator(CellIndex(TE, PE), polarized=True)
    acc.add(ExitSamples(d, w, side, M))
    c = acc.table_cells(n)
    m = c.mueller_per_sr[1]
    np.testing.assert_array_equal(m[..., 0, 0], c.values_per_sr[1])
    lit = m[..., 0, 0] > 0
    np.testing.assert_allclose(m[..., 0, 1][lit] / m[..., 0, 0][lit], 0.25, rtol=1e-5)
    assert np.all(c.mueller_per_sr[0] == 0)


def test_cell_index_search_path_agrees_with_float64_angles_on_uneven_grids():
    rng = np.random.default_rng(4)
    d = lambertian(100_000, rng)
    te = np.array([0.0, 5.0, 12.0, 30.0, 31.0, 70.0, 90.0])
    pe = np.array([0.0, 10.0, 50.0, 180.0, 300.0, 360.0])
    cells = CellIndex(te, pe)
    assert not cells.fast
    th = np.degrees(np.arccos(d[:, 2]))
    ph = np.mod(np.degrees(np.arctan2(d[:, 1], d[:, 0])), 360.0)
    want = (np.searchsorted(te, th, side="right") - 1) * (pe.size - 1) + np.searchsorted(pe, ph, side="right") - 1
    assert np.mean(cells(d) == want) > 0.9999


def test_subtile_batch_means_recover_a_known_realisation_variance():
    """Paths in G groups whose cell probabilities are modulated (a tile's realisation, known
    variance) give sigma_tile = the modulation's standard error; unmodulated groups give a total
    sigma equal to the binomial one (the tile part then adds nothing beyond its noise)."""
    rng = np.random.default_rng(4)
    G, per = 64, 4000
    n = G * per
    group = np.repeat(np.arange(G), per)
    te, pe = np.linspace(0.0, 90.0, 7), np.arange(-30.0, 360.0, 60.0)
    S, A = te.size - 1, pe.size - 1
    psa = projected_solid_angle(te, pe)
    for amp in (0.0, 0.3):
        eps = 1 + amp * rng.standard_normal((G, S * A))            # per-group, per-cell modulation
        base = (psa / psa.sum()).ravel()
        p = np.clip(base[None, :] * eps, 0, None)
        p /= p.sum(axis=1, keepdims=True)
        cell = np.concatenate([rng.choice(S * A, size=per, p=p[g]) for g in range(G)])
        ring, az = np.divmod(cell, A)
        th = np.radians(0.5 * (te[ring] + te[ring + 1]))
        ph = np.radians(0.5 * (pe[az] + pe[az + 1]))
        d = np.column_stack([np.sin(th) * np.cos(ph), np.sin(th) * np.sin(ph), np.cos(th)])
        acc = CellAccumulator(CellIndex(te, pe), n_groups=G)
        acc.count_paths(group)
        acc.add(ExitSamples(d, np.ones(n), np.zeros(n, np.int8), group=group))
        c = acc.table_cells(n)
        mc = np.sqrt(base * (1 - base) / n)                         # binomial sigma of a power fraction
        tile_true = base * amp / np.sqrt(G)                         # standard error of the group modulation
        got_tile = (c.sigma_tile_per_sr[0] * psa).ravel()
        got_total = (c.sigma_per_sr[0] * psa).ravel()
        if amp == 0:
            # total ~ binomial (clipped noise of the tile part: at most a few tens of percent)
            assert np.all(got_total / mc > 0.9) and np.median(got_total / mc) < 1.25, got_total / mc
        else:
            r = got_tile / tile_true
            assert 0.8 < np.median(r) < 1.2 and r.min() > 0.6 and r.max() < 1.5, r
            assert np.all(got_total > got_tile)


def test_without_groups_sigma_is_monte_carlo_only():
    acc = CellAccumulator(CellIndex(TE, PE))
    rng = np.random.default_rng(5)
    acc.add(ExitSamples(lambertian(1000, rng), np.ones(1000), np.zeros(1000, np.int8)))
    c = acc.table_cells(1000)
    assert c.sigma_tile_per_sr is None
