"""The fit on the relief's own physics, on recordings the project's forward model did not make.

Issue 18 item 5: two plates simulated INDEPENDENTLY (relief conceal: the validation's photon Monte
Carlo through the ray-traced true relief, its own transport loop and detector) whose relief files
are 1/0.791 and 1/1.215 of the true heights (true = 0.791 x file, 1.215 x file).  `relief fit` with
its default physics (auto: ray tracing, this relief is rough on the wavelength scale) must give the
true scale back within 5 % and say that the recording does not ask for a filter: in geometric
optics scale and filter both act only on slopes, and this Gaussian relief keeps a Gaussian slope
distribution under filtering, so a filter is not identifiable and the simplest point is g = 0.
"""
import json

import pytest

from relief_bsdf.cli import main
from relief_bsdf.validation.conceal import CaseSpec, make_case


@pytest.mark.slow
@pytest.mark.parametrize("s_true, seed", [(0.791, 31), (1.215, 32)])
def test_default_fit_gives_back_the_true_scale_and_needs_no_filter(tmp_path, s_true, seed):
    spec = CaseSpec(name=f"scale{s_true}", effect="relief_scale", parameters={"height_scale": s_true}, seed=seed,
                    relief_n=96, photons=300_000, theta_i_deg=(0.0, 30.0),
                    theta_s_deg=tuple(float(x) for x in range(0, 90, 4)))
    make_case(spec, tmp_path / "case")
    out = tmp_path / "fit"
    assert main(["fit", str(tmp_path / "case" / "sample.toml"), "-o", str(out), "--max-iter", "40",
                 "--samples", "60000"]) == 0
    doc = json.loads((out / "fit.json").read_text())
    assert doc["method"] == "ray" and doc["method_reason"].startswith("auto: ray")
    assert doc["parameters"]["height_scale"] == pytest.approx(s_true, rel=0.05)
    assert doc["parameters"]["filter_sigma_um"] == 0.0
    assert doc["identifiability"]["filter_needed"] is False
    assert any("does not ask for filtering" in w for w in doc["warnings"])
    lo, hi = doc["intervals"]["height_scale"]
    assert lo < doc["parameters"]["height_scale"] < hi
    # reaching the recording's noise is item 2 (the forward model's accuracy), not asserted here:
    # on this 96 px relief the fit ends at a metric of ~2.4 from ~3.7 (see the closing note)
    assert doc["rms_after"] < doc["rms_before"]
