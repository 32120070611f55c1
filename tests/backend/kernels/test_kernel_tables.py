"""Compiled ray kernels (`relief_bsdf.kernels`) against their numpy twins, whole tables: the same bit for bit.

Each compiled kernel repeats the float32 / float64 operations of its numpy twin (`kernels.twins`), in the
same order, so a table traced with either is identical, polarised and scalar, from outside and from inside
(total internal reflection), for a metal (complex index: the numpy Fresnel branch) and with the
tile's sub-tile groups; RELIEF_RAY_KERNEL=numpy forces the numpy code in a fresh process.  The tables
are traced in this process (serial backend): `kernels.select` switches this process only, and the
table's metadata["ray_kernel"] (from its tasks) shows which kernels traced it.  Without a
built extension (a pure-Python install) the comparisons are skipped and the numpy code is what runs.
"""
from __future__ import annotations

import os
import subprocess
import sys

import numpy as np
import pytest

from relief_bsdf import kernels
from relief_bsdf.bsdf.builder import CellAccumulator, CellIndex, ExitSamples
from relief_bsdf.core.index import ConstantIndex, Material
from relief_bsdf.methods import ray
from relief_bsdf.methods.request import Request
from relief_bsdf.surface.synth import random_relief

pytestmark = pytest.mark.filterwarnings("ignore:ray table:RuntimeWarning")   # a small tile, on purpose
# `make test` builds the kernels (pip install -e backend): where they are missing the comparison fails, so a
# compiler that fails silently in CI is seen; only an install asked to be pure Python (RELIEF_PURE_PYTHON=1,
# the Blender wheel's build) has none to compare, and says so
PURE = os.environ.get("RELIEF_PURE_PYTHON", "") in ("1", "true", "yes")
needs_compiled = pytest.mark.skipif(PURE, reason="RELIEF_PURE_PYTHON=1: an install without the compiled kernels")


def test_the_compiled_kernels_are_built_unless_pure_python_was_asked_for():
    assert PURE or kernels.available(), ("the compiled ray kernels are not built: `pip install -e backend` with a "
                                         "C compiler builds them (see its output), or set RELIEF_PURE_PYTHON=1")
TE = tuple(np.linspace(0.0, 90.0, 31))
PE = tuple(np.arange(-7.5, 360.0, 15.0))

@pytest.fixture
def kernel():
    """Switch kernels inside a test; the one in use before is restored."""
    prev = kernels.name()
    yield kernels.select
    kernels.select(prev)


def steep_relief(seed: int = 5):
    L = 6e-6
    return random_relief(64, 1e-6, 0.6 * L / 2, L, seed=seed)     # rms slope 0.6: many inter-reflections


def tables(kernel, name: str, material, **options):
    """Tables traced in this process (serial backend: a worker process would use its own kernels)."""
    kernel(name)
    req = Request(theta_i_deg=(0.0, 50.0, 75.0), incident_from=("outside", "inside"), samples=30000, seed=4,
                  theta_s_edges_deg=TE, phi_s_edges_deg=PE, options={"threads": 2, "backend": "serial", **options})
    return ray.reconstruct(steep_relief(), material, req)


@needs_compiled
@pytest.mark.parametrize("polarized", [True, False])
def test_compiled_and_numpy_kernels_give_the_same_tables(kernel, polarized, same_tables):
    glass = Material(ConstantIndex(1.5))
    compiled = tables(kernel, "cython", glass, polarized=polarized)
    reference = tables(kernel, "numpy", glass, polarized=polarized)
    same_tables(compiled, reference)
    assert compiled[0].metadata["ray_kernel"] == "cython" and reference[0].metadata["ray_kernel"] == "numpy"
    assert np.any(compiled[1].mueller_per_sr != 0) if polarized else True


@needs_compiled
def test_compiled_kernels_leave_a_metal_and_a_table_without_tile_groups_unchanged(kernel, same_tables):
    metal = Material(ConstantIndex(0.2, 3.0))
    req = dict(polarized=True, tile_uncertainty=False)
    kernel("cython")
    r = Request(theta_i_deg=(30.0, 60.0), samples=20000, seed=2, theta_s_edges_deg=TE, phi_s_edges_deg=PE,
                options={"threads": 1, "backend": "serial", **req})
    a = ray.reconstruct(steep_relief(6), metal, r)
    kernel("numpy")
    b = ray.reconstruct(steep_relief(6), metal, r)
    same_tables(a, b)
    assert a[0].metadata["ray_kernel"] == "cython" and b[0].metadata["ray_kernel"] == "numpy"


@needs_compiled
def test_binning_kernel_adds_batches_as_bincount_does(kernel):
    """Several batches into one accumulator (the kernel adds a batch's own sums to non-empty ones)."""
    accs = {}
    for name in ("cython", "numpy"):
        kernel(name)
        acc = CellAccumulator(CellIndex(TE, PE), polarized=True)
        r = np.random.default_rng(1)
        for _ in range(3):
            n = 5000
            d = r.normal(size=(n, 3)).astype(np.float32)
            d /= np.linalg.norm(d, axis=1)[:, None]
            w = r.random(n).astype(np.float32) * 3
            M = r.normal(size=(16, n)).astype(np.float32)
            spec = r.random(n) < 0.01
            acc.add(ExitSamples(d, w, (d[:, 2] < 0).astype(np.int8), M, spec))
        accs[name] = acc
    for f in ("sum_w", "sum_w2", "sum_M", "spec", "spec_M"):
        np.testing.assert_array_equal(getattr(accs["cython"], f), getattr(accs["numpy"], f), err_msg=f)
    assert accs["cython"].outside_table == accs["numpy"].outside_table


@needs_compiled
def test_specular_prefilter_of_both_ideal_directions_flags_what_numpy_flags(kernel):
    """Exits scattered about the mirror and the refraction direction at 1e-7 to 1e-3 rad, and random ones:
    the one-pass prefilter of both (`near_two_directions`) flags the same exits as numpy's two passes."""
    from relief_bsdf.bsdf.builder import specular_flags

    rng = np.random.default_rng(3)
    mirror = np.array([0.5, 0.0, np.sqrt(0.75)])
    refr = np.array([0.33, 0.0, -np.sqrt(1 - 0.33 ** 2)])
    base = np.concatenate([np.tile(mirror, (3000, 1)), np.tile(refr, (3000, 1)), rng.normal(size=(3000, 3))])
    d = base + rng.normal(size=base.shape) * rng.choice([1e-7, 1e-5, 1e-3], size=(base.shape[0], 1))
    d = (d / np.linalg.norm(d, axis=1)[:, None]).astype(np.float32)
    side = (d[:, 2] < 0).astype(np.int8)
    flags = {}
    for name in ("cython", "numpy"):
        kernel(name)
        flags[name] = specular_flags(d, side, (mirror, refr), float(np.cos(1e-5)))
    np.testing.assert_array_equal(flags["cython"], flags["numpy"])
    assert 1000 < np.count_nonzero(flags["numpy"][:6000]) < 5000 and not flags["numpy"][6000:].any()


@needs_compiled
def test_compact_exit_records_expand_to_the_same_columns(kernel):
    """A chunk traced with the Mueller carrier and the first-hit split: both kernels hold the same exits
    compactly (factors and exit rotation, `Exits.compact`: most of them); `Exits.ordered` expands them to
    the same columns, bit for bit."""
    from relief_bsdf.methods.ray.transport import Media, Rays, StokesCarrier, TraceSettings, trace_chunk

    tracer = ray.ReliefTracer(steep_relief(7), threads=1)
    n = 4000
    rng = np.random.default_rng(5)
    th = np.radians(35.0)
    k_in = np.array([np.sin(th), 0.0, -np.cos(th)], np.float32)
    ordered, compact = {}, {}
    for name in ("cython", "numpy"):
        kernel(name)
        o = np.stack([rng.uniform(-tracer.hx, tracer.hx, n), rng.uniform(-tracer.hy, tracer.hy, n),
                      np.full(n, tracer.z_top)], axis=1).astype(np.float32) if name == "cython" else o
        rays = Rays(o.copy(), np.tile(k_in, (n, 1)), np.zeros(n, bool), np.ones(n, np.float32),
                    np.zeros(n, np.int16), np.arange(n, dtype=np.int64))
        ex = trace_chunk(tracer, rays, StokesCarrier(4), Media(1.0, 1.5), TraceSettings(100, True, 0.0),
                         np.random.default_rng(9), s_init=np.array([0.0, 1.0, 0.0], np.float32))
        compact[name] = int(np.count_nonzero(ex.compact[:ex.n]))
        ordered[name] = ex.ordered()
    assert compact["cython"] == compact["numpy"] > n                # most of the 2 n exits held compactly
    for a, b in zip(ordered["cython"], ordered["numpy"], strict=True):
        np.testing.assert_array_equal(a, b)


def test_environment_variable_forces_the_numpy_kernels():
    code = ("from relief_bsdf import kernels; from relief_bsdf.methods import ray; "
            "print(kernels.name(), kernels.bin_cells is kernels.REGISTRY['bin_cells'].twin)")
    env = dict(os.environ, RELIEF_RAY_KERNEL="numpy")
    out = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True, check=True)
    assert out.stdout.split() == ["numpy", "True"]
    env["RELIEF_RAY_KERNEL"] = ""
    out = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True, check=True)
    assert out.stdout.split() == (["cython", "False"] if kernels.available() else ["numpy", "True"])


def test_selecting_an_unbuilt_or_unknown_kernel_is_refused(kernel):
    with pytest.raises(ValueError):
        kernel("fortran")
    if not kernels.available():
        with pytest.raises(RuntimeError):
            kernel("cython")


@needs_compiled
@pytest.mark.parametrize("periodic", [True, False])
def test_subtile_kernel_tags_points_as_numpy_does(kernel, periodic):
    """Points inside, on the edges of and beyond the tile; a mirror-extended (non-periodic) map folds them."""
    from relief_bsdf.methods.ray.tracer import ReliefTracer
    from relief_bsdf.surface.relief import Relief

    rng = np.random.default_rng(0)
    relief = steep_relief() if periodic else Relief(rng.normal(size=(40, 50)) * 1e-7, 1e-6, 1e-6, periodic=False)
    tracer = ReliefTracer(relief, threads=1)
    hx, hy = float(tracer.hx), float(tracer.hy)
    p = np.stack([rng.uniform(-1.2 * hx, 1.2 * hx, 50000), rng.uniform(-1.2 * hy, 1.2 * hy, 50000),
                  np.zeros(50000)], axis=1).astype(np.float32)
    p[:4, :2] = [[hx, hy], [-hx, -hy], [hx, -hy], [0.0, 0.0]]
    assert tracer.mesh.mirrored is not periodic
    for grid in ((4, 3), (8, 8), (1, 2)):
        kernel("cython")
        a = tracer.subtile_of(p, grid)
        kernel("numpy")
        np.testing.assert_array_equal(a, tracer.subtile_of(p, grid))
