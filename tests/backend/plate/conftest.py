"""Fixtures of the plate tests: the forward model's memory owner, analytic boundary tables."""
import numpy as np
import pytest

from relief_bsdf.plate.memory import ForwardMemory

from relief_bsdf.bsdf.table import BsdfTable
from relief_bsdf.methods.request import Request


def _lambert(frm, aR, aT, th, spec_R=0.0, spec_T=0.0, mueller=False):
    r = Request(theta_i_deg=tuple(th))
    v = np.zeros((1, len(th), 1, 2, r.theta_s_deg.size, r.phi_s_deg.size))
    v[:, :, :, 0] = aR / np.pi
    v[:, :, :, 1] = aT / np.pi
    mu = v[..., None, None] * np.diag([1.0, 0, 0, 0]) if mueller else None
    return BsdfTable(r.wavelengths_nm, r.theta_i_deg, r.phi_i_deg, r.theta_s_edges_deg, r.phi_s_edges_deg, v,
                     incident_from=frm, specular_R=spec_R, specular_T=spec_T, mueller_per_sr=mu)


@pytest.fixture
def lambert_table():
    """Factory: isotropic table with constant (Lambertian) cells, albedos aR, aT at every incidence.

    lambert_table(incident_from, aR, aT, theta_i_list, spec_R=0, spec_T=0, mueller=False) -> BsdfTable
    """
    return _lambert


@pytest.fixture(scope="module", autouse=True)
def module_memory():
    """One memory owner per test module (`plate.memory.ForwardMemory`, active for the module's tests): the
    tests of a module share its tables and solvers (their values are pure functions of their keys), no
    module sees another's; a test that needs an owner of its own asks for `fresh_memory`."""
    with ForwardMemory(4e9).active() as memory:
        yield memory


@pytest.fixture
def fresh_memory():
    """An empty memory owner of this test alone, active for it."""
    with ForwardMemory(4e9).active() as memory:
        yield memory
