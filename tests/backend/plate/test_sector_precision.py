"""One evaluation's memory on an anisotropic relief (plate.deterministic): the sector kernels in single
precision change the rows far below any recording's noise; once the kernels exist the sector table is let
go, and a held solver answers a later evaluation on the same tables without deriving any table."""
import warnings

import numpy as np
import pytest

from relief_bsdf.core.index import ConstantIndex
from relief_bsdf.plate import Experiment, FlatFace, Instrument, Plate, ReliefFace, TableGrid, in_plane_rows, simulate
from relief_bsdf.plate import faces, sector_loop
from relief_bsdf.plate.faces import derive, relief, sectors
from relief_bsdf.plate.memory import ForwardMemory
from relief_bsdf.surface.synth import RandomFieldSpec, relief_from_spec

GRID = TableGrid(3.0, 15.0, 15.0)
ROWS = in_plane_rows(550.0, [0.0, 60.0], np.arange(1.0, 89.0, 4.0))


@pytest.fixture(scope="module")
def experiment() -> Experiment:
    relief = relief_from_spec(RandomFieldSpec(64, 64, 1e-6, 0.5e-6, 4e-6, anisotropy=2.5, angle_deg=0.0), 33)
    return Experiment(Plate(2e-3, ConstantIndex(1.5), ReliefFace(relief, "ray", 3000, 34), FlatFace()),
                      Instrument(detector_half_angle_deg=2.5))


def _simulate(ex: Experiment, memory: ForwardMemory) -> np.ndarray:
    with memory.active(), warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)          # the anisotropy warning
        return simulate(ex, ROWS, grid=GRID).values_per_sr


def test_single_precision_sector_kernels_move_the_rows_far_below_a_recordings_noise(experiment, monkeypatch):
    """The sector kernels' differences rounded to single precision (`_SectorKernels`: precision argument)
    against the same kernels in double: the rows move by less than 1e-4 of the largest row (a recording's
    noise is ~1e-2), and they do move (the check would see a precision that changed nothing)."""
    single = _simulate(experiment, ForwardMemory(4e9))
    monkeypatch.setattr(sector_loop, "SECTOR_LOOP_DTYPE", np.float64)
    monkeypatch.setattr(sector_loop, "SECTOR_EXIT_DTYPE", np.complex128)
    double = _simulate(experiment, ForwardMemory(4e9))
    change = np.max(np.abs(single - double)) / np.max(np.abs(double))
    assert 0 < change < 1e-4


def test_the_loop_differences_on_the_tables_incidences_are_those_on_the_engines_cells(experiment, monkeypatch):
    """The sector loop's kernel differences kept on the tables' own incidences and interpolated onto the
    engine's cells in the product (`_SectorKernels.interp`) against the same differences made on the
    engine's cells, both in double precision: the same linear map in another order, so the rows agree to
    rounding (< 1e-9 of the largest row); and the kept kernels are half as large."""
    monkeypatch.setattr(sector_loop, "SECTOR_LOOP_DTYPE", np.float64)
    monkeypatch.setattr(sector_loop, "SECTOR_EXIT_DTYPE", np.complex128)
    m_table = ForwardMemory(4e9)
    on_table = _simulate(experiment, m_table)
    monkeypatch.setattr(sector_loop, "SECTOR_LOOP_ON_TABLE_INCIDENCES", False)
    m_engine = ForwardMemory(4e9)
    on_engine = _simulate(experiment, m_engine)
    assert np.max(np.abs(on_table - on_engine)) < 1e-9 * np.max(np.abs(on_engine))
    kernels = [next(iter(m.values("solver")[-1]._tops.values()))["sector_kernels"] for m in (m_table, m_engine)]
    assert kernels[0].interp is not None and kernels[1].interp is None
    n_i, n_engine = kernels[0].interp.shape[1], kernels[0].interp.shape[0]
    assert kernels[0].loop.nbytes * n_engine == kernels[1].loop.nbytes * n_i and n_i < n_engine


def test_the_sector_table_goes_once_its_kernels_exist_and_a_held_solver_needs_no_table(experiment, monkeypatch):
    memory = ForwardMemory(4e9)
    first = _simulate(experiment, memory)
    solver = memory.values("solver")[-1]
    assert isinstance(solver.inside_sectors, sector_loop.SectorsHeader)       # the loop ran by sector ...
    assert not any(faces.SECTORS_KEY in k[0] + k[1:] for k, _ in memory.entries("table"))   # ... without its table
    assert solver._tops and all(t["sector_kernels"] is not None for t in solver._tops.values())
    # what a held solver keeps: not the 0-deg loop kernel (it lives in the factors), not the sectors' average
    assert all(t["Kh"] is None and "sector_average" not in t for t in solver._tops.values())

    def no_table(*args, **kwargs):
        raise AssertionError("a table was derived for a held solver")
    changed = [experiment.with_instrument(blur_deg=1.0, polarization_q=1.0), experiment.with_bulk(absorption_per_m=40.0)]
    with monkeypatch.context() as m:
        for module in (derive, relief, sectors):         # every caller of the one table derivation
            m.setattr(module, "_reconstruct_side", no_table)
        reused = [_simulate(ex, memory) for ex in changed]
    fresh = [_simulate(ex, ForwardMemory(4e9)) for ex in changed]     # every table derived anew
    for r, f in zip(reused, fresh):
        np.testing.assert_allclose(r, f, rtol=1e-12, atol=0)
    assert not np.allclose(reused[0], first) and not np.allclose(reused[1], first)
