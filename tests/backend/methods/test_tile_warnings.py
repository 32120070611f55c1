"""The finite-tile warnings can be silenced for a run that derives many tables of one relief (a
diagnosis's probes), and only they: the numbers they state stay in the tables' metadata."""
import re
import warnings

import numpy as np
import pytest

from relief_bsdf.methods.realisation import TILE_WARNING, tile_warnings_quiet, uncertainty_meta


def _meta():
    values = np.ones((1, 6))
    sigma = np.full((1, 6), 0.5)               # the lobe's cells scatter by 50 % between tiles: a warning
    return uncertainty_meta("kirchhoff", "outside", values, sigma, "test", 12.0)


def test_the_tile_warning_is_issued_outside_the_context():
    with pytest.warns(RuntimeWarning, match="the tile holds 12 correlation areas"):
        info, warn = _meta()
    assert info["lobe_relative_tile_sigma_max"] == pytest.approx(0.5) and len(warn) == 1


def test_inside_the_context_only_the_tile_warnings_are_silenced():
    with warnings.catch_warnings(record=True) as seen:
        warnings.simplefilter("always")
        with tile_warnings_quiet():
            info, warn = _meta()
            warnings.warn("ray table (inside): the tile holds only 2 x 2 sub-tiles of 4 correlation lengths",
                          RuntimeWarning)
            warnings.warn("something else went wrong", RuntimeWarning)
        _meta()                                 # after the context: issued again
    messages = [str(w.message) for w in seen]
    assert messages[0] == "something else went wrong"
    assert len(messages) == 2 and "the tile holds 12 correlation areas" in messages[1]
    assert warn and info["lobe_relative_tile_sigma_max"] == pytest.approx(0.5)   # still in the metadata


def test_the_pattern_matches_every_tables_tile_warning():
    for msg in ("ray table (outside): the tile holds 295 correlation areas, too few",
                "ray table (inside): the tile holds only 3 x 3 sub-tiles",
                "microfacet table (outside): the tile holds 12 correlation areas",
                "rayleigh-rice table (inside): the tile holds an unknown number of correlation areas"):
        assert re.match(TILE_WARNING, msg), msg
    assert not re.match(TILE_WARNING, "ray table (outside): 3 % of the rays were lost")
