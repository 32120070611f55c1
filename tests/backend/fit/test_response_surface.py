"""The response surface that finishes the relief fit (fit.response_surface)."""
import numpy as np
import pytest

from relief_bsdf.fit.gauss_newton import polish
from relief_bsdf.fit.response_surface import design_offsets, smoothed_optimum

RNG = np.random.default_rng(5)
A = RNG.standard_normal((300, 2)) * np.array([40.0, 10.0])
X_TRUE = np.array([0.3, -0.8])
B = A @ X_TRUE + RNG.standard_normal(300)
X_LSQ = np.linalg.lstsq(A, B, rcond=None)[0]
SD = np.sqrt(np.diag(np.linalg.inv(A.T @ A)))          # the estimate's standard deviations
LO, HI = np.array([-5.0, -5.0]), np.array([5.0, 5.0])


def _bumpy(seed: int, amp: float = 0.15):
    """Linear residuals plus a 'table noise' that moves with x: per row a sinusoid of x with a
    period of about one standard deviation of the estimate (the scale on which the demo fit's chi^2
    bumps), the same x giving the same noise (common random numbers)."""
    r = np.random.default_rng(seed)
    k = r.standard_normal((A.shape[0], 2)) / SD * (2 * np.pi / 1.5)
    ph = r.uniform(0, 2 * np.pi, A.shape[0])
    return lambda x: A @ x - B + amp * np.sin(k @ x + ph)


def test_design_has_the_stated_points_and_refuses_other_dimensions():
    assert design_offsets(1).tolist() == [[-1.0], [-0.5], [0.5], [1.0]]
    d2 = design_offsets(2)
    assert d2.shape == (8, 2) and not np.any(np.all(d2 == 0, axis=1)) and np.array_equal(d2.sum(0), [0, 0])
    with pytest.raises(ValueError):
        design_offsets(3)
    with pytest.raises(ValueError):
        smoothed_optimum(lambda x: A @ x - B, X_LSQ, LO, HI, np.array([0.0, 1.0]))


def test_linear_residuals_give_the_exact_least_squares_optimum_and_jacobian():
    calls = []

    def z(x):
        calls.append(x.copy())
        return A @ x - B
    s = smoothed_optimum(z, X_LSQ + 0.5 * SD, LO, HI, 2 * SD)
    assert s.x == pytest.approx(X_LSQ, abs=1e-10)
    assert s.jacobian == pytest.approx(A, rel=1e-9)
    assert s.rounds == 1 and s.points == 9 and len(calls) == 9
    assert s.scatter == pytest.approx(0.0, abs=1e-9)
    one = smoothed_optimum(lambda x: A[:, :1] @ x - (B - A[:, 1] * X_LSQ[1]), X_LSQ[:1] + SD[:1], LO[:1], HI[:1],
                           3 * SD[:1])
    assert one.x == pytest.approx(X_LSQ[:1], abs=1e-10) and one.points == 5


def test_a_far_start_moves_the_design_and_stops_after_the_rounds():
    far = X_LSQ + 10 * SD
    two = smoothed_optimum(lambda x: A @ x - B, far, LO, HI, 2 * SD, rounds=2)
    assert two.rounds == 2
    # each round moves at most 2 half-widths: 10 sd away, two rounds of 4 sd leave 2 sd to go
    assert np.all(np.abs(two.x - X_LSQ) == pytest.approx(2 * SD, rel=1e-9))
    many = smoothed_optimum(lambda x: A @ x - B, far, LO, HI, 2 * SD, rounds=4)
    assert many.x == pytest.approx(X_LSQ, abs=1e-10) and many.rounds == 4


def test_the_design_stays_in_the_bounds_and_an_unseen_parameter_does_not_move():
    pts = []

    def z(x):
        pts.append(x.copy())
        return A[:, :1] @ x[:1] - (B - A[:, 1] * X_LSQ[1])     # the second parameter is not seen by the rows
    lo = np.array([-5.0, 0.0])
    s = smoothed_optimum(z, np.array([X_LSQ[0] + 0.5 * SD[0], 0.0]), lo, HI, np.array([SD[0], 0.1]))
    P = np.array(pts)
    assert np.all(P >= lo) and np.all(P <= HI)
    assert len({tuple(p) for p in P}) == len(P) == 6          # 3 x 3 less the centre, clipped: 5 distinct + centre
    assert s.rounds == 1 and s.x[0] == pytest.approx(X_LSQ[0], abs=1e-10)
    assert s.x[1] == pytest.approx(0.0, abs=1e-12)


def test_bumps_of_the_tables_noise_do_not_trap_the_estimate_where_local_steps_stop():
    """On residuals with bumps on the interval's own scale, started 3 standard deviations off, the
    surface's answer lies within one standard deviation of the smooth model's optimum in every one of
    ten noise realisations; Gauss-Newton steps with central differences of a hundredth of a standard
    deviation (the polish) follow the bumps' local slopes and stay trapped near the start."""
    miss_surface, miss_polish = [], []
    for seed in range(20, 30):          # realisations not looked at while the design was chosen (0-19 were)
        z = _bumpy(seed)
        smooth = X_LSQ                                    # the bumps average to zero: the optimum without them
        start = smooth + np.array([3.0, -2.5]) * SD
        s = smoothed_optimum(z, start, LO, HI, 2 * SD)
        miss_surface.append(np.max(np.abs(s.x - smooth) / SD))

        def res(x):
            v = z(x)
            return float(v @ v), v

        def jac(x, central, h=0.01 * SD):
            return np.stack([(z(x + h * e) - z(x - h * e)) / (2 * h[j]) for j, e in enumerate(np.eye(2))], 1)
        p = polish(res, jac, start, LO, HI, 0.01 * SD, 8)
        miss_polish.append(np.max(np.abs(p.x - smooth) / SD))
    assert max(miss_surface) < 1.0, miss_surface
    assert np.median(miss_polish) > 2.0, miss_polish


def test_the_fits_design_spans_two_standard_deviations_and_leaves_an_unseen_filter_alone():
    """fit.optimise._smoothed on a stub objective whose residuals are linear in ln s with a known
    standard deviation and do not see the filter: the design's half-width in ln s is two standard
    deviations, the unseen filter gets one finite-difference step (not a design across its bounds)
    and does not move, and the answer is the exact optimum in ln s."""
    from relief_bsdf.fit.optimise import SURFACE_SIGMAS, FitSettings, _Coords, _smoothed
    a = RNG.standard_normal(400) * 50.0
    b = a * np.log(1.25) + RNG.standard_normal(400)
    ln_s_hat = float(a @ b / (a @ a))
    seen = []

    class Stub:
        def likelihood_residuals(self, s, g):
            seen.append((s, g))
            return a * np.log(s) - b
    c = _Coords.make(FitSettings(), True, 2.0, 0.1)
    sd = 1.0 / np.sqrt(a @ a)
    ln_s0 = ln_s_hat + 0.5 * sd
    J0 = np.column_stack([a, np.zeros_like(a)])              # the polish's Jacobian: the filter unseen
    s, g, J, surf = _smoothed(Stub(), c, float(np.exp(ln_s0)), 0.5, J0)
    lns = np.log([p[0] for p in seen])
    w = np.array([p[1] for p in seen]) ** 2
    chi2 = float(np.sum((a * ln_s0 - b) ** 2))
    c_hat = max(1.0, chi2 / (a.size - 2))
    assert surf.rounds == 1 and surf.points == 9
    assert np.max(np.abs(lns - ln_s0)) == pytest.approx(SURFACE_SIGMAS * sd * np.sqrt(c_hat), rel=1e-6)
    assert np.max(np.abs(w - 0.25)) == pytest.approx(c.step[1], rel=1e-6)
    assert np.log(s) == pytest.approx(ln_s_hat, abs=1e-9) and g == pytest.approx(0.5, abs=1e-12)
    assert J[:, 0] == pytest.approx(a, rel=1e-6) and np.allclose(J[:, 1], 0.0, atol=1e-6)
