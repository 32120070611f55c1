"""The ray method's one bounce loop (methods.ray.transport), generic over what a ray carries.

Checked: the intensity and the Stokes carriers run the same loop with the same random numbers
(a path with one interaction has the same outcome whatever it carries, and the tables' S0
agree with the scalar tables on a relief within the Monte-Carlo noise: the only physical
difference, polarisation after the first bounce, is small at low slope).  The loop's float32
in-place kernels live in core.stokes / core.frames and are tested equal there
(tests/backend/core/test_stokes.py).
"""
from __future__ import annotations

import numpy as np

from relief_bsdf.core.index import ConstantIndex, Material
from relief_bsdf.methods import ray
from relief_bsdf.methods.request import Request
from relief_bsdf.surface.synth import random_relief

GLASS = Material(ConstantIndex(1.5))
TE = tuple(np.linspace(0.0, 90.0, 31))
PE = tuple(np.arange(-7.5, 360.0, 15.0))


def relief(slope_per_axis: float, n: int = 128, corr_px: float = 8.0):
    L = corr_px * 1e-6
    return random_relief(n, 1e-6, slope_per_axis * np.sqrt(2) * L / 2, L, seed=5)


def test_scalar_and_stokes_carriers_share_the_loop_and_its_random_numbers():
    """scatter() with and without polarisation: same seeds, same paths wherever the physics is the same."""
    tr = ray.ReliefTracer(relief(0.1))
    n = 20_000
    d = np.tile([np.sin(0.5), 0.0, -np.cos(0.5)], (n, 1))
    a = tr.scatter(d, 1.0, 1.5, np.random.default_rng(3), polarized=False)
    b = tr.scatter(d, 1.0, 1.5, np.random.default_rng(3), polarized=True)
    one = (a.bounces == 1) & (b.bounces == 1)
    assert one.mean() > 0.9                                  # low slope: mostly single interactions
    same = (a.state == b.state) & np.all(np.abs(a.dirs - b.dirs) < 1e-5, axis=1)
    assert same[one].mean() > 0.999                          # the same roulette draw decides them
    np.testing.assert_allclose(b.stokes[:, 0], b.weight)
    assert a.segments == b.segments or abs(a.segments - b.segments) < 0.01 * a.segments


def test_one_loop_scalar_and_stokes_S0_tables_agree_on_one_relief():
    r = relief(0.12)
    kw = dict(theta_i_deg=(30.0,), incident_from=("outside", "inside"), samples=100_000, seed=2,
              theta_s_edges_deg=TE, phi_s_edges_deg=PE)
    # one tile, the same entry points: like with like, Monte-Carlo sigma only
    scal = ray.reconstruct(r, GLASS, Request(options={"polarized": False, "tile_uncertainty": False}, **kw))
    pol = ray.reconstruct(r, GLASS, Request(options={"polarized": True, "tile_uncertainty": False}, **kw))
    for a, b in zip(scal, pol):
        np.testing.assert_array_equal(b.mueller_per_sr[..., 0, 0], b.values_per_sr)
        ha, hb = a.hemispherical(), b.hemispherical()
        for key in ("R", "T"):
            assert abs(float(ha[key].ravel()[0] - hb[key].ravel()[0])) < 2e-3, (a.incident_from, key)
        f, g = a.values_per_sr[0, 0, 0], b.values_per_sr[0, 0, 0]
        lobe = f > 0.2 * f.max()
        z = (g - f)[lobe] / np.hypot(a.sigma_per_sr[0, 0, 0], b.sigma_per_sr[0, 0, 0])[lobe]
        assert np.abs(z).max() < 4 and abs(z.mean()) < 0.5, (a.incident_from, np.abs(z).max(), z.mean())


def test_ray_reads_typed_options_and_refuses_a_misspelled_one():
    """The ray method reads RayOptions: a typo is a RequestError naming it, before any tracing."""
    import pytest

    from relief_bsdf.core.index import ConstantIndex, Material
    from relief_bsdf.errors import RequestError
    from relief_bsdf.methods import reconstruct
    from relief_bsdf.methods.request import Request
    from relief_bsdf.surface.synth import random_relief

    rel = random_relief(128, 1e-6, 0.3e-6, 5e-6, "gaussian", 1)
    mat = Material(inside=ConstantIndex(1.5), outside=ConstantIndex(1.0))
    with pytest.raises(RequestError, match="max_bounce"):
        reconstruct(rel, mat, Request(wavelengths_nm=(550.0,), theta_i_deg=(0.0,), samples=2000,
                                      options={"max_bounce": 3}), "ray")
    (t,) = reconstruct(rel, mat, Request(wavelengths_nm=(550.0,), theta_i_deg=(0.0,), samples=2000,
                                         options={"max_bounces": 3, "polarized": False}), "ray")
    assert t.metadata["request"]["options"]["max_bounces"] == 3 and t.mueller_per_sr is None


# ----------------------------------------------------------------------------- reuse across fit evaluations

def test_with_heights_reuses_the_topology_and_equals_a_fresh_tracer():
    from relief_bsdf.surface.mesh import build_tile_mesh
    r = relief(0.2, n=64)
    tr = ray.ReliefTracer(r)
    r2 = r.scaled(1.01).gaussian_filtered(1.5e-6)
    tr2 = tr.with_heights(r2)
    fresh = build_tile_mesh(r2)
    assert tr2.mesh.triangles is tr.mesh.triangles                      # the index buffer is reused
    np.testing.assert_array_equal(tr2.mesh.vertices, fresh.vertices)
    assert (tr2.mesh.z_min, tr2.mesh.z_max) == (fresh.z_min, fresh.z_max)
    assert set(tr2.build_split_s) == {"mesh", "embree_buffers", "bvh_commit"}
    req = Request(theta_i_deg=(40.0,), samples=20_000, seed=4, theta_s_edges_deg=TE, phi_s_edges_deg=PE)
    a = ray.reconstruct_with(tr2, r2, GLASS, req)[0]
    b = ray.reconstruct(r2, GLASS, req)[0]
    np.testing.assert_array_equal(a.values_per_sr, b.values_per_sr)
    np.testing.assert_array_equal(a.mueller_per_sr, b.mueller_per_sr)
    # raw heights on the same grid; another grid is refused
    tr3 = tr.with_heights(r2.heights_m)
    np.testing.assert_array_equal(tr3.mesh.vertices, fresh.vertices)
    import pytest
    from relief_bsdf.errors import InputError
    with pytest.raises(InputError, match="do not fit the mesh's grid"):
        tr.with_heights(relief(0.2, n=32))


def test_common_random_numbers_keep_every_unchanged_path_unchanged():
    """A given seed uses the same random numbers for every height map, per path and interaction (not a
    stream shared by the paths): after a 0.1 % height change only the paths that meet different facets
    change their outcome (a shared stream re-deals the numbers of every later path: ~7 % changed here);
    the roulette-only engine is the hardest case.  Tables then move by a fraction of another seed's scatter."""
    r = relief(0.3, n=128)
    tr = ray.ReliefTracer(r)
    r2 = r.scaled(1.001)
    tr2 = tr.with_heights(r2)
    n, th = 60_000, np.radians(50.0)
    d = np.tile([np.sin(th), 0.0, -np.cos(th)], (n, 1))
    a = tr.scatter(d, 1.0, 1.5, np.random.default_rng(3), polarized=False)
    b = tr2.scatter(d, 1.0, 1.5, np.random.default_rng(3), polarized=False)
    changed = (a.state != b.state) | (a.bounces != b.bounces)
    assert changed.mean() < 0.005, changed.mean()
    assert (a.bounces > 1).mean() > 0.01                         # paths that used roulette numbers after the first
    req = Request(theta_i_deg=(50.0,), samples=60_000, seed=9, theta_s_edges_deg=TE, phi_s_edges_deg=PE,
                  options={"polarized": False, "tile_uncertainty": False, "first_hit_split": False})
    f = ray.reconstruct_with(tr, r, GLASS, req)[0].values_per_sr[0, 0, 0]
    g = ray.reconstruct_with(tr2, r2, GLASS, req)[0].values_per_sr[0, 0, 0]
    c = ray.reconstruct_with(tr, r, GLASS, Request(theta_i_deg=(50.0,), samples=60_000, seed=10,
                                                    theta_s_edges_deg=TE, phi_s_edges_deg=PE,
                                                    options=dict(req.options)))[0].values_per_sr[0, 0, 0]
    lobe = f > 0.2 * f.max()
    assert np.sqrt(np.mean((f - g)[lobe] ** 2)) < 0.35 * np.sqrt(np.mean((f - c)[lobe] ** 2))


def test_first_interaction_columns_equal_the_core_matrices_multiplied():
    """The written-out M Rot of the identity shortcut equals core.fresnel's interface matrix times
    core.stokes' frame rotation, for reflection and transmission, below and past the critical angle."""
    from relief_bsdf.core.fresnel import interface_coefficients_f32, mueller_interface
    from relief_bsdf.core.stokes import double_angle_cd, rotation_by_angle
    from relief_bsdf.methods.ray.transport import first_interaction_columns
    rng = np.random.default_rng(2)
    n = 200
    ci = rng.uniform(0.05, 1.0, n).astype(np.float32)
    psi = rng.uniform(-180, 180, n)
    c, d = np.cos(np.radians(psi)).astype(np.float32), np.sin(np.radians(psi)).astype(np.float32)
    c2, s2 = double_angle_cd(c.copy(), d.copy())
    for n1, n2 in ((1.0, 1.5), (1.5, 1.0)):                   # from inside: TIR for ci < 0.745
        R, T = interface_coefficients_f32(ci, np.float32(n1), np.float32(n2))
        inv = np.full(n, 1.0, np.float32)
        for coef, kind in ((R, "R"), (T, "T")):
            got = first_interaction_columns(coef, c2, s2, inv)
            for i in range(0, n, 17):
                want = mueller_interface(float(ci[i]), n1, n2, kind) @ rotation_by_angle(psi[i])
                np.testing.assert_allclose(got[:, :, i], want, atol=2e-5)
    assert np.any(np.abs(R[3]) > 0.1)                           # TIR retardance was exercised


def test_direct_buffers_and_in_place_height_update_trace_like_embreex_own_mesh():
    """The numpy-written Embree buffers (methods.ray.embree_buffers) trace the paths of embreex's own
    TriangleMesh; `update_heights` (vertex z rewritten in place, BVH refitted) traces the paths of a
    tracer built from scratch on the new heights."""
    r = relief(0.3, n=96)
    direct = ray.ReliefTracer(r)
    own = ray.ReliefTracer(r, direct_buffers=False)
    assert direct.direct_buffers and not own.direct_buffers
    n, th = 40_000, np.radians(40.0)
    d = np.tile([np.sin(th), 0.0, -np.cos(th)], (n, 1))

    def trace(tr):
        return tr.scatter(d, 1.0, 1.5, np.random.default_rng(1), polarized=False)

    a, b = trace(direct), trace(own)
    assert (a.state == b.state).mean() > 0.999
    assert np.quantile(np.abs(a.dirs - b.dirs).max(axis=1), 0.999) < 1e-4   # a BVH of other quality: edge hits
    r2 = r.scaled(1.25).gaussian_filtered(1.2e-6)
    seconds = direct.update_heights(r2)
    assert seconds > 0 and direct.relief is r2
    fresh = ray.ReliefTracer(r2, direct_buffers=False)
    a2, c = trace(direct), trace(fresh)
    assert (a2.state == c.state).mean() > 0.999
    assert np.quantile(np.abs(a2.dirs - c.dirs).max(axis=1), 0.999) < 1e-4
    assert np.abs(a2.dirs - a.dirs).max() > 0.1                           # the heights really changed
    assert direct.z_top == fresh.z_top and direct.eps == fresh.eps
    import pytest
    with pytest.raises(RuntimeError, match="with_heights"):
        own.update_heights(r2)


def test_the_loop_keeps_freed_heap_under_glibc():
    """After a trace, glibc's malloc keeps freed blocks for reuse (transport.keep_freed_heap): the
    per-bounce temporaries stop paying page faults.  On another C library the call is a no-op."""
    import platform
    from relief_bsdf.methods.ray.transport import keep_freed_heap
    tr = ray.ReliefTracer(relief(0.1, n=32))
    tr.scatter(np.tile([0.0, 0.0, -1.0], (100, 1)), 1.0, 1.5, np.random.default_rng(1))
    glibc = platform.system() == "Linux" and platform.libc_ver()[0] == "glibc"
    assert keep_freed_heap() is glibc


def test_exit_columns_of_factors_equal_the_rotated_materialised_columns():
    """The exit columns computed from a first interaction's factors (the fast path: 6 numbers per ray)
    equal the reference: the 16 columns materialised, then rotated onto the exit frame by core.stokes'
    kernel - bit for bit (array_equal: only the sign of a zero may differ), below and past TIR."""
    from relief_bsdf.core.fresnel import interface_coefficients_f32
    from relief_bsdf.core.stokes import double_angle_cd, rotate_stokes_columns_cd
    from relief_bsdf.methods.ray.transport import (columns_of_factors, exit_columns_of_factors,
                                                   first_interaction_columns, first_interaction_factors)
    rng = np.random.default_rng(5)
    n = 5000
    ci = rng.uniform(0.01, 1.0, n).astype(np.float32)
    psi, psi_exit = rng.uniform(-180, 180, (2, n))
    c, d = (np.cos(np.radians(psi)) * 0.7).astype(np.float32), (np.sin(np.radians(psi)) * 0.7).astype(np.float32)
    c2, s2 = double_angle_cd(c, d)
    ce, de = np.cos(np.radians(psi_exit)).astype(np.float32), np.sin(np.radians(psi_exit)).astype(np.float32)
    ce[:7], de[:7] = 0, 0                                         # r = 0: the identity rotation
    inv = rng.uniform(0.5, 30.0, n).astype(np.float32)
    for n1, n2 in ((1.0, 1.5), (1.5, 1.0)):
        R, T = interface_coefficients_f32(ci, np.float32(n1), np.float32(n2))
        for coef in (R, T):
            F = first_interaction_factors(coef, c2, s2, inv)
            A = columns_of_factors(F)
            np.testing.assert_array_equal(A, first_interaction_columns(coef, c2, s2, inv))
            rotate_stokes_columns_cd(A, ce.copy(), de.copy())
            out = np.full((4, 4, 3 * n), np.nan, np.float32)
            exit_columns_of_factors(F, ce.copy(), de.copy(), out[:, :, n:2 * n])   # a slot of a record
            np.testing.assert_array_equal(out[:, :, n:2 * n], A)
            assert np.isnan(out[:, :, :n]).all() and np.isnan(out[:, :, 2 * n:]).all()
            assert coef is T or np.count_nonzero(A) > 0.6 * A.size     # (T past TIR is 0)
    assert np.any(np.abs(R[3]) > 0.1)                             # TIR retardance (d) was exercised


def test_factored_first_interactions_give_the_tables_of_materialised_columns(monkeypatch):
    """The Stokes carrier keeps a ray's first interaction as factors (StokesCarrier.factored); the
    tables are bit for bit those of the columns materialised at once (the reference path), with and
    without the first-hit split, from both sides (TIR, re-entering rays, several bounces), for a metal."""
    from relief_bsdf.methods.ray.transport import StokesCarrier
    metal = Material(ConstantIndex(0.2, 3.0))
    r = relief(0.45, n=96)
    both = ("outside", "inside")
    cases = [(GLASS, both, True), (GLASS, both, False), (metal, ("outside",), True)]
    names = ("values_per_sr", "sigma_per_sr", "mueller_per_sr", "specular_R", "specular_T", "lost",
             "specular_mueller_R", "specular_mueller_T")
    for mat, sides, split in cases:
        req = Request(theta_i_deg=(0.0, 35.0, 70.0), incident_from=sides, samples=30_000, seed=6,
                      theta_s_edges_deg=TE, phi_s_edges_deg=PE,
                      options={"first_hit_split": split, "max_bounces": 6, "backend": "serial"})
        fast = ray.reconstruct(r, mat, req)
        monkeypatch.setattr(StokesCarrier, "factored", False)
        ref = ray.reconstruct(r, mat, req)
        monkeypatch.setattr(StokesCarrier, "factored", True)
        for a, b in zip(fast, ref):
            assert a.mueller_per_sr is not None and np.abs(a.mueller_per_sr).max() > 0
            for name in names:
                np.testing.assert_array_equal(getattr(a, name), getattr(b, name),
                                              err_msg=f"{name} split={split} {sides}")
        mb = [t["lost"]["max_bounces"] for t in fast[0].metadata["tasks"]]
        assert split is False or mat is metal or max(mb) > 0            # rays still bouncing after 6: the loop ran deep


def test_row_helpers_equal_numpys_copies():
    """transport.take_rows keeps a broadcast basis a view with np.take's values; method._repeat_row (a
    collimated beam's directions) equals a copy of the broadcast row, C-contiguous, for any length."""
    from relief_bsdf.methods.ray.method import _repeat_row
    from relief_bsdf.methods.ray.transport import take_rows
    v = np.array([0.25, -0.5, -0.8291562], np.float32)
    for n in (0, 1, 2, 3, 5, 64, 1000, 65536 + 7):
        r = _repeat_row(v, n)
        assert r.flags.c_contiguous and r.dtype == np.float32
        np.testing.assert_array_equal(r, np.broadcast_to(v, (n, 3)))
    rng = np.random.default_rng(1)
    idx = np.flatnonzero(rng.random(500) < 0.7)
    b = np.broadcast_to(v, (500, 3))
    got = take_rows(b, idx)
    assert got.strides[0] == 0 and got.shape == (idx.size, 3)
    np.testing.assert_array_equal(got, np.take(b, idx, axis=0))
    a = rng.random((500, 3)).astype(np.float32)
    np.testing.assert_array_equal(take_rows(a, idx), a[idx])
    assert take_rows(np.zeros((0, 3), np.float32), idx[:0]).shape == (0, 3)


def test_copysign_positive_is_numpys_copysign_bit_for_bit():
    """tracer.copysign_positive (the query's slab bounds by the sign of k) gives np.copysign's bits
    for magnitudes >= 0, whatever the sign source: +-0, +-inf, NaN, denormals."""
    from relief_bsdf.methods.ray.tracer import copysign_positive
    rng = np.random.default_rng(3)
    mag = np.abs(rng.normal(size=3000)).astype(np.float32)
    mag[:4] = (0.0, np.inf, 1e-42, 3.4e38)
    sgn = rng.normal(size=3000).astype(np.float32)
    sgn[:8] = (0.0, -0.0, np.inf, -np.inf, np.nan, -np.nan, 1e-42, -1e-42)
    got, want = copysign_positive(mag, sgn), np.copysign(mag, sgn)
    assert got.dtype == np.float32
    np.testing.assert_array_equal(got.view(np.uint32), want.view(np.uint32))
