"""The plate tests' comparison with the validation's photon Monte Carlo: rms relative deviation of
several simulations over the bright part of one side's lobe (a uniquely named module: pytest puts
this folder on sys.path, and two conftest.py cannot both be imported as 'conftest')."""
import numpy as np


def bright_deviation(models, mc: np.ndarray, mc_sigma: np.ndarray, sides: np.ndarray, side: str,
                     min_rows: int) -> list:
    """[rms(model / mc - 1)] for each model over the rows of `side` where the Monte Carlo is above a tenth
    of that side's peak and its own noise below 3 %; at least `min_rows` such rows."""
    bright = (sides == side) & (mc > 0.1 * mc[sides == side].max()) & (mc_sigma < 0.03 * mc)
    assert bright.sum() >= min_rows, (side, int(bright.sum()))
    return [float(np.sqrt(np.mean((m[bright] / mc[bright] - 1) ** 2))) for m in models]
