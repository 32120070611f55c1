"""Ray tables on graded scatter cells (a relief-scale request's edges): the compiled search of the cells
(`methods.ray.cells.SearchedCells`, `kernels.cells_of_edges`) gives the tables of the builder's numpy search
(`bsdf.builder.CellIndex`), bit for bit, polarised and scalar, from outside and inside, and so do the numpy
twins of every kernel.  Tolerance: none (the same cells, so the same sums in the same order)."""
from __future__ import annotations

import numpy as np
import pytest

from relief_bsdf import kernels
from relief_bsdf.bsdf.builder import CellIndex
from relief_bsdf.core.index import ConstantIndex, Material
from relief_bsdf.methods import ray
from relief_bsdf.methods.ray import method as ray_method
from relief_bsdf.methods.ray.cells import SearchedCells
from relief_bsdf.methods.request import Request
from relief_bsdf.surface.synth import random_relief

pytestmark = pytest.mark.filterwarnings("ignore:ray table:RuntimeWarning")   # a small tile, on purpose
TE = tuple(np.concatenate([np.linspace(0.0, 10.0, 41), np.linspace(10.5, 90.0, 80)]))
PE = tuple(np.concatenate([np.arange(-2.5, 3.0, 1.0), np.arange(7.5, 358.0, 5.0)]))


def graded_tables(polarized: bool):
    L = 6e-6
    relief = random_relief(64, 1e-6, 0.6 * L / 2, L, seed=5)
    req = Request(theta_i_deg=(0.0, 50.0), incident_from=("outside", "inside"), samples=20000, seed=4,
                  theta_s_edges_deg=TE, phi_s_edges_deg=PE,
                  options={"polarized": polarized, "sparse_cells": True, "threads": 2, "backend": "serial"})
    return ray.reconstruct(relief, Material(ConstantIndex(1.5)), req)



def test_graded_edges_are_searched_by_the_compiled_pass():
    cells = SearchedCells(TE, PE)
    assert cells.searched and not CellIndex(TE, PE).fast
    assert not SearchedCells(tuple(np.linspace(0, 90, 91)), tuple(np.arange(0, 361, 5.0))).searched   # uniform


@pytest.mark.parametrize("polarized", [True, False])
def test_compiled_search_gives_the_builders_tables(polarized, monkeypatch, same_tables):
    compiled = graded_tables(polarized)
    assert compiled[0].mueller_per_sr is not None or not polarized
    assert np.count_nonzero(compiled[0].values_per_sr) > 100          # a lobe over many graded cells
    monkeypatch.setattr(ray_method, "cell_index", CellIndex)           # the builder's numpy search
    same_tables(compiled, graded_tables(polarized), tasks=False)


@pytest.mark.skipif(not kernels.available(), reason="no compiled kernels to compare the twins with")
def test_numpy_twins_give_the_same_graded_tables(same_tables):
    prev = kernels.select("cython")
    try:
        compiled = graded_tables(True)
        kernels.select("numpy")
        same_tables(compiled, graded_tables(True), tasks=False)
    finally:
        kernels.select(prev)
