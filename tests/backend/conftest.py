"""Shared fixtures of the backend tests (no bpy).

Reliefs are built by the project's ONE random-field generator (`surface.synth.random_relief`,
autocovariance s^2 exp(-r^2/L^2), formats.md) so every test sees the same convention; real
instrument files come from tests/data/topography/ (SOURCE.md).  Test folders mirror the packages
(tests/backend/<package>/); helper modules that several folders import (`_wave_reliefs`) live
here, on sys.path.
"""
from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
import pytest

HERE = Path(__file__).resolve().parent
REPO = HERE.parents[1]
if str(HERE) not in sys.path:
    sys.path.insert(0, str(HERE))          # `import _wave_reliefs` from any test folder


@pytest.fixture
def gaussian_relief():
    """Factory: periodic isotropic Gaussian relief, autocovariance s^2 exp(-r^2/L^2).

    gaussian_relief(n, pitch_m, rms_m, corr_m, seed=0) -> Relief
    """
    from relief_bsdf.surface.synth import random_relief

    def make(n: int, pitch_m: float, rms_m: float, corr_m: float, seed: int = 0):
        return random_relief(n, pitch_m, rms_m, corr_m, "gaussian", seed)
    return make


@pytest.fixture
def flat_relief():
    """Factory: a perfectly flat periodic tile, flat_relief(n=64, pitch_m=0.1e-6) -> Relief."""
    from relief_bsdf.surface.relief import Relief

    def make(n: int = 64, pitch_m: float = 0.1e-6):
        return Relief(np.zeros((n, n)), pitch_m, pitch_m, periodic=True, source="flat")
    return make


@pytest.fixture
def glass():
    """Air over a non-dispersive glass of index 1.5."""
    from relief_bsdf.core.index import ConstantIndex, Material
    return Material(inside=ConstantIndex(1.5), outside=ConstantIndex(1.0))


@pytest.fixture(scope="session")
def demo_dir() -> Path:
    """The default scene (scenes/demo: relief.x3p, sample.toml, recording.csv)."""
    return REPO / "scenes" / "demo"


@pytest.fixture
def fresh_memory():
    """A new forward-model memory owner (`plate.memory.ForwardMemory`) in force for the test: nothing
    kept from other tests is found, and nothing the test derives is left for them."""
    from relief_bsdf.plate.memory import ForwardMemory
    with ForwardMemory().active() as memory:
        yield memory


TABLE_ARRAYS = ("values_per_sr", "sigma_per_sr", "mueller_per_sr", "specular_R", "specular_T", "lost",
                "specular_mueller_R", "specular_mueller_T")


def _untimed(tasks: list) -> list:
    """A ray table's task diagnostics (rays, segments, bounces, lost detail, tile scatter) without timings
    and kernel name."""
    return [{k: v for k, v in d.items() if not k.endswith("_s") and k != "ray_kernel"} for d in tasks]


def _assert_same_tables(a, b, tasks: bool = True) -> None:
    """Two lists of BsdfTables equal bit for bit in every array; with `tasks`, their ray-task diagnostics too."""
    import numpy as np
    for ta, tb in zip(a, b, strict=True):
        for name in TABLE_ARRAYS:
            x, y = getattr(ta, name), getattr(tb, name)
            if x is None:
                assert y is None
            else:
                np.testing.assert_array_equal(x, y, err_msg=f"{ta.incident_from}: {name}")
        if tasks:
            assert _untimed(ta.metadata["tasks"]) == _untimed(tb.metadata["tasks"])


@pytest.fixture(scope="session")
def same_tables():
    """assert_same_tables(a, b, tasks=True): the one bit-for-bit comparison of table lists."""
    return _assert_same_tables
