"""Each compiled kernel against its numpy twin (`relief_bsdf.kernels.REGISTRY`), directly, over the cases whole
tables rarely reach: normal and grazing incidence, the critical angle to the last float32 ulp, total internal
reflection, a facet hit along its normal (the degenerate basis), every index pair the ray method meets (air
over glass and glass under air, n = 1.3 to 1.9), NaN and infinite distances, cells on the table's edges.

Tolerance: none, bit for bit.  Each kernel does the twin's IEEE-754 operations in the twin's order (additions,
multiplications, divisions and square roots, each correctly rounded, so the same operands give the same bits),
compiled without fused multiply-adds (-ffp-contract=off, backend/setup.py), so any difference is a bug, not a
rounding.  Where two NaNs meet their payloads are not compared (no sum or comparison tells them apart).
`cells_of_directions` is the one kernel that computes otherwise (double-precision angles, numpy's float32
arccos and arctan2 only within 2e-5 rad of a cell edge): its cells must equal those of numpy's angles (its
twin) wherever it settles them, at every edge of several grids, to the last ulp of the angle.
The property-based tests draw their inputs with hypothesis, derandomised (the same examples every run).
A few physics checks of the twins against closed forms (Fresnel at normal incidence, energy, the critical
angle) keep the reference itself honest.
"""
from __future__ import annotations

import os

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from hypothesis.extra.numpy import arrays

from relief_bsdf import kernels

F32 = np.float32
PURE = os.environ.get("RELIEF_PURE_PYTHON", "") in ("1", "true", "yes")
pytestmark = pytest.mark.skipif(PURE or not kernels.available(),
                                reason="no compiled kernels (RELIEF_PURE_PYTHON=1): nothing to compare the twins with")
PROPERTY = settings(derandomize=True, database=None, deadline=None, max_examples=80,
                    suppress_health_check=[HealthCheck.too_slow, HealthCheck.data_too_large])
NS = (1.3, 1.4, 1.5, 1.6, 1.7, 1.8, 1.9)
INDEX_PAIRS = tuple((1.0, n) for n in NS)       # (n_above, n_below): air over the relief's material
ABOVE, BELOW, LEAK = 0, 1, 3


# ----------------------------------------------------------------------------- comparison


def same_bits(a, b, what: str = "") -> None:
    """a and b equal bit for bit (NaN against NaN whatever the payload)."""
    a, b = np.asarray(a), np.asarray(b)
    assert a.shape == b.shape and a.dtype == b.dtype, f"{what}: {a.shape} {a.dtype} vs {b.shape} {b.dtype}"
    if a.dtype.kind == "f":
        both_nan = np.isnan(a) & np.isnan(b)
        ua, ub = a.view(f"u{a.itemsize}"), b.view(f"u{b.itemsize}")
        bad = (ua != ub) & ~both_nan
        assert not bad.any(), f"{what}: {np.count_nonzero(bad)} differ, first at {np.argwhere(bad)[0]}: " \
                              f"{a[tuple(np.argwhere(bad)[0])]} vs {b[tuple(np.argwhere(bad)[0])]}"
    else:
        np.testing.assert_array_equal(a, b, err_msg=what)


def both(name: str, make_args):
    """Run the compiled kernel and its twin on fresh copies of make_args() (outputs written in place);
    assert that they return the same and leave every array argument the same; the twin's arguments."""
    k = kernels.REGISTRY[name]
    ac, at = make_args(), make_args()
    rc, rt = k.compiled(*ac), k.twin(*at)
    assert rc == rt or (rc is None and rt is None), f"{name}: returned {rc} vs {rt}"
    for i, (x, y) in enumerate(zip(ac, at)):
        if isinstance(x, np.ndarray):
            same_bits(x, y, f"{name} argument {i}")
    return at


def test_every_compiled_kernel_has_a_twin_and_one_rule_binds_them():
    import relief_bsdf.kernels._compiled as compiled
    public = {n for n in dir(compiled) if not n.startswith("_") and callable(getattr(compiled, n))
              and getattr(getattr(compiled, n), "__module__", "") == compiled.__name__}
    assert public == set(kernels.NAMES) == set(kernels.REGISTRY)
    prev = kernels.select("numpy")
    try:
        assert all(getattr(kernels, n) is kernels.REGISTRY[n].twin for n in kernels.NAMES)
        kernels.select("cython")
        assert all(getattr(kernels, n) is kernels.REGISTRY[n].compiled for n in kernels.NAMES)
    finally:
        kernels.select(prev)


# ----------------------------------------------------------------------------- facets: the hard angles


def critical_cos(n1: float, n2: float) -> float:
    """cos of the critical angle from n1 into n2 < n1 (float64)."""
    return float(np.sqrt(1.0 - (n2 / n1) ** 2))


def ulps_around(x: float, k: int = 3) -> np.ndarray:
    """float32 x and its k neighbours either side."""
    c = F32(x)
    out = [c]
    lo = hi = c
    for _ in range(k):
        lo, hi = np.nextafter(lo, F32(-np.inf)), np.nextafter(hi, F32(np.inf))
        out += [lo, hi]
    return np.array(sorted(out), F32)


def hard_cosines(n_above: float, n_below: float) -> np.ndarray:
    """cos i of the hard cases: normal, grazing (down to 0), the critical angle from the dense side to the
    last ulp, and ordinary ones between."""
    c = [1.0, 0.999999, 0.5, 0.1, 1e-2, 1e-4, 1e-7, 0.0]
    cs = np.concatenate([np.array(c, F32), ulps_around(critical_cos(max(n_above, n_below), min(n_above, n_below)))])
    return cs[(cs >= 0) & (cs <= 1)]


def axis_rays(cos_i: np.ndarray, below: bool):
    """Rays meeting a flat facet (Embree's normal (0, 0, 4): unnormalised by a power of two, so cos i = |k_z| exactly)
    k = (sin i, 0, -cos i) from above, (sin i, 0, cos i) from below (float32 components)."""
    ci = cos_i.astype(F32)
    si = np.sqrt(np.maximum(F32(0), F32(1) - ci * ci))
    k = np.stack([si, np.zeros_like(ci), ci if below else -ci], axis=1).astype(F32)
    ng = np.tile(np.array([0.0, 0.0, 4.0], F32), (ci.size, 1))
    return ng, k


def tilted_rays(n: int, seed: int, below: np.ndarray | None = None):
    """Rays on tilted facets (rms slope ~1) from random directions of their side, and some leaking ones."""
    rng = np.random.default_rng(seed)
    ng = np.concatenate([rng.normal(size=(n, 2)), np.abs(rng.normal(size=(n, 1))) + 0.05], axis=1)
    k = rng.normal(size=(n, 3))
    k /= np.linalg.norm(k, axis=1)[:, None]
    below = rng.random(n) < 0.5 if below is None else below
    return ng.astype(F32), k.astype(F32), below


def geometry_args(ng, k, below, n_above, n_below):
    eta_dn, eta_up = F32(n_above) / F32(n_below), F32(n_below) / F32(n_above)
    n = k.shape[0]

    def make():
        return (ng.copy(), k.copy(), below.astype(np.uint8), eta_up, eta_dn, F32(n_above), F32(n_below),
                np.full((12, n), F32(7)), np.zeros(n, np.uint8), np.zeros(n, np.uint8))
    return make


def facets(ng, k, below, n_above, n_below):
    """facet_geometry's rows and flags (both kernels give the same: asserted)."""
    a = both("facet_geometry", geometry_args(ng, k, below, n_above, n_below))
    return a[7], a[8].astype(bool), a[9].astype(bool)


@pytest.mark.parametrize("n_above, n_below", INDEX_PAIRS)
@pytest.mark.parametrize("from_below", [False, True])
def test_facet_geometry_at_normal_grazing_and_critical_incidence(n_above, n_below, from_below):
    ci = hard_cosines(n_above, n_below)
    ng, k = axis_rays(ci, from_below)
    out, tir, leak = facets(ng, k, np.full(ci.size, from_below), n_above, n_below)
    same_bits(out[6], ci, "cos i = |k_z| on a flat facet")
    assert not leak[ci > 0].any()
    n1, n2 = (n_below, n_above) if from_below else (n_above, n_below)
    # Snell in float32: TIR exactly where (1 - ci^2) (n1/n2)^2 >= 1 in float32, so a few ulps either side of
    # the critical cosine from the dense side, none from the light side
    eta = F32(n1) / F32(n2)
    expect = (F32(1) - ci * ci) * (eta * eta) >= 1
    np.testing.assert_array_equal(tir, expect)
    assert expect.any() == (n1 > n2) and (~expect).any()


@pytest.mark.parametrize("n_above, n_below", INDEX_PAIRS[::3])
def test_facet_geometry_on_tilted_facets_and_leaks(n_above, n_below):
    ng, k, below = tilted_rays(4000, 1)
    out, tir, leak = facets(ng, k, below, n_above, n_below)
    assert leak.any() and not leak.all() and tir.any()


def event_args(out, below, s, A=None, split=False):
    """facet_event's arguments from facet_geometry's rows (the engine's order)."""
    kx, ky, kz, nfx, nfy, nfz, ci, _, _, _, n1, n2 = out
    n = ci.size

    def make():
        rows = np.full((14, n), F32(-5))
        F = (np.full((6, n), F32(9)), np.full((6, n), F32(9))) if split else (None, None)
        return (nfx.copy(), nfy.copy(), nfz.copy(), kx.copy(), ky.copy(), kz.copy(), s.copy(), ci.copy(),
                n1.copy(), n2.copy(), None if A is None else A.copy(), np.full((n, 3), F32(-3)), rows[11:14],
                rows[0], rows[1], rows[2:6], rows[6:10], rows[10], *F)
    return make


def s_axes(k: np.ndarray, seed: int) -> np.ndarray:
    """A unit s-axis normal to each k (a random one: any basis the rays carry)."""
    rng = np.random.default_rng(seed)
    v = rng.normal(size=k.shape)
    s = np.cross(k.astype(np.float64), v)
    return (s / np.linalg.norm(s, axis=1)[:, None]).astype(F32)


@pytest.mark.parametrize("n_above, n_below", INDEX_PAIRS)
@pytest.mark.parametrize("from_below", [False, True])
@pytest.mark.parametrize("mode", ["identity", "columns", "split"])
def test_facet_event_at_the_hard_angles(n_above, n_below, from_below, mode):
    ci = hard_cosines(n_above, n_below)
    ng, k = axis_rays(ci, from_below)
    ng2, k2, b2 = tilted_rays(500, 2, np.full(500, from_below))
    ng, k = np.concatenate([ng, ng2]), np.concatenate([k, k2])
    below = np.full(k.shape[0], from_below)
    out, _, leak = facets(ng, k, below, n_above, n_below)
    keep = np.flatnonzero(~leak)
    out = np.ascontiguousarray(out[:, keep])
    s = s_axes(k[keep], 3)
    A = np.random.default_rng(4).normal(size=(4, 4, keep.size)).astype(F32) if mode == "columns" else None
    both("facet_event", event_args(out, below[keep], s, A, split=mode == "split"))


def test_facet_event_keeps_the_basis_at_normal_incidence():
    """k along the facet's normal: |n x k| < 1e-6, the old s kept (the degenerate branch) in both."""
    ng, k = axis_rays(np.array([1.0, 1.0, 0.9999999], F32), False)
    out, _, _ = facets(ng, k, np.zeros(3, bool), 1.0, 1.5)
    s = np.array([[1, 0, 0], [0, 1, 0], [0.6, 0.8, 0]], F32)
    a = both("facet_event", event_args(out, np.zeros(3, bool), s))
    same_bits(a[11][:2], s[:2], "the basis kept")


@PROPERTY
@given(data=st.data())
def test_facet_kernels_agree_on_any_facet_and_direction(data):
    n = data.draw(st.integers(1, 40))
    comp = st.floats(-1, 1, width=32)
    ng = data.draw(arrays(F32, (n, 3), elements=comp))
    k = data.draw(arrays(F32, (n, 3), elements=comp))
    below = data.draw(arrays(np.bool_, n))
    n_above, n_below = data.draw(st.sampled_from(INDEX_PAIRS))
    out, _, _ = facets(ng, k, below, n_above, n_below)
    mode = data.draw(st.sampled_from(["identity", "columns", "split"]))
    A = data.draw(arrays(F32, (4, 4, n), elements=st.floats(-2, 2, width=32))) if mode == "columns" else None
    s = data.draw(arrays(F32, (n, 3), elements=comp))
    with np.errstate(all="ignore"):
        both("facet_event", event_args(np.ascontiguousarray(out), below, s, A, split=mode == "split"))


# ----------------------------------------------------------------------------- the twins' physics


@pytest.mark.parametrize("n", NS)
def test_twin_fresnel_meets_the_closed_forms(n):
    """The reference itself: R at normal incidence ((n1 - n2) / (n1 + n2))^2 to float32 rounding (a few ulps
    of the ~12 operations: rel 1e-6), R + T = 1 below the critical angle (T = 1 - R: one rounding, 2^-24),
    R = 1 and T = 0 from the critical angle on."""
    for n1, n2 in ((1.0, n), (n, 1.0)):
        ci = np.concatenate([[1.0], hard_cosines(n1, n2)]).astype(F32)
        m = ci.size
        R, T, pR = np.zeros((4, m), F32), np.zeros((4, m), F32), np.zeros(m, F32)
        z = np.zeros(m, F32)
        kernels.twins.facet_event(z, z, np.ones(m, F32), z + F32(0.3), z, -ci, np.tile(np.array([0, 1, 0], F32), (m, 1)),
                                  ci, np.full(m, F32(n1)), np.full(m, F32(n2)), None, np.zeros((m, 3), F32),
                                  np.zeros((3, m), F32), z.copy(), z.copy(), R, T, pR)
        assert R[0, 0] == pytest.approx(((n1 - n2) / (n1 + n2)) ** 2, rel=1e-6)
        sin2t = (F32(n1) / F32(n2)) ** 2 * (F32(1) - ci * ci)
        tir = sin2t >= 1
        np.testing.assert_allclose((R[0] + T[0])[~tir], 1.0, atol=2.0**-23)
        assert np.all(R[0][tir] == 1) and np.all(T[:, tir] == 0)
        assert tir.any() == (n1 > n2)
        assert np.all((pR >= 0) & (pR <= 1))


# ----------------------------------------------------------------------------- first interaction, exits


@pytest.mark.parametrize("n_above, n_below", INDEX_PAIRS[::2])
@pytest.mark.parametrize("tag", [False, True])
def test_split_kernels_at_the_hard_angles(n_above, n_below, tag):
    ci = hard_cosines(n_above, n_below)
    ng, k = axis_rays(ci, True)
    ng2, k2, b2 = tilted_rays(300, 5)
    ng, k = np.concatenate([ng, ng2]), np.concatenate([k, k2])
    below = np.concatenate([np.ones(ci.size, bool), b2])
    out, _, leak = facets(ng, k, below, n_above, n_below)
    keep = np.flatnonzero(~leak)
    out, below = np.ascontiguousarray(out[:, keep]), below[keep]
    n = keep.size
    rng = np.random.default_rng(6)
    o = rng.uniform(-1e-5, 1e-5, (n, 3)).astype(F32)
    th = rng.uniform(0, 2e-6, n).astype(F32)
    ids = rng.permutation(n).astype(np.int64)
    grid = (F32(1e-5), F32(1e-5), F32(1e-5), F32(1e-5), F32(4) / F32(2e-5), F32(3) / F32(2e-5), False, 4, 3)
    kx, ky, kz, nfx, nfy, nfz, ci_, ct, eta = out[:9]

    def make():
        return (kx.copy(), ky.copy(), kz.copy(), nfx.copy(), nfy.copy(), nfz.copy(), eta.copy(), ci_.copy(),
                ct.copy(), th.copy(), o.copy(), F32(2e-12), np.zeros((n, 3), F32), *(np.zeros((n, 3), F32)
                                                                                    for _ in range(4)),
                grid if tag else None, ids if tag else None, np.full(n, -1, np.int32) if tag else None)
    both("split_rays", make)
    pR = np.concatenate([[0.0, 1.0, 1.0, 0.5], rng.random(n - 4)]).astype(F32)   # TIR: P_R = 1

    def make_w():
        return (rng_w.copy(), pR.copy(), below.astype(np.uint8), ids.copy(), np.arange(n, dtype=np.int16) % 7,
                n, np.zeros(n, F32), np.zeros(n, F32), np.zeros(n, np.uint8), np.zeros(n, np.int64),
                np.zeros(n, np.int16))
    rng_w = rng.random(n).astype(F32)
    both("split_weights", make_w)


def exit_args(n: int, seed: int, factored: bool, gather: bool, compact: bool):
    rng = np.random.default_rng(seed)
    k = rng.normal(size=(n, 3))
    k[:5] = [[0, 0, 1], [0, 0, -1], [1e-8, 0, 1], [0, -1e-9, -1], [1e-6, 1e-6, 1]]    # along z and nearly
    k = (k / np.linalg.norm(k, axis=1)[:, None]).astype(F32)
    m = 2 * n
    s = s_axes(rng.normal(size=(m, 3)), seed + 1)
    F = rng.normal(size=(6, m)).astype(F32)
    F[4:6] /= np.sqrt(F[4] ** 2 + F[5] ** 2)                         # (cos 2psi, sin 2psi)
    A = rng.normal(size=(4, 4, m)).astype(F32)
    idx = rng.choice(m, n, replace=False).astype(np.int64) if gather else None
    if not gather:
        s, F, A = s[:n].copy(), np.ascontiguousarray(F[:, :n]), np.ascontiguousarray(A[:, :, :n])

    def make():
        return (F.copy() if factored else None, None if factored else A.copy(), s.copy(), k.copy(), idx,
                np.full((4, 4, n), F32(5)), 1e-14, np.full(n, 7, np.uint8) if compact else None)
    return make


@pytest.mark.parametrize("factored", [True, False])
@pytest.mark.parametrize("gather", [True, False])
@pytest.mark.parametrize("compact", [True, False])
def test_exit_columns_along_z_and_off_it(factored, gather, compact):
    a = both("exit_columns", exit_args(300, 7, factored, gather, compact))
    if factored and compact:                                          # the compact records expand alike
        M = a[5].reshape(16, -1)
        both("expand_compact", lambda: (M.copy(), a[7].copy(), None))
        both("expand_compact", lambda: (M.copy(), a[7].copy(), np.arange(0, 300, 3, dtype=np.int64)))


# ----------------------------------------------------------------------------- binning


CELLS_S, CELLS_A = 30, 24


def cell_case(seed: int, n: int, grouped: bool, by_path: bool, polar: bool, compact: bool, start_zero: bool):
    rng = np.random.default_rng(seed)
    nc = 2 * CELLS_S * CELLS_A
    cell = rng.integers(-1, nc, n).astype(np.int32)
    cell[:3] = [0, nc - 1, -1]
    w = (rng.random(n) * 3).astype(F32)
    w[:2] = [0.0, 1e-30]
    M = rng.normal(size=(16, n)).astype(F32)
    flags = (rng.random(n) < 0.5).astype(np.uint8) if compact else None
    n_paths = n // 2 + 1
    group = rng.integers(0, 16, n_paths if by_path else n).astype(np.int32)
    pids = rng.integers(0, 2 * n_paths, n).astype(np.int64)
    sums = [np.zeros(nc), np.zeros(nc), np.zeros((nc, 16))]
    if not start_zero:
        sums = [s + rng.normal(size=s.shape) for s in sums]

    def make():
        return (cell.copy(), w.copy(), M.copy() if polar else None, *(s.copy() for s in sums),
                group.copy() if grouped else None, np.zeros(n, np.int32) if grouped else None,
                np.zeros(n, F32) if grouped else None, flags.copy() if compact else None,
                pids.copy() if by_path else None, n_paths if by_path else 0)
    return make


@pytest.mark.parametrize("grouped, by_path", [(False, False), (True, False), (True, True)])
@pytest.mark.parametrize("polar, compact", [(False, False), (True, False), (True, True)])
@pytest.mark.parametrize("start_zero", [True, False])
def test_bin_cells_into_empty_and_filled_sums(grouped, by_path, polar, compact, start_zero):
    both("bin_cells", cell_case(8, 3000, grouped, by_path, polar, compact, start_zero))


@pytest.mark.parametrize("key_t, w_t", [(np.int32, F32), (np.int64, np.float64), (np.int32, np.float64)])
def test_add_at_adds_repeated_keys_in_order(key_t, w_t):
    rng = np.random.default_rng(9)
    keys = rng.integers(0, 50, 5000).astype(key_t)
    w = (rng.random(5000) * 10.0 ** rng.integers(-8, 8, 5000)).astype(w_t)       # sums that round differently
    out = rng.normal(size=50)                                                      # in another order
    both("add_at", lambda: (keys.copy(), w.copy(), out.copy()))


def cell_index_args(k: np.ndarray, side: np.ndarray):
    from relief_bsdf.bsdf.builder import CellIndex
    ci = CellIndex(tuple(np.linspace(0.0, 90.0, CELLS_S + 1)), tuple(np.arange(-7.5, 360.0, 15.0)))
    n = k.shape[0]
    parts = both("direction_parts", lambda: (k.copy(), np.zeros(n, F32), np.zeros(n, F32), np.zeros(n, F32)))
    x = np.arccos(parts[1])
    y = np.arctan2(parts[3], parts[2])
    return lambda: (x.copy(), y.copy(), ci.t_scale, ci.t_off, ci.p_scale, ci.p_off, ci.ring_lut, ci.az_lut, ci.A,
                    side.astype(np.int8), ci.S * ci.A, np.zeros(n, np.int32))


def test_cells_of_directions_on_the_edges_and_beyond():
    """Directions on ring and azimuth edges (float32 rounding of the edge angles either way), along z,
    in the plane, |k_z| slightly above 1, NaN."""
    th = np.radians(np.concatenate([np.linspace(0, 90, CELLS_S + 1), np.linspace(0, 90, 7)]))
    ph = np.radians(np.concatenate([np.arange(-7.5, 360.0, 15.0), [0.0, 180.0, -180.0]]))
    T, P = np.meshgrid(th, ph)
    k = np.stack([np.sin(T) * np.cos(P), np.sin(T) * np.sin(P), np.cos(T)], axis=-1).reshape(-1, 3)
    k = np.concatenate([k, k * [1, 1, -1]]).astype(F32)
    k = np.concatenate([k, [[0, 0, 1.0000001], [0, 0, -1.0000001], [np.nan, 0, 1], [0, np.nan, np.nan],
                            [1, 0, 0], [-1, 0, 0], [0, -1, 0]]]).astype(F32)
    side = (k[:, 2] < 0).astype(np.int8)
    with np.errstate(invalid="ignore"):
        both("cells_of_angles", cell_index_args(k, side))


@PROPERTY
@given(k=arrays(F32, st.tuples(st.integers(1, 60), st.just(3)), elements=st.floats(-1.5, 1.5, width=32)))
def test_cells_of_any_direction(k):
    with np.errstate(invalid="ignore", divide="ignore"):
        both("cells_of_angles", cell_index_args(k, (k[:, 2] < 0).astype(np.int8)))



def edge_directions(cells, n_per_edge: int = 9) -> np.ndarray:
    """Unit float32 directions whose polar angle or azimuth sits on a cell edge of `cells` (CellIndex) and
    on its float32 neighbours (the angle the float32 look-up sees: edge +- a few ulps), both hemispheres."""
    te, pe = np.radians(cells.te), np.radians(cells.pe)
    out = []
    rng = np.random.default_rng(15)
    for th in te:
        for d in np.linspace(-3e-6, 3e-6, n_per_edge):
            ph = rng.uniform(-np.pi, np.pi, 4)
            t = th + d
            out.append(np.stack([np.sin(t) * np.cos(ph), np.sin(t) * np.sin(ph), np.cos(t) * np.ones(4)], 1))
    for ph in pe:
        for d in np.linspace(-3e-6, 3e-6, n_per_edge):
            t = rng.uniform(0, np.pi / 2, 4)
            p = ph + d
            out.append(np.stack([np.sin(t) * np.cos(p), np.sin(t) * np.sin(p), np.cos(t)], 1))
    k = np.concatenate(out)
    k = np.concatenate([k, k * [1, 1, -1], [[0, 0, 1], [0, 0, -1], [1, 0, 0], [-1, 0, 0], [0, 1, 0], [0, -1, 0],
                                            [-1, -0.0, 0], [np.nan, 0, 1], [0.3, 0.2, 1.0000001]]])
    return k.astype(F32)


def directions_args(k: np.ndarray, cells):
    from relief_bsdf.bsdf.builder import ANGLE_MARGIN_RAD
    n = k.shape[0]
    side = (k[:, 2] < 0).astype(np.int8)
    return lambda: (k.copy(), cells.t_scale, cells.t_off, cells.p_scale, cells.p_off, cells.ring_lut, cells.az_lut,
                    cells.A, side.copy(), cells.S * cells.A, ANGLE_MARGIN_RAD, np.zeros(n, np.int32),
                    np.zeros(n, np.int64))


def same_cells_where_settled(k: np.ndarray, cells) -> np.ndarray:
    """`cells_of_directions`: the compiled kernel's cells equal its twin's (numpy's float32 angles) for every
    direction it settles, and it lists exactly those it leaves (out -2) in exact; the twin settles all.
    The mask of the directions left to numpy's angles."""
    k_ = kernels.REGISTRY["cells_of_directions"]
    ac, at = directions_args(k, cells)(), directions_args(k, cells)()
    with np.errstate(invalid="ignore", divide="ignore"):
        ne, nt = k_.compiled(*ac), k_.twin(*at)
    out_c, out_t = ac[-2], at[-2]
    left = out_c == -2
    assert nt == 0 and not (out_t == -2).any()
    np.testing.assert_array_equal(np.sort(ac[-1][:ne]), np.flatnonzero(left))
    np.testing.assert_array_equal(out_c[~left], out_t[~left])
    return left


GRIDS = ((np.linspace(0.0, 90.0, 31), np.arange(-7.5, 360.0, 15.0)),
         (np.linspace(0.0, 90.0, 91), np.arange(0.0, 360.1, 5.0)),
         (np.linspace(10.0, 80.0, 15), np.arange(-30.0, 30.1, 2.5)))            # part of the sphere only


@pytest.mark.parametrize("grid", range(len(GRIDS)))
def test_cells_of_directions_at_the_edges_equals_the_float32_angles(grid):
    """The cells without numpy's arccos and arctan2 (`kernels.cells_of_directions` and `CellIndex.with_side`)
    are those of numpy's float32 angles (`_cells_of_numpy_angles`), for directions on every edge to the last
    ulps: the kernel leaves these to numpy (it cannot tell), so they take the same path; and for directions
    away from the edges, which it settles alone."""
    from relief_bsdf.bsdf.builder import CellIndex
    cells = CellIndex(tuple(GRIDS[grid][0]), tuple(GRIDS[grid][1]))
    assert cells.fast
    rng = np.random.default_rng(16)
    r = rng.normal(size=(20000, 3))
    edges = edge_directions(cells)
    k = np.concatenate([edges, (r / np.linalg.norm(r, axis=1)[:, None])]).astype(F32)
    left = same_cells_where_settled(k, cells)
    m = edges.shape[0]
    # nearly all edge directions (within 3e-6 rad of an edge < the margin), few random ones (those within the
    # margin of an edge: a fraction ~ 2 margin x edges / range, < 1 %)
    assert np.count_nonzero(left[:m]) > 0.9 * m and np.count_nonzero(left[m:]) < 0.01 * (k.shape[0] - m)
    side = (k[:, 2] < 0).astype(np.int8)
    with np.errstate(invalid="ignore"):
        same_bits(cells.with_side(k, side), cells._cells_of_numpy_angles(k, side), "cells")


@PROPERTY
@given(k=arrays(F32, st.tuples(st.integers(1, 60), st.just(3)), elements=st.floats(-1.5, 1.5, width=32)),
       grid=st.sampled_from(range(len(GRIDS))))
def test_cells_of_directions_of_any_direction(k, grid):
    from relief_bsdf.bsdf.builder import CellIndex
    cells = CellIndex(tuple(GRIDS[grid][0]), tuple(GRIDS[grid][1]))
    same_cells_where_settled(k, cells)
    side = (k[:, 2] < 0).astype(np.int8)
    with np.errstate(invalid="ignore", divide="ignore"):
        same_bits(cells.with_side(k, side), cells._cells_of_numpy_angles(k, side), "cells")


# graded edges (a relief-scale request: fine rings, azimuths of 1 and 5 degrees), searched by the builder
SEARCHED_GRIDS = ((np.concatenate([np.linspace(0.0, 10.0, 61), np.linspace(10.5, 90.0, 160)]),
                   np.concatenate([np.arange(-2.5, 3.0, 1.0), np.arange(7.5, 358.0, 5.0)])),
                  (np.concatenate([np.linspace(5.0, 40.0, 8), [42.0, 47.0, 60.0, 80.0]]),     # part of the sphere
                   np.array([-30.0, -10.0, -2.0, 0.0, 3.0, 25.0])),
                  (np.concatenate([[0.0, 0.25, 1.0], np.linspace(2.0, 90.0, 45)]),
                   np.array([350.0, 352.0, 355.0, 360.0, 370.0, 400.0, 500.0, 700.0])))   # edges past 360


def searched_args(k: np.ndarray, cells):
    from relief_bsdf.methods.ray.cells import MARGIN_DEG
    n = k.shape[0]
    side = (k[:, 2] < 0).astype(np.int8)
    return lambda: (k.copy(), cells.te_sin2, cells.last_ring, cells.lut_t, cells.scale_t, cells.pe_rel, cells.lut_p,
                    cells.scale_p, float(cells.pe[0]), MARGIN_DEG, side.copy(), cells.S * cells.A,
                    np.zeros(n, np.int32), np.zeros(n, np.int64))


def same_searched_cells_where_settled(k: np.ndarray, cells) -> np.ndarray:
    """`cells_of_edges`: the compiled kernel's cells equal its twin's (numpy's searches, numpy's float32 arctan2)
    for every direction it settles, and it lists exactly those it leaves (out -2); the twin settles all.  The
    mask of the directions left to numpy."""
    k_ = kernels.REGISTRY["cells_of_edges"]
    ac, at = searched_args(k, cells)(), searched_args(k, cells)()
    with np.errstate(invalid="ignore", divide="ignore"):
        ne, nt = k_.compiled(*ac), k_.twin(*at)
    out_c, out_t = ac[-2], at[-2]
    left = out_c == -2
    assert nt == 0 and not (out_t == -2).any()
    np.testing.assert_array_equal(np.sort(ac[-1][:ne]), np.flatnonzero(left))
    np.testing.assert_array_equal(out_c[~left], out_t[~left])
    return left


@pytest.mark.parametrize("grid", range(len(SEARCHED_GRIDS)))
def test_cells_of_searched_edges_at_the_edges_equal_numpys(grid):
    """The cells of graded edges in one compiled pass (`kernels.cells_of_edges`, `methods.ray.cells.SearchedCells`)
    are the builder's (`CellIndex.with_side`: searches on sin^2 theta and on numpy's float32 azimuth), for
    directions on every edge to the last ulps (the ring exactly; the azimuths within the margin of an edge left
    to numpy) and for directions away from the edges, which the kernel settles alone."""
    from relief_bsdf.bsdf.builder import CellIndex
    from relief_bsdf.methods.ray.cells import SearchedCells
    te, pe = tuple(SEARCHED_GRIDS[grid][0]), tuple(SEARCHED_GRIDS[grid][1])
    cells, ref = SearchedCells(te, pe), CellIndex(te, pe)
    assert cells.searched and not ref.fast
    rng = np.random.default_rng(17)
    r = rng.normal(size=(20000, 3))
    edges = edge_directions(cells)
    k = np.concatenate([edges, (r / np.linalg.norm(r, axis=1)[:, None])]).astype(F32)
    left = same_searched_cells_where_settled(k, cells)
    m = edges.shape[0]
    # the azimuth edges' directions are left to numpy (within 3e-6 rad of an edge < the margin) where their ring
    # is in the table; few random ones are (within the margin of an azimuth edge: < 1 %)
    assert np.count_nonzero(left[m:]) < 0.01 * (k.shape[0] - m) and np.count_nonzero(left[:m]) > 0
    side = (k[:, 2] < 0).astype(np.int8)
    with np.errstate(invalid="ignore", divide="ignore"):
        same_bits(cells.with_side(k, side), ref.with_side(k, side), "cells")


@PROPERTY
@given(k=arrays(F32, st.tuples(st.integers(1, 60), st.just(3)), elements=st.floats(-1.5, 1.5, width=32)),
       grid=st.sampled_from(range(len(SEARCHED_GRIDS))))
def test_cells_of_searched_edges_of_any_direction(k, grid):
    from relief_bsdf.bsdf.builder import CellIndex
    from relief_bsdf.methods.ray.cells import SearchedCells
    te, pe = tuple(SEARCHED_GRIDS[grid][0]), tuple(SEARCHED_GRIDS[grid][1])
    cells = SearchedCells(te, pe)
    same_searched_cells_where_settled(k, cells)
    side = (k[:, 2] < 0).astype(np.int8)
    with np.errstate(invalid="ignore", divide="ignore"):
        same_bits(cells.with_side(k, side), CellIndex(te, pe).with_side(k, side), "cells")


def test_searched_cells_count_tables_start_at_or_below_every_count():
    """The look-up tables of the searches never start a count past the edges <= a value in their bucket (the
    count then goes on from there: exact), on the buckets' bounds and just below them."""
    from relief_bsdf.methods.ray.cells import SearchedCells
    cells = SearchedCells(tuple(SEARCHED_GRIDS[0][0]), tuple(SEARCHED_GRIDS[0][1]))
    for edges, lut, scale in ((cells.te_sin2, cells.lut_t, cells.scale_t), (cells.pe_rel, cells.lut_p, cells.scale_p)):
        j = np.arange(lut.size)
        for v in (j / scale, np.nextafter(j / scale, -np.inf), (j + 0.5) / scale):
            v = v[v >= 0]
            b = np.clip((v * scale).astype(np.int64), 0, lut.size - 1)
            assert np.all(lut[b] <= np.searchsorted(edges, v, side="right"))

@PROPERTY
@given(dirs=arrays(F32, st.tuples(st.integers(0, 60), st.just(3)), elements=st.floats(-1, 1, width=32)),
       a=st.tuples(*[st.floats(-1, 1, width=32)] * 3), b=st.tuples(*[st.floats(-1, 1, width=32)] * 3),
       cos_min=st.floats(-1, 1, width=32))
def test_near_directions(dirs, a, b, cos_min):
    n = dirs.shape[0]
    both("near_direction", lambda: (dirs.copy(), *a, cos_min, np.zeros(n, np.int64)))
    both("near_two_directions", lambda: (dirs.copy(), *a, *b, cos_min, np.zeros(n, np.int64), np.zeros(n, np.int64)))


def test_near_directions_at_the_threshold():
    """Directions whose float32 dot product with the mirror direction is cos_min and its neighbours."""
    d = np.array([0.5, 0.0, np.sqrt(0.75)], F32)
    rng = np.random.default_rng(10)
    dirs = (d + rng.normal(size=(20000, 3)) * rng.choice([0.0, 1e-7, 1e-5, 1e-3], (20000, 1))).astype(F32)
    c = F32(0.9999)
    n = dirs.shape[0]
    a = both("near_direction", lambda: (dirs.copy(), *d, c, np.zeros(n, np.int64)))
    assert 0 < a[-1].size


# ----------------------------------------------------------------------------- geometry of a batch


HX, HY, ZH, ZC = F32(1e-5), F32(1.2e-5), F32(2e-6), F32(-1e-7)


def slab_rays(n: int, seed: int):
    """Origins inside, on the sides and faces of the slab; directions with zero components (infinite and NaN
    distances: 0 / 0 for a ray on a side moving along it), grazing and steep."""
    rng = np.random.default_rng(seed)
    o = np.stack([rng.uniform(-HX, HX, n), rng.uniform(-HY, HY, n), rng.uniform(ZC - ZH, ZC + ZH, n)], axis=1)
    k = rng.normal(size=(n, 3))
    o[:6] = [[HX, 0, ZC], [-HX, -HY, ZC + ZH], [0, HY, ZC - ZH], [HX, HY, ZC], [0, 0, ZC], [HX, 0, 0]]
    k[:8] = [[0, 0, 1], [1, 0, 0], [0, 1, 0], [0, 0, -1], [1e-30, 0, 1], [0, 0, 0], [-1, 1, 1e-9], [1, 1, 0]]
    return o.astype(F32), k.astype(F32)


def test_slab_distances_and_far_limits():
    o, k = slab_rays(2000, 11)
    n = k.shape[0]
    with np.errstate(all="ignore"):
        both("slab_far", lambda: (o.copy(), k.copy(), HX, HY, ZH, ZC, np.zeros(n, F32), np.zeros(n, np.uint8)))
        both("slab_distances", lambda: (o.copy(), k.copy(), HX, HY, ZH, ZC, np.zeros((3, n), F32),
                                        np.zeros(n, F32), np.zeros(n, F32)))


@PROPERTY
@given(o=arrays(F32, (24, 3), elements=st.floats(-float(F32(2e-5)), float(F32(2e-5)), width=32)),
       k=arrays(F32, (24, 3), elements=st.floats(-1, 1, width=32)))
def test_slab_kernels_on_any_ray(o, k):
    with np.errstate(all="ignore"):
        both("slab_far", lambda: (o.copy(), k.copy(), HX, HY, ZH, ZC, np.zeros(24, F32), np.zeros(24, np.uint8)))
        both("slab_distances", lambda: (o.copy(), k.copy(), HX, HY, ZH, ZC, np.zeros((3, 24), F32),
                                        np.zeros(24, F32), np.zeros(24, F32)))


@PROPERTY
@given(hit=arrays(np.uint8, 40, elements=st.integers(0, 1)), lat=arrays(np.uint8, 40, elements=st.integers(0, 1)),
       kz=arrays(F32, 40, elements=st.floats(-1, 1, width=32)), below=arrays(np.uint8, 40, elements=st.integers(0, 1)))
def test_classify_misses(hit, lat, kz, below):
    k = np.stack([np.zeros(40, F32), np.zeros(40, F32), kz], axis=1)
    both("classify_misses", lambda: (hit.copy(), lat.copy(), k.copy(), below.copy(), ABOVE, BELOW, LEAK,
                                     np.zeros(40, np.int64), np.zeros(40, np.int8), np.zeros(40, np.int64)))


def test_beam_origins():
    rng = np.random.default_rng(12)
    n = 5000
    ix, iy = rng.integers(0, 1000, n).astype(np.int64), rng.integers(0, 700, n).astype(np.int64)
    jit = rng.random((n, 2))
    jit[:2] = [[0.0, 0.0], [np.nextafter(1.0, 0.0)] * 2]
    both("beam_origins", lambda: (ix, iy, jit, 1e-8, float(F32(5e-6)), 1.3e-8, float(F32(4.55e-6)), F32(3e-7),
                                  np.zeros((n, 3), F32)))


@pytest.mark.parametrize("mirrored", [False, True])
def test_subtile_index_on_edges_and_beyond(mirrored):
    rng = np.random.default_rng(13)
    p = np.stack([rng.uniform(-1.3 * HX, 1.3 * HX, 5000), rng.uniform(-1.3 * HY, 1.3 * HY, 5000)], axis=1)
    p[:6] = [[HX, HY], [-HX, -HY], [0, 0], [HX / 2, -HY / 2], [np.nan, 0], [np.inf, -np.inf]]
    p = p.astype(F32)
    half_x, half_y = HX, HY
    scale = (F32(4) / half_x, F32(3) / half_y) if mirrored else (F32(4) / (2 * HX), F32(3) / (2 * HY))
    with np.errstate(invalid="ignore"):
        both("subtile_index", lambda: (p.copy(), HX, HY, half_x, half_y, *scale, mirrored, 4, 3,
                                       np.zeros(5000, np.int32)))


# ----------------------------------------------------------------------------- gathers


def test_gathers():
    rng = np.random.default_rng(14)
    n, m = 3000, 1000
    o, k = rng.normal(size=(n, 3)).astype(F32), rng.normal(size=(n, 3)).astype(F32)
    below, w = (rng.random(n) < 0.5).astype(np.uint8), rng.random(n).astype(F32)
    nb, ids = rng.integers(0, 100, n).astype(np.int16), rng.integers(0, 1 << 40, n).astype(np.int64)
    idx = np.sort(rng.choice(n, m, replace=False)).astype(np.int64)
    both("gather_records", lambda: (idx, k, w, nb, ids, np.zeros((m, 3), F32), np.zeros(m, F32),
                                    np.zeros(m, np.int16), np.zeros(m, np.int64)))
    both("gather_rays", lambda: (idx, o, k, below, w, nb, ids, np.zeros((m, 3), F32), np.zeros((m, 3), F32),
                                 np.zeros(m, np.uint8), np.zeros(m, F32), np.zeros(m, np.int16),
                                 np.zeros(m, np.int64)))
