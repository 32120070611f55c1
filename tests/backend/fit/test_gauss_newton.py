"""The one Gauss-Newton polish of the fit and the diagnosis (fit.gauss_newton)."""
import numpy as np
import pytest

from relief_bsdf.fit.gauss_newton import polish

RNG = np.random.default_rng(3)
A = RNG.standard_normal((200, 2)) * np.array([30.0, 8.0])     # two parameters of different leverage
X_TRUE = np.array([0.7, -1.3])
B = A @ X_TRUE + RNG.standard_normal(200)


class _Model:
    """Residuals z(x) = A x - b + a small non-linearity, and optionally a jagged 'table noise': a
    fixed pseudo-random field of x (common random numbers: the same x, the same noise) that changes
    on a scale finer than a finite-difference step.  Counts the distinct points it is asked for."""

    def __init__(self, noise: float = 0.0):
        self.noise, self.points = noise, set()

    def z(self, x):
        self.points.add(tuple(np.round(x, 12)))
        z = A @ x - B + 0.5 * (A @ x) ** 2 / 400.0
        if self.noise:
            phase = np.sin(4.0e3 * x[0] + 7.1e3 * x[1] + np.arange(z.size))
            z = z + self.noise * phase
        return z

    def residuals(self, x):
        z = self.z(x)
        return float(z @ z), z

    def jacobian(self, x, central, h=np.array([0.01, 0.01])):
        cols = []
        for j in range(2):
            e = np.zeros(2)
            e[j] = h[j]
            cols.append((self.z(x + e) - self.z(x - e)) / (2 * h[j]) if central else (self.z(x + e) - self.z(x)) / h[j])
        return np.stack(cols, 1)


def _optimum(model):
    from scipy.optimize import least_squares
    r = least_squares(model.z, X_TRUE, xtol=1e-14, ftol=1e-14, gtol=1e-14)
    J = r.jac
    return r.x, np.sqrt(np.diag(np.linalg.inv(J.T @ J)))


@pytest.mark.parametrize("central", [True, False])
def test_polish_reaches_the_least_squares_optimum_from_afar_and_hands_over_its_jacobian(central):
    """From 20 standard deviations away on a smooth model: the optimum that scipy's least_squares
    finds, to a hundredth of a standard deviation, and a central Jacobian at the answer."""
    m = _Model()
    x_opt, sd = _optimum(m)
    x0 = x_opt + 20 * sd * np.array([1.0, -1.0])
    out = polish(m.residuals, m.jacobian, x0, np.array([-5.0, -5.0]), np.array([5.0, 5.0]),
                 np.array([0.01, 0.01]), steps=8, central=central)
    assert np.all(np.abs(out.x - x_opt) < 0.01 * sd)
    assert out.jacobian is not None
    assert np.allclose(out.jacobian, m.jacobian(out.x, True), rtol=0.02)
    assert out.f == pytest.approx(m.residuals(x_opt)[0], rel=1e-6)


def test_polish_on_a_noisy_model_ends_near_the_optimum_in_few_points():
    """Jagged noise on the residuals (as a ray-traced table's between two nearby reliefs: here it
    lengthens the second column of a central-difference Jacobian by ~10 %) makes the objective's own
    optimum wander by a fraction of a standard deviation; from 6 standard deviations away the polish
    still ends within one of the noise-free optimum, with a Jacobian for the intervals, spending
    fewer points than a new central Jacobian and a step at each of five steps would (25)."""
    clean = _Model()
    x_opt, sd = _optimum(clean)
    m = _Model(noise=0.05)
    J_noisy, J_clean = m.jacobian(x_opt, True), clean.jacobian(x_opt, True)
    assert np.linalg.norm(J_noisy[:, 1]) > 1.05 * np.linalg.norm(J_clean[:, 1])
    m.points.clear()
    out = polish(m.residuals, m.jacobian, x_opt + 6 * sd, np.array([-5.0, -5.0]), np.array([5.0, 5.0]),
                 np.array([0.01, 0.01]), steps=8)
    assert np.all(np.abs(out.x - x_opt) < sd)
    assert out.jacobian is not None
    assert len(m.points) < 25


def test_polish_keeps_to_the_bounds_and_never_ends_worse_than_it_started():
    m = _Model()
    x_opt, _ = _optimum(m)
    lower, upper = np.array([-5.0, x_opt[1] + 0.05]), np.array([5.0, 5.0])     # the optimum outside
    x0 = np.array([x_opt[0] + 0.2, x_opt[1] + 0.3])
    f0 = m.residuals(x0)[0]
    out = polish(m.residuals, m.jacobian, x0, lower, upper, np.array([0.01, 0.01]), steps=6)
    assert np.all(out.x >= lower) and np.all(out.x <= upper)
    assert out.f <= f0
    assert out.x[1] == pytest.approx(lower[1])


def test_ahead_is_told_the_trial_points_that_are_then_asked_for_and_changes_nothing():
    """`ahead` hears a full step's first trial points (d and 2 d) before they are asked for: the
    answer and every point asked are the same with and without it, and most points it was told
    were then asked for (the stretch is tried whenever the full step lowers f)."""
    lo, hi, h = np.array([-5.0, -5.0]), np.array([5.0, 5.0]), np.array([0.01, 0.01])
    plain = _Model(noise=0.05)
    x_opt, sd = _optimum(_Model())
    x0 = x_opt + 20 * sd * np.array([1.0, -1.0])
    ref = polish(plain.residuals, plain.jacobian, x0, lo, hi, h, steps=8)
    told = []
    m = _Model(noise=0.05)
    out = polish(m.residuals, m.jacobian, x0, lo, hi, h, steps=8, ahead=lambda xs: told.extend(xs))
    assert np.array_equal(out.x, ref.x) and out.f == ref.f and m.points == plain.points
    told = {tuple(np.round(x, 12)) for x in told}
    assert told and len(told & m.points) >= 0.5 * len(told)


def test_a_rough_polish_believes_a_converged_chord_and_ends_sooner_near_the_same_point():
    """`trust_chord` (a candidate's conditional fit at a later diagnosis step): the chord step that says
    converged ends the polish, without the confirming Jacobian and end game: fewer points, no Jacobian
    handed over, and an objective within what the convergence test leaves (the 68 % interval in units
    of the reduced chi^2) of the full polish's, most of the full polish's gain on the start."""
    lo, hi, h = np.array([-5.0, -5.0]), np.array([5.0, 5.0]), np.array([0.01, 0.01])
    x_opt, sd = _optimum(_Model())
    for k in (3.0, 6.0):
        x0 = x_opt + k * sd * np.array([1.0, -1.0])
        full_m, rough_m = _Model(noise=0.05), _Model(noise=0.05)
        full = polish(full_m.residuals, full_m.jacobian, x0, lo, hi, h, steps=8)
        rough = polish(rough_m.residuals, rough_m.jacobian, x0, lo, hi, h, steps=8, trust_chord=True)
        assert full.jacobian is not None and rough.jacobian is None
        assert len(rough_m.points) < len(full_m.points)
        assert rough.f <= full.f + max(1.0, full.f / (B.size - 2))
        f0 = full_m.residuals(x0)[0]
        assert f0 - rough.f > 0.5 * (f0 - full.f)


def test_the_parabola_through_a_step_and_its_stretch_says_what_is_left_on_the_line():
    from relief_bsdf.fit.gauss_newton import line_gain_left
    q = lambda t: 3.0 * (t - 0.6) ** 2 + 2.0          # noqa: E731 - minimum 2.0 at t = 0.6
    assert line_gain_left(q(0.0), q(1.0), q(2.0)) == pytest.approx(q(1.0) - 2.0, rel=1e-12)
    assert line_gain_left(5.0, 4.0, 3.0) == float("inf")              # still falling on the line: no minimum


class _Linear:
    """z(x) = G (x - x_star) + e: linear residuals with a floor e (a model that misses the noise a
    little), strong leverage G so that a step of half a difference step predicts many units of chi^2."""

    def __init__(self):
        rng = np.random.default_rng(7)
        self.G = rng.standard_normal((150, 2)) * np.array([400.0, 250.0])
        self.e = rng.standard_normal(150) * 1.1
        self.x_star = np.array([0.3, -0.2])
        self.points = []

    def z(self, x):
        self.points.append(tuple(np.round(x, 12)))
        return self.G @ (x - self.x_star) + self.e

    def residuals(self, x):
        z = self.z(x)
        return float(z @ z), z

    def jacobian(self, x, central, h=np.array([0.01, 0.01])):
        e = np.eye(2) * h
        return np.stack([(self.z(x + e[j]) - self.z(x - e[j])) / (2 * h[j]) for j in range(2)], 1)


def test_a_step_within_its_stencil_whose_stretch_rises_is_settled_without_a_confirming_jacobian():
    """A step made with a central Jacobian at the point, within one difference step, that lowers f while
    its stretch to 2 d does not, where the parabola through the three leaves under one unit of chi^2:
    the polish ends there (the least-squares optimum of a linear model) with that Jacobian, after the
    start, the Jacobian's 4 points, the step and its stretch; from farther away (a step longer than
    the difference step) the same landing is confirmed by a Jacobian at the answer instead."""
    lo, hi, h = np.array([-5.0, -5.0]), np.array([5.0, 5.0]), np.array([0.01, 0.01])
    m = _Linear()
    x_opt = np.linalg.lstsq(m.G, m.G @ m.x_star - m.e, rcond=None)[0]
    x0 = x_opt + np.array([0.5, -0.4]) * h
    f0 = m.residuals(x0)[0]
    m.points.clear()
    out = polish(m.residuals, m.jacobian, x0, lo, hi, h, steps=8)
    assert np.allclose(out.x, x_opt, atol=1e-9)
    assert f0 - out.f > 100.0                               # not a "small" step: many units of chi^2
    assert out.jacobian is not None and np.allclose(out.jacobian, m.G)
    assert len(m.points) == 1 + 4 + 2
    far = _Linear()
    out_far = polish(far.residuals, far.jacobian, x_opt + np.array([5.0, -4.0]) * h, lo, hi, h, steps=8)
    assert np.allclose(out_far.x, x_opt, atol=1e-9)
    assert len(far.points) > 1 + 4 + 2 + 4                 # a second Jacobian, at the answer
