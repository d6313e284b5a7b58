"""Tests for `jaxquat._fitting`: angular velocity and torque-free rigid bodies fitted to orientations.

Synthetic observations are generated independently of jaxquat's forward models (SciPy's `Rotation`
and `solve_ivp`), so a test compares the fit against the truth, not the library against itself.

Noise model: r_k = exp(n_k) ⊗ q(t_k), n_k ~ N(0, σ² I₃) (isotropic world-frame angle noise).

**Cramér–Rao bound for constant ω.** Linearising the world-frame model
q(t) = exp(ω τ) ⊗ exp(δ) ⊗ q₀ (τ = t − t₀) about the truth, the residual of observation k is
ρ_k = R_k δ + τ_k J(ωτ_k) δω − n_k, with R_k the rotation by ωτ_k and J the left Jacobian of SO(3).

- Along the rotation axis u: R_k u = J u = u, so ρ∥ = δ∥ + τ_k δω∥ − n∥: a straight-line fit,
  Var(ω∥) = σ² / Σ(τ_k − τ̄)² ≈ 12σ² / (N T²) for N samples spread uniformly over a span T.
- Across the axis (the plane ⊥ u as ℂ, φ_k = |ω|τ_k): R = e^{iφ}, τJ = (e^{iφ} − 1)/(i|ω|), so
  ρ⊥ = e^{iφ_k} b − a − n⊥ with a = δω⊥/(i|ω|), b = δ⊥ + a: a regression on {e^{iφ_k}, 1}, giving
  Var(each component of ω⊥) = |ω|² σ² / (N (1 − |m|²)), m = mean_k e^{iφ_k}.

So the ~12σ²/(NT²) per axis of a slowly turning body holds only along the axis once the body turns
by more than about a radian: tilting the spin axis by ε changes the orientation by at most ~2ε
however long one watches, and the cross-axis error stays at |ω|σ/√N.
"""

import time

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from scipy.integrate import solve_ivp
from scipy.interpolate import CubicSpline
from scipy.spatial.transform import Rotation

import jaxquat
from jaxquat._fitting import _orientation_residuals

SIGMA = 1e-3


# --------------------------------------------------------------------------------------------------
# Synthetic data (independent of jaxquat's forward models)


def _to_wxyz(rotation):
    xyzw = rotation.as_quat()
    return np.concatenate([xyzw[..., 3:], xyzw[..., :3]], axis=-1)


def _from_wxyz(q):
    q = np.asarray(q)
    return Rotation.from_quat(np.concatenate([q[..., 1:], q[..., :1]], axis=-1))


def _random_times(rng, num, span):
    return np.sort(np.concatenate([[0.0, span], rng.uniform(0.0, span, num - 2)]))


def _constant_truth(rng, times, omega, q0, frame="world"):
    """Orientations exp(ω t) ⊗ q₀ (world) or q₀ ⊗ exp(ω t) (body) by SciPy."""
    turn = Rotation.from_rotvec(np.outer(times, omega))
    start = _from_wxyz(q0)
    return _to_wxyz(turn * start if frame == "world" else start * turn)


def _add_noise(rng, qs, sigma=SIGMA):
    noise = Rotation.from_rotvec(sigma * rng.standard_normal(qs.shape[:-1] + (3,)))
    return _to_wxyz(noise * _from_wxyz(qs))


def _flip_signs(rng, qs):
    signs = np.where(rng.random(qs.shape[:-1]) < 0.5, -1.0, 1.0)
    return qs * signs[..., None]


def _constant_crb(times, omega, sigma=SIGMA):
    """The closed-form covariance of ω̂ (module docstring), shape (3, 3)."""
    speed = np.linalg.norm(omega)
    axis = omega / speed
    tau = times - times[0]
    along = sigma**2 / np.sum((tau - tau.mean()) ** 2)
    mean_phase = np.abs(np.mean(np.exp(1j * speed * tau)))
    across = speed**2 * sigma**2 / (len(times) * (1.0 - mean_phase**2))
    outer = np.outer(axis, axis)
    return along * outer + across * (np.eye(3) - outer)


@pytest.fixture(scope="module")
def constant_case():
    rng = np.random.default_rng(20261122)
    times = _random_times(rng, 200, 10.0)
    omega = np.array([0.3, -0.5, 0.8])  # |ω| ≈ 0.99 rad/s: 9.9 rad (1.6 turns) over the span
    q0 = _to_wxyz(Rotation.random(random_state=1))
    exact = _constant_truth(rng, times, omega, q0)
    noisy = _add_noise(rng, exact)
    return dict(times=times, omega=omega, q0=q0, exact=exact, noisy=noisy, rng=rng)


# --------------------------------------------------------------------------------------------------
# The residual


def test_residual_sign_invariant_smooth_and_exact_at_zero(getkey):
    """ρ = 2 sgn(w(e)) vec(e): invariant under q → −q and r → −r, |ρ|² = 4(1 − ⟨q, r⟩²), and at zero
    residual its Jacobian is the exact one (finite differences), the loss gradient 0."""
    q = jaxquat.random(getkey(), (64,))
    r = jaxquat.random(getkey(), (64,))
    residuals = jax.jit(_orientation_residuals, static_argnames="frame")
    dots = np.sum(np.asarray(q) * np.asarray(r), axis=-1)
    theta = np.asarray(jax.jit(jaxquat.angle_between)(q, r))
    for frame in ("world", "body"):
        rho = np.asarray(residuals(q, r, frame=frame))
        for a, b in ((-q, r), (q, -r), (-q, -r)):
            np.testing.assert_allclose(residuals(a, b, frame=frame), rho, rtol=0, atol=1e-15)
        np.testing.assert_allclose(np.sum(rho**2, -1), 4 * (1 - dots**2), rtol=1e-12, atol=1e-14)
        # |ρ| = 2 sin(θ/2) for the geodesic angle θ.
        np.testing.assert_allclose(np.linalg.norm(rho, axis=-1), 2 * np.sin(theta / 2), rtol=1e-12)

    # At zero residual, for both sheets of the observation: Jacobian w.r.t. a rotation vector φ applied
    # to the model, exact (= identity for the world-frame error) and NaN-free; loss gradient 0.
    def residual(phi, observed):
        model = jaxquat.multiply(jaxquat.from_rotvec(phi), q[0])
        return _orientation_residuals(model, observed, "world")

    jacfwd = jax.jit(jax.jacfwd(residual))
    jacrev = jax.jit(jax.jacrev(residual))
    grad = jax.jit(jax.grad(lambda phi, observed: 0.5 * jnp.sum(residual(phi, observed) ** 2)))
    value = jax.jit(residual)
    zero = jnp.zeros(3)
    step = 1e-6
    for observed in (q[0], -q[0]):
        jacobian = jacfwd(zero, observed)
        np.testing.assert_allclose(jacobian, np.eye(3), atol=1e-15)
        np.testing.assert_allclose(jacrev(zero, observed), jacobian, atol=1e-15)
        gradient = grad(zero, observed)
        assert (
            np.all(np.isfinite(gradient)) and np.max(np.abs(gradient)) <= 1e-15
        )  # 0 up to round-off
        fd = np.stack(
            [
                (value(step * e, observed) - value(-step * e, observed)) / (2 * step)
                for e in np.eye(3)
            ],
            axis=1,
        )
        np.testing.assert_allclose(fd, jacobian, atol=1e-9)


# --------------------------------------------------------------------------------------------------
# Constant angular velocity


@pytest.mark.parametrize("speed", [1.2, 10.0])
def test_constant_exact_data(speed):
    """Exact data, no initial guess, random signs: 1.9 turns, and 16 turns with up to ~2.5 rad between
    neighbouring observations (the self-start needs < π)."""
    rng = np.random.default_rng(7)
    times = _random_times(rng, 200, 10.0)
    omega = speed * np.array([-0.7, 0.4, 0.9]) / np.linalg.norm([-0.7, 0.4, 0.9])
    assert speed * np.max(np.diff(times)) < np.pi
    q0 = _to_wxyz(Rotation.random(random_state=3))
    qs = _flip_signs(rng, _constant_truth(rng, times, omega, q0))
    fit = jaxquat.fit_angular_velocity(times, qs)
    error = float(np.max(np.abs(fit.omega - omega)))
    print(
        f"\nconstant ω, exact data, {speed * 10 / (2 * np.pi):.1f} turns, largest step "
        f"{speed * np.max(np.diff(times)):.2f} rad: |Δω|max = {error:.1e}, {int(fit.num_steps)} steps"
    )
    assert fit.converged
    assert error <= 1e-10
    assert np.min(np.abs([np.linalg.norm(fit.q0 - q0), np.linalg.norm(fit.q0 + q0)])) <= 1e-10
    assert float(jnp.max(fit.residual_angles)) <= 1e-10


def test_constant_noisy_meets_cramer_rao(constant_case):
    """Acceptance 1: 200 observations, 1e-3 rad noise, 9.9 rad of rotation, no user guess."""
    c = constant_case
    fit = jaxquat.fit_angular_velocity(c["times"], c["noisy"])
    error = float(np.linalg.norm(fit.omega - c["omega"]))
    crb = _constant_crb(c["times"], c["omega"])
    expected = float(np.sqrt(np.trace(crb)))

    # The closed form agrees with the bound computed from the model's own Jacobian at the truth.
    def residuals(params):
        delta, omega = params
        q0 = jaxquat.multiply(jaxquat.from_rotvec(delta), jnp.asarray(c["q0"]))
        model = jaxquat.step(q0, omega, jnp.asarray(c["times"]))
        return _orientation_residuals(model, jnp.asarray(c["exact"]), "world").reshape(-1)

    jac = jnp.concatenate(
        jax.jit(jax.jacfwd(residuals))((jnp.zeros(3), jnp.asarray(c["omega"]))), axis=1
    )
    numeric = SIGMA**2 * np.linalg.inv(np.asarray(jac.T @ jac))[3:, 3:]
    np.testing.assert_allclose(crb, numeric, rtol=0.05, atol=0.05 * np.max(np.abs(numeric)))
    tau = c["times"] - c["times"][0]
    axis = c["omega"] / np.linalg.norm(c["omega"])
    along = float(np.sqrt(axis @ crb @ axis))
    rule = SIGMA * np.sqrt(12 / (len(tau) * tau[-1] ** 2))
    print(
        f"\nconstant ω, σ = {SIGMA}, N = {len(tau)}, T = {tau[-1]:.1f} s: |Δω| = {error:.2e} rad/s; "
        f"Cramér–Rao RMS {expected:.2e} (along the axis {along:.2e}, 12σ²/(NT²) rule {rule:.2e}; "
        f"across {np.sqrt((expected**2 - along**2) / 2):.2e} per component); "
        f"{int(fit.num_steps)} steps"
    )
    assert fit.converged
    assert int(fit.num_steps) <= 50
    assert error <= 2e-4
    assert error <= 3 * expected
    assert abs(along / rule - 1) < 0.1
    # Residual angles are the noise: RMS ≈ σ√3 less the 6 fitted degrees of freedom.
    rms = float(np.sqrt(np.mean(np.asarray(fit.residual_angles) ** 2)))
    assert abs(rms / (SIGMA * np.sqrt(3 * (1 - 6 / 600))) - 1) < 0.1


def test_start_at_zero_falls_into_wrong_minimum(constant_case):
    """Why the fit finds its own start: Levenberg–Marquardt from ω = 0 on 1.6 turns of data fails."""
    c = constant_case
    from_zero = jaxquat.fit_angular_velocity(c["times"], c["noisy"], omega0=np.zeros(3))
    assert float(np.linalg.norm(from_zero.omega - c["omega"])) > 0.1
    guided = jaxquat.fit_angular_velocity(c["times"], c["noisy"], omega0=0.9 * c["omega"])
    assert float(np.linalg.norm(guided.omega - c["omega"])) < 2e-4


def test_sign_flips_give_the_same_fit(constant_case):
    """Acceptance 4: observations with random signs give the same answer."""
    c = constant_case
    flipped = _flip_signs(np.random.default_rng(11), c["noisy"])
    assert np.any(np.sign(flipped[:, 0]) != np.sign(c["noisy"][:, 0]))
    fit = jaxquat.fit_angular_velocity(c["times"], c["noisy"])
    fit_flipped = jaxquat.fit_angular_velocity(c["times"], flipped)
    np.testing.assert_allclose(fit_flipped.omega, fit.omega, rtol=0, atol=1e-13)
    np.testing.assert_allclose(fit_flipped.residual_angles, fit.residual_angles, rtol=0, atol=1e-13)
    np.testing.assert_allclose(fit_flipped.loss, fit.loss, rtol=1e-12)
    q_distance = min(
        np.linalg.norm(fit_flipped.q0 - fit.q0), np.linalg.norm(fit_flipped.q0 + fit.q0)
    )
    assert q_distance <= 1e-13


def test_zero_weights_remove_outliers(constant_case):
    c = constant_case
    corrupted = c["exact"].copy()
    bad = np.arange(5, 200, 10)
    corrupted[bad] = _to_wxyz(Rotation.random(len(bad), random_state=4))
    weights = np.ones(200)
    weights[bad] = 0.0
    fit = jaxquat.fit_angular_velocity(c["times"], corrupted, weights=weights)
    assert fit.converged
    assert float(np.max(np.abs(fit.omega - c["omega"]))) <= 1e-10
    assert float(np.max(np.delete(np.asarray(fit.residual_angles), bad))) <= 1e-10
    assert float(np.min(np.asarray(fit.residual_angles)[bad])) > 1e-3  # still reported


@pytest.mark.parametrize("positive", [0, 1])
def test_weights_must_leave_two_observations(constant_case, positive):
    """All-zero weights returned ω₀ with converged=True: nothing was fitted, and nothing said so."""
    c = constant_case
    weights = np.zeros(200)
    weights[:positive] = 1.0
    with pytest.raises(ValueError, match=rf"`weights` .* at least two .*got {positive}\."):
        jaxquat.fit_angular_velocity(c["times"], c["exact"], weights=weights)


def test_traced_weights_leaving_fewer_than_two_observations_do_not_converge(constant_case):
    """Under jit/vmap the weights are not seen at trace time: an all-zero lane returned ω₀ with
    converged=True (loss 0). It must say it did not converge; the other lanes are unaffected."""
    c = constant_case
    lanes = np.ones((3, 200))
    lanes[0] = 0.0
    lanes[1, 1:] = 0.0
    fits = jax.vmap(
        lambda w: jaxquat.fit_angular_velocity(
            c["times"], c["exact"], weights=w, omega0=c["omega"] + 0.05
        )
    )(jnp.asarray(lanes))
    assert fits.converged.tolist() == [False, False, True]
    assert float(np.max(np.abs(fits.omega[2] - c["omega"]))) <= 1e-10
    # Their derivatives: the singular Hessian of the degenerate lanes raised inside lineax (an LU
    # solve) and aborted the whole batch's; now each lane has its own. On exact data ρ = 0 at the
    # optimum, so the good lane's −H⁻¹Jₖᵀρₖ is 0 for every k.
    derivative = jax.vmap(
        jax.jacrev(
            lambda w: (
                jaxquat.fit_angular_velocity(
                    c["times"], c["exact"], weights=w, omega0=c["omega"] + 0.05
                ).omega
            )
        )
    )(jnp.asarray(lanes))
    assert np.all(np.isfinite(np.asarray(derivative)))
    assert float(np.max(np.abs(derivative[2]))) < 1e-12


@pytest.mark.parametrize(
    "option", [dict(method="cf5"), dict(substeps=0), dict(max_steps=0), dict(solver="lm")]
)
def test_rigid_body_options_are_checked_before_the_start_is_computed(monkeypatch, option):
    """`method` (and the other options) were checked only after the automatic starting point had
    been computed and compiled: a typo cost that compilation before its ValueError."""

    def start(*args):
        raise AssertionError("the starting point was computed before the options were checked")

    monkeypatch.setattr(jaxquat._fitting, "_rigid_body_start", start)
    times = np.linspace(0.0, 1.0, 6)
    qs = np.tile([1.0, 0.0, 0.0, 0.0], (6, 1))
    with pytest.raises(ValueError, match=next(iter(option))):
        jaxquat.fit_rigid_body(times, qs, **option)


def test_weights_must_leave_enough_observations_for_the_model():
    """Observations of weight 0 determine nothing, but the knots were counted and checked against
    all observations: 2 positive weights of 20 gave a piecewise-linear ω(t) of 5 knots (18 unknowns
    from 6 equations), one of infinitely many minima, with converged=True (true ω constant; fitted
    knot values −0.33 … 0.55 × it). The same for a rigid body (8 unknowns) with 2 positive
    weights: three starts, three different inertias, all converged. Now the knots are counted,
    placed by default and checked against the observations of positive weight, a rigid body needs
    three, and traced weights that leave too few say converged=False."""
    omega = jnp.array([0.3, -0.5, 0.8])
    times = np.linspace(0.0, 4.0, 20)
    qs = jaxquat.step(jaxquat.identity(), omega, times)

    def weights(*used):
        w = np.zeros(20)
        w[list(used)] = 1.0
        return w

    with pytest.raises(ValueError, match="2 knots are too many for 2 observations of positive"):
        jaxquat.fit_angular_velocity(times, qs, weights=weights(0, 19), model="piecewise_linear")
    with pytest.raises(ValueError, match="4 knots are too many for 3 observations of positive"):
        jaxquat.fit_angular_velocity(times, qs, weights=weights(0, 9, 19), model="spline")
    with pytest.raises(ValueError, match="times of the observations of positive `weights` do not"):
        jaxquat.fit_angular_velocity(
            times, qs, weights=weights(*range(8)), model="piecewise_linear", knots=3
        )
    # Four positive weights: two knots by default, and the exact ω (the closed form's).
    fit = jaxquat.fit_angular_velocity(
        times, qs, weights=weights(0, 6, 13, 19), model="piecewise_linear"
    )
    assert fit.converged and fit.omega.knots.shape == (2,)
    np.testing.assert_allclose(fit.omega.values, np.tile(omega, (2, 1)), atol=1e-9)
    # Traced weights: 5 default knots need 6 observations of positive weight.
    lanes = np.stack([weights(*range(0, 20, 4)), weights(*range(0, 20, 3)), np.ones(20)])
    fits = jax.vmap(
        lambda w: jaxquat.fit_angular_velocity(times, qs, weights=w, model="piecewise_linear")
    )(jnp.asarray(lanes))
    assert fits.converged.tolist() == [False, True, True]
    np.testing.assert_allclose(fits.omega.values[1:], np.tile(omega, (2, 5, 1)), atol=1e-8)
    # A rigid body: 8 unknowns, 3 equations per observation.
    body_qs, _ = jaxquat.simulate_rigid_body(
        jaxquat.identity(), jnp.array([0.5, 0.8, 0.6]), jnp.array([1.0, 1.6, 2.3]), 4.0 / 19, 19
    )
    with pytest.raises(ValueError, match="`weights` must give at least three observations"):
        jaxquat.fit_rigid_body(times, body_qs, weights=weights(0, 3))
    traced = jax.jit(lambda w: jaxquat.fit_rigid_body(times, body_qs, weights=w).converged)
    assert not bool(traced(weights(0, 3)))


@pytest.fixture(scope="module")
def weighted_case():
    """40 noisy observations (SciPy) with two outliers given weight 0, and the fit's weights."""
    rng = np.random.default_rng(20261125)
    times = _random_times(rng, 40, 4.0)
    omega = np.array([0.7, 0.2, -0.9])
    q0 = _to_wxyz(Rotation.random(random_state=3))
    qs = _add_noise(rng, _constant_truth(rng, times, omega, q0))
    qs[[7, 23]] = _to_wxyz(Rotation.random(2, random_state=5))
    weights = rng.uniform(0.5, 2.0, 40)
    weights[[7, 23]] = 0.0
    return dict(times=times, qs=qs, weights=weights, omega=omega)


@pytest.mark.parametrize("model", ["constant", "spline"])
def test_derivative_at_a_zero_weight_is_finite_and_correct(weighted_case, model):
    """Through √w the derivative with respect to a weight of exactly 0 was 0·∞ = NaN (jacrev) and
    jacfwd aborted in lineax. The fit's stationarity condition Σ wₖ Jₖᵀρₖ = 0 is linear in the
    weights, so the implicit derivative −H⁻¹Jₖᵀρₖ is finite; it must match a one-sided second-order
    difference of the fit itself (weights cannot go negative). The differences start from the fit at
    w = 0 (`omega0`), so that all of them follow its minimum: the automatic start of a fit whose
    outlier has a weight of 1e-4 uses the outlier, as any positively weighted observation."""
    c = weighted_case
    knots = None if model == "constant" else np.linspace(c["times"][0], c["times"][-1], 4)

    def fit(w, omega0=None):
        return jaxquat.fit_angular_velocity(
            c["times"], c["qs"], weights=w, model=model, knots=knots, omega0=omega0
        )

    w = jnp.asarray(c["weights"])
    at_zero = fit(w)
    assert at_zero.converged
    omega0 = at_zero.omega if model == "constant" else at_zero.omega.values

    def omega_hat(w):
        omega = fit(w, omega0).omega
        return omega if model == "constant" else omega(1.3)

    reverse = np.asarray(jax.jacrev(omega_hat)(w))
    assert np.all(np.isfinite(reverse))
    if model == "constant":  # (forward mode compiles for another ~15 s with the spline)
        forward = np.asarray(jax.jacfwd(omega_hat)(w))
        np.testing.assert_allclose(forward, reverse, rtol=1e-9, atol=1e-13)
    eps = 1e-4
    for k in (7, 23, 11):  # the two zero weights and a positive one
        f0, f1, f2 = (np.asarray(omega_hat(w.at[k].add(h))) for h in (0.0, eps, 2 * eps))
        difference = (-3 * f0 + 4 * f1 - f2) / (2 * eps)
        np.testing.assert_allclose(reverse[:, k], difference, rtol=1e-6, atol=1e-9)
    # The outliers (≈ 2 rad off) pull hard: their derivatives are far from zero.
    assert np.min(np.linalg.norm(reverse[:, [7, 23]], axis=0)) > 1e-3


def test_reverse_mode_through_the_automatic_start_is_not_nan(weighted_case):
    """Without `omega0` the fit starts from log-differences of the observations; the norm of a zero
    turn there made jacrev NaN in the times and the observations, while jacfwd was finite: the
    bridged interval of a weight-0 observation, and a body at rest (every observation the identity,
    every turn exactly zero; all three models). Reverse mode must match central differences. (One
    compiled jacrev: the data are arguments.)"""
    c = weighted_case
    times, qs, w = (jnp.asarray(c[k]) for k in ("times", "qs", "weights"))
    rest = jnp.tile(jaxquat.identity(), (qs.shape[0], 1))

    def omega_hat(times, qs, w):
        return jaxquat.fit_angular_velocity(times, qs, weights=w).omega

    gradient = jax.jit(jax.jacrev(omega_hat, argnums=(0, 1)))
    eps = 1e-6
    for data in (qs, rest):
        reverse = gradient(times, data, w)
        assert all(np.all(np.isfinite(np.asarray(r))) for r in reverse)
        for k in (0, 7, 8):  # the first time, an outlier's, the one after it
            step = jnp.zeros_like(times).at[k].set(eps)
            difference = (omega_hat(times + step, data, w) - omega_hat(times - step, data, w)) / (
                2 * eps
            )
            np.testing.assert_allclose(reverse[0][:, k], difference, rtol=1e-6, atol=1e-8)
        for k, i in ((7, 2), (8, 0), (11, 3)):  # an outlier's observation, the ones after it
            step = jnp.zeros_like(data).at[k, i].set(eps)
            difference = (omega_hat(times, data + step, w) - omega_hat(times, data - step, w)) / (
                2 * eps
            )
            np.testing.assert_allclose(reverse[1][:, k, i], difference, rtol=1e-6, atol=1e-8)


@pytest.mark.parametrize("dtype", [np.float64, np.float32])
def test_loss_derivative_in_the_weights_is_the_envelope(weighted_case, dtype):
    """d loss / d wₖ = ½|ρₖ|² = 2 sin²(θₖ/2) at the optimum (envelope theorem: the fit's own change
    does not move a stationary loss), zero weights included; float32 too (it was NaN at w = 0)."""
    c = weighted_case
    qs = c["qs"].astype(dtype)
    fit = jaxquat.fit_angular_velocity(c["times"], qs, weights=c["weights"].astype(dtype))
    gradient = jax.grad(lambda w: jaxquat.fit_angular_velocity(c["times"], qs, weights=w).loss)(
        jnp.asarray(c["weights"], dtype)
    )
    assert gradient.dtype == dtype
    expected = 2 * np.sin(np.asarray(fit.residual_angles, np.float64) / 2) ** 2
    tolerance = 1e-12 if dtype == np.float64 else 2e-5
    np.testing.assert_allclose(gradient, expected, rtol=tolerance, atol=tolerance)
    assert np.min(expected[[7, 23]]) > 0.1


@pytest.mark.parametrize("model", ["constant", "spline", "piecewise_linear"])
@pytest.mark.parametrize("frame", ["world", "body"])
def test_outliers_of_weight_zero_are_not_used_even_first(weighted_case, model, frame):
    """Outliers of weight 0 at the first observation and inside: the starting guesses took
    log-differences to them (rates of up to π/Δt) and centred the parameters on observation 0; the
    spline fit then converged to a wrong minimum (loss 7.9 instead of 6e-5) with converged=True."""
    c = weighted_case
    times, omega = c["times"], c["omega"]
    q0 = _to_wxyz(Rotation.random(random_state=3))
    rng = np.random.default_rng(7)
    qs = _add_noise(rng, _constant_truth(rng, times, omega, q0, frame))
    bad = [0, 1, 7, 39]
    qs[bad] = _to_wxyz(Rotation.random(len(bad), random_state=5))
    weights = np.ones(40)
    weights[bad] = 0.0
    knots = None if model == "constant" else np.linspace(times[0], times[-1], 4)
    fit = jaxquat.fit_angular_velocity(
        times, qs, weights=weights, model=model, knots=knots, frame=frame
    )
    assert fit.converged
    good = np.delete(np.arange(40), bad)
    # Noise σ = 1e-3 rad per axis: the fitted orientations stay within a few σ of the good data.
    assert float(np.max(np.asarray(fit.residual_angles)[good])) < 6 * SIGMA
    estimate = fit.omega if model == "constant" else fit.omega(jnp.asarray(times[good]))
    assert float(np.max(np.abs(np.asarray(estimate) - omega))) < 0.02
    # The first observation is an outlier; q0 is still the truth at t0.
    assert float(jaxquat.angle_between(fit.q0, jnp.asarray(q0))) < 6 * SIGMA


@pytest.mark.parametrize("model", ["constant", "spline"])
@pytest.mark.parametrize("frame", ["world", "body"])
def test_half_a_turn_per_interval(model, frame):
    """|ω|Δt = π exactly: each log-difference is n̂π or −n̂π as the noise falls, the starting ω
    averaged them to ~0.05π, and the fit converged (converged=True) to residuals of 2.9 rad. The
    start now keeps near-π turns on the branch that continues the previous rate."""
    rng = np.random.default_rng(11)
    times = np.arange(20.0)
    axis = np.array([0.3, -0.5, 0.8]) / np.linalg.norm([0.3, -0.5, 0.8])
    omega = np.pi * axis
    qs = _add_noise(
        rng, _constant_truth(rng, times, omega, _to_wxyz(Rotation.random(random_state=2)), frame)
    )
    knots = None if model == "constant" else 4
    fit = jaxquat.fit_angular_velocity(times, qs, model=model, knots=knots, frame=frame)
    assert fit.converged
    assert float(np.max(np.asarray(fit.residual_angles))) < 6 * SIGMA
    estimate = fit.omega if model == "constant" else fit.omega(jnp.asarray(times))
    # ±ω fit the observations equally (a half turn either way): compare up to that sign.
    estimate = np.asarray(estimate)
    error = min(np.max(np.abs(estimate - omega)), np.max(np.abs(estimate + omega)))
    assert error < 0.01


def _torque_free_observations(
    num, span, sigma, seed, inertia=(1.0, 1.7, 2.6), omega0=(0.4, 1.1, -0.3)
):
    """Noisy orientations of a torque-free body (by default asymmetric and tumbling) by SciPy's
    DOP853."""
    inertia = np.array(inertia)
    omega0 = np.array(omega0)
    q0 = _to_wxyz(Rotation.random(random_state=6))

    def rhs(t, y):
        omega = y[4:]
        w, x, yy, z = y[:4]
        a, b, c = omega
        dq = 0.5 * np.array(
            [
                -x * a - yy * b - z * c,
                w * a + yy * c - z * b,
                w * b - x * c + z * a,
                w * c + x * b - yy * a,
            ]
        )
        return np.concatenate([dq, np.cross(inertia * omega, omega) / inertia])

    rng = np.random.default_rng(seed)
    times = _random_times(rng, num, span)
    solution = solve_ivp(
        rhs,
        (0.0, span),
        np.concatenate([q0, omega0]),
        t_eval=times,
        method="DOP853",
        rtol=1e-13,
        atol=1e-13,
    )
    qs = solution.y[:4].T
    if sigma:
        qs = _add_noise(rng, qs, sigma)
    return times, _flip_signs(rng, qs), inertia, omega0


@pytest.mark.parametrize(
    "num, kinds",
    [
        (60, [(12.0, 1e-3), (12.0, 1e-2), (30.0, 1e-3), (45.0, 3e-3)]),  # one compilation
        (500, [(20.0, 1e-2)]),  # 25 per second: rates over baselines of several intervals
    ],
)
def test_rigid_body_from_noisy_data_with_outliers(num, kinds):
    """Noisy observations over (span, σ), three noise draws each. The start took ω̇ from differences
    of neighbouring rates, whose noise is ~σ/Δt², and the fit ended unconverged at I₃/I₁ = 400 (loss
    46) or NaN; ω₀ extrapolated from the first rates then put long and sparse fits in a wrong minimum
    with converged=True (χ²/dof up to 6e4), as did a start fitted to the whole span at once (sparse
    data; some draws here have gaps turning the body by up to 1.5π, outside the documented domain).
    Outliers of weight 0 (the first observation among them) are bridged. 2·loss/σ² is χ² with
    3(N − 3) − 8 degrees of freedom."""
    bad = [0, 7, 23]
    for span, sigma in kinds:
        for seed in (10, 11, 12):
            times, qs, inertia, omega0 = _torque_free_observations(num, span, sigma, seed=seed)
            qs[bad] = _to_wxyz(Rotation.random(len(bad), random_state=5))
            weights = np.ones(num)
            weights[bad] = 0.0
            fit = jaxquat.fit_rigid_body(times, qs, weights=weights)
            case = (span, sigma, seed)
            assert fit.converged, case
            dof = 3 * (num - len(bad)) - 8
            chi2 = 2 * float(fit.loss) / sigma**2
            assert abs(chi2 - dof) < 5 * np.sqrt(2 * dof), (case, chi2, dof)
            ratio_error = np.max(np.abs(np.asarray(fit.inertia_ratios) / inertia[1:] - 1))
            assert ratio_error < 2 * sigma, (case, ratio_error)  # measured ≤ 0.5σ
            assert np.linalg.norm(fit.omega0 - omega0) < 2 * sigma, case


def test_rigid_body_axisymmetric_in_free_precession():
    """I = 1 : 1 : 2.5 precessing: the equation error is nearly degenerate (singular values 9.7, 2.1,
    0.68), the start was the sphere, and the fit converged to ratios 0.90 : 1.10 with residuals of
    0.17 rad on exact data (converged=True; a review). Exact data and three noise draws."""
    for sigma, seed in [(0.0, 29), (1e-2, 1), (1e-2, 2), (1e-2, 3)]:
        times, qs, inertia, omega0 = _torque_free_observations(
            500, 20.0, sigma, seed, inertia=(1.0, 1.0, 2.5), omega0=(0.5, 0.2, 1.5)
        )
        fit = jaxquat.fit_rigid_body(times, qs)
        assert fit.converged, (sigma, seed)
        ratio_error = np.max(np.abs(np.asarray(fit.inertia_ratios) / inertia[1:] - 1))
        if sigma == 0:
            assert ratio_error < 1e-4 and float(np.max(fit.residual_angles)) < 1e-3
        else:
            dof = 3 * 500 - 8
            chi2 = 2 * float(fit.loss) / sigma**2
            assert abs(chi2 - dof) < 5 * np.sqrt(2 * dof), (seed, chi2, dof)
            assert ratio_error < 3 * sigma, (seed, ratio_error)


@pytest.mark.parametrize("sigma", [0.0, 1e-3])
def test_rigid_body_steady_spin_stays_finite(sigma):
    """A steady spin about a principal axis leaves the ratios undetermined (documented). With weights
    of 0 the equation-error start was 1 : 2e15 : 1e8 and the fit NaN; it must start from a sphere
    and fit the orientations. With noise the loss is flat in the ratios and the solver may wander
    along them to its step limit (converged=False, honestly), but the fit stays finite and good."""
    rng = np.random.default_rng(4)
    times = _random_times(rng, 60, 10.0)  # 60: the compilation of the test above
    q0 = _to_wxyz(Rotation.random(random_state=8))
    qs = _constant_truth(rng, times, np.array([0.0, 0.0, 1.5]), q0, frame="body")
    if sigma:
        qs = _add_noise(rng, qs, sigma)
    weights = np.ones(60)
    weights[[0, 59]] = 0.0
    fit = jaxquat.fit_rigid_body(times, qs, weights=weights)
    assert fit.converged or sigma > 0
    assert np.all(np.isfinite(np.asarray(fit.inertia))) and np.all(np.asarray(fit.inertia) > 0)
    assert float(np.max(np.asarray(fit.residual_angles)[1:-1])) < 6 * sigma + 1e-9
    np.testing.assert_allclose(fit.omega0, [0.0, 0.0, 1.5], atol=6 * sigma + 1e-9)


@pytest.mark.parametrize(
    "call, name",
    [
        (
            lambda c: jaxquat.fit_angular_velocity(c["times"], c["exact"], omega0=[np.nan, 0, 0]),
            "omega0",
        ),
        (
            lambda c: jaxquat.fit_rigid_body(c["times"], c["exact"], inertia0=[np.nan, 1, 2]),
            "inertia0",
        ),
        (lambda c: jaxquat.fit_rigid_body(c["times"], c["exact"], omega0=[0, np.inf, 0]), "omega0"),
    ],
)
def test_non_finite_starting_guesses_are_refused(constant_case, call, name):
    with pytest.raises(ValueError, match=rf"`{name}` must be finite"):
        call(constant_case)


def test_rows_of_extreme_magnitude_fit_like_unit_rows(constant_case):
    """Rows are only directions: 4.6e307·q (its largest component above 1/2.2e-308, where XLA's
    x/m = x·(1/m) flushed 1/m to zero and gave NaN) and 1e-300·q fit as q does."""
    c = constant_case
    reference = jaxquat.fit_angular_velocity(c["times"], c["noisy"])
    big = c["noisy"] * (4.6e307 / np.max(np.abs(c["noisy"]), axis=-1, keepdims=True))
    scaled = big.copy()
    scaled[::2] = c["noisy"][::2] * 1e-300
    fit = jaxquat.fit_angular_velocity(c["times"], scaled)
    np.testing.assert_allclose(fit.omega, reference.omega, rtol=0, atol=1e-13)
    np.testing.assert_allclose(fit.residual_angles, reference.residual_angles, rtol=0, atol=1e-13)


def test_fit_is_differentiable_in_the_data(constant_case):
    """Through optimistix's implicit adjoint: stretching time by s divides ω by s, so d ω̂/ds = −ω̂."""
    c = constant_case
    fit = jaxquat.fit_angular_velocity(c["times"], c["noisy"])
    derivative = jax.jacrev(
        lambda s: jaxquat.fit_angular_velocity(s * c["times"], c["noisy"]).omega
    )(1.0)
    np.testing.assert_allclose(derivative, -fit.omega, rtol=1e-9)


def test_vmap_1000_bodies_equals_one_by_one_and_cramer_rao():
    """Acceptance 5, and the bound checked statistically: for unbiased errors at the Cramér–Rao bound,
    eᵀ C⁻¹ e is χ²(3): its mean over 1,000 independent bodies is 3 ± 0.08."""
    rng = np.random.default_rng(42)
    num_bodies, num_obs, span = 1000, 200, 10.0
    times = np.stack([_random_times(rng, num_obs, span) for _ in range(num_bodies)])
    directions = rng.standard_normal((num_bodies, 3))
    directions /= np.linalg.norm(directions, axis=1, keepdims=True)
    omegas = directions * rng.uniform(0.5, 1.5, (num_bodies, 1))
    q0s = _to_wxyz(Rotation.random(num_bodies, random_state=5))
    qs = np.stack([_constant_truth(rng, times[b], omegas[b], q0s[b]) for b in range(num_bodies)])
    qs = _flip_signs(rng, _add_noise(rng, qs))

    start = time.perf_counter()
    batched = jax.jit(jax.vmap(jaxquat.fit_angular_velocity))(times, qs)
    jax.block_until_ready(batched)
    batched_time = time.perf_counter() - start
    assert np.all(batched.converged)
    assert batched.omega.shape == (num_bodies, 3)

    start = time.perf_counter()
    single = [jaxquat.fit_angular_velocity(times[b], qs[b]) for b in range(num_bodies)]
    jax.block_until_ready(single)
    loop_time = time.perf_counter() - start
    one_by_one = np.stack([np.asarray(f.omega) for f in single])
    np.testing.assert_allclose(batched.omega, one_by_one, rtol=0, atol=1e-12)
    np.testing.assert_allclose(
        batched.q0, np.stack([np.asarray(f.q0) for f in single]), rtol=0, atol=1e-12
    )
    np.testing.assert_array_equal(batched.num_steps, [int(f.num_steps) for f in single])

    errors = np.asarray(batched.omega) - omegas
    mahalanobis = np.array(
        [
            errors[b] @ np.linalg.solve(_constant_crb(times[b], omegas[b]), errors[b])
            for b in range(num_bodies)
        ]
    )
    print(
        f"\n1,000 bodies: vmapped {batched_time:.1f} s (incl. compile), one by one {loop_time:.1f} s; "
        f"mean eᵀC⁻¹e = {mahalanobis.mean():.3f} (χ²(3): 3 ± 0.08); "
        f"steps median {np.median(batched.num_steps):.0f}, max {np.max(batched.num_steps)}"
    )
    assert 2.75 < mahalanobis.mean() < 3.25
    assert np.max(batched.num_steps) <= 50


def test_float32_in_float32_out_body_frame():
    rng = np.random.default_rng(3)
    times = _random_times(rng, 100, 5.0)
    omega = np.array([1.1, 0.2, -0.6])
    q0 = _to_wxyz(Rotation.random(random_state=9))
    qs = _flip_signs(rng, _constant_truth(rng, times, omega, q0, frame="body"))
    fit = jaxquat.fit_angular_velocity(
        times.astype(np.float32), qs.astype(np.float32), frame="body"
    )
    for leaf in jax.tree_util.tree_leaves(fit):
        if jnp.issubdtype(leaf.dtype, jnp.floating):
            assert leaf.dtype == jnp.float32
    error = float(np.max(np.abs(fit.omega - omega)))
    print(f"\nconstant body-frame ω, float32 exact data: |Δω|max = {error:.1e}")
    assert fit.converged
    assert error < 1e-5
    assert min(np.linalg.norm(fit.q0 - q0), np.linalg.norm(fit.q0 + q0)) < 1e-5


# --------------------------------------------------------------------------------------------------
# Time-varying angular velocity


def _coning_truth(times, spin=2.1, precession=1.3, tilt=0.4):
    """q(t) = exp(Ω_p t ẑ) ⊗ exp(β x̂) ⊗ exp(Ω_s t ẑ): the body axis cones about ẑ.

    World ω(t) = Ω_p ẑ + Ω_s · (exp(Ω_p t ẑ) exp(β x̂)) ẑ.
    """
    z = np.array([0.0, 0.0, 1.0])
    outer = Rotation.from_rotvec(np.outer(precession * times, z)) * Rotation.from_rotvec(
        [tilt, 0, 0]
    )
    qs = _to_wxyz(outer * Rotation.from_rotvec(np.outer(spin * times, z)))
    return qs, precession * z + spin * outer.apply(z)


def _relative_rms(curve, truth_fn, times):
    t = np.linspace(times[0], times[-1], 2001)
    error = np.asarray(curve(t)) - truth_fn(t)
    return float(np.sqrt(np.mean(np.sum(error**2, -1)) / np.mean(np.sum(truth_fn(t) ** 2, -1))))


def test_coning_spline_recovers_omega_t():
    """Acceptance 2: coning, 20 knots, noise-free, non-uniform times, mixed signs: ω(t) within 1e-3."""
    rng = np.random.default_rng(5)
    times = _random_times(rng, 200, 6.0)
    qs, _ = _coning_truth(times)
    fit = jaxquat.fit_angular_velocity(times, _flip_signs(rng, qs), model="spline", knots=20)
    error = _relative_rms(fit.omega, lambda t: _coning_truth(t)[1], times)
    print(
        f"\nconing, spline with 20 knots: relative RMS ω(t) error {error:.1e}, {int(fit.num_steps)} steps"
    )
    assert fit.converged
    assert error <= 1e-3
    assert isinstance(fit.omega, jaxquat.AngularVelocityCurve)


def test_piecewise_linear_recovers_piecewise_linear_truth():
    """Body-frame ω(t) piecewise linear, knots at observation times: the model class contains the
    truth and ω is smooth on every interval (Magnus-4 keeps its order), so exact data (SciPy's DOP853)
    are fitted to the integrator's accuracy."""
    rng = np.random.default_rng(8)
    times = _random_times(rng, 120, 4.0)
    knots = times[[0, 40, 70, 119]]
    knot_values = rng.uniform(-1.5, 1.5, (4, 3))

    def omega_true(t):
        return np.stack([np.interp(t, knots, knot_values[:, i]) for i in range(3)], axis=-1)

    def rhs(t, q):
        w, x, y, z = q
        a, b, c = omega_true(t)
        return 0.5 * np.array(
            [
                -x * a - y * b - z * c,
                w * a + y * c - z * b,
                w * b - x * c + z * a,
                w * c + x * b - y * a,
            ]
        )

    q0 = _to_wxyz(Rotation.random(random_state=2))
    solution = solve_ivp(rhs, (0.0, 4.0), q0, t_eval=times, method="DOP853", rtol=1e-13, atol=1e-13)
    fit = jaxquat.fit_angular_velocity(
        times, solution.y.T, model="piecewise_linear", knots=knots, frame="body", substeps=4
    )
    error = np.max(np.abs(np.asarray(fit.omega.values) - knot_values))
    print(f"\npiecewise-linear body ω, exact data: max knot error {error:.1e}")
    assert fit.converged
    assert error < 1e-8


def test_piecewise_linear_keeps_fourth_order_with_knots_between_observations():
    """Knots that fall inside observation intervals: the model's Magnus-4 steps used to straddle the
    kinks of ω(t), and the error only halved with the substeps (first order: 9.6e-4, 5.1e-4 at 8 and
    16 substeps here). The steps now end on the knots: fourth order, 16× per halving. The data are
    SciPy DOP853 restarted at each kink (so the reference has no kink inside a step)."""
    rng = np.random.default_rng(3)
    knots = np.linspace(0.0, 6.0, 6)
    knot_values = 2.0 * rng.standard_normal((6, 3))
    times = np.sort(np.concatenate([[0.0, 6.0], rng.uniform(0.0, 6.0, 23)]))
    assert not np.any(np.isin(knots[1:-1], times))

    def rhs(t, q):
        a, b, c = (np.interp(t, knots, knot_values[:, i]) for i in range(3))
        w, x, y, z = q  # world frame: ½ ω̃ q
        return 0.5 * np.array(
            [
                -a * x - b * y - c * z,
                a * w + b * z - c * y,
                b * w + c * x - a * z,
                c * w + a * y - b * x,
            ]
        )

    q = _to_wxyz(Rotation.random(random_state=4))
    observed = []
    for start, end in zip(knots[:-1], knots[1:], strict=True):
        inside = times[(times >= start) & (times < end)]
        solution = solve_ivp(
            rhs,
            (start, end),
            q,
            t_eval=np.append(inside, end),
            method="DOP853",
            rtol=1e-13,
            atol=1e-14,
        )
        observed.extend(solution.y.T[:-1])
        q = solution.y[:, -1]
    observed.append(q)
    errors = []
    for substeps in (4, 8):
        fit = jaxquat.fit_angular_velocity(
            times, np.asarray(observed), model="piecewise_linear", knots=6, substeps=substeps
        )
        assert fit.converged
        errors.append(np.max(np.abs(np.asarray(fit.omega.values) - knot_values)))
    print(f"\nknot errors at 4 and 8 substeps: {errors[0]:.2e}, {errors[1]:.2e}")
    assert errors[0] / errors[1] > 10.0  # 16 for a fourth-order method
    assert errors[1] < 5e-5


def test_spline_curve_matches_scipy_not_a_knot():
    rng = np.random.default_rng(4)
    knots = np.sort(rng.uniform(0, 3, 9))
    values = rng.standard_normal((9, 3))
    t = np.linspace(knots[0] - 0.2, knots[-1] + 0.2, 301)  # includes cubic extrapolation

    @jax.jit
    def evaluate(knots, values, t):
        through = jaxquat.AngularVelocityCurve.through
        return through(knots, values, "spline")(t), through(knots, values, "piecewise_linear")(t)

    spline, linear = evaluate(knots, values, t)
    np.testing.assert_allclose(spline, CubicSpline(knots, values)(t), rtol=1e-10, atol=1e-10)
    inside = (t >= knots[0]) & (t <= knots[-1])
    expected = np.stack([np.interp(t[inside], knots, values[:, i]) for i in range(3)], -1)
    np.testing.assert_allclose(linear[inside], expected, rtol=1e-12, atol=1e-12)
    # Outside the knots the end pieces continue linearly.
    before = t < knots[0]
    slope = (values[1] - values[0]) / (knots[1] - knots[0])
    np.testing.assert_allclose(
        linear[before], values[0] + (t[before] - knots[0])[:, None] * slope, rtol=1e-12, atol=1e-12
    )


# --------------------------------------------------------------------------------------------------
# Torque-free rigid body


def test_rigid_body_inertia_ratios_and_omega0():
    """Acceptance 3: 500 noise-free orientations (SciPy DOP853, random signs) of a tumbling asymmetric
    body: inertia ratios and ω₀ to 1e-4 relative."""
    times, qs, inertia, omega0 = _torque_free_observations(500, 20.0, 0.0, seed=9)
    fit = jaxquat.fit_rigid_body(times, qs)
    ratio_error = np.max(np.abs(np.asarray(fit.inertia_ratios) / (inertia[1:] / inertia[0]) - 1))
    omega_error = np.linalg.norm(fit.omega0 - omega0) / np.linalg.norm(omega0)
    print(
        f"\ntorque-free body: inertia ratios rel. error {ratio_error:.1e}, ω0 rel. error {omega_error:.1e}, {int(fit.num_steps)} steps"
    )
    assert fit.converged
    assert ratio_error <= 1e-4
    assert omega_error <= 1e-4


# --------------------------------------------------------------------------------------------------
# Validation


def test_validation_errors():
    times = np.linspace(0.0, 1.0, 5)
    qs = np.tile([1.0, 0.0, 0.0, 0.0], (5, 1))
    fit = jaxquat.fit_angular_velocity
    with pytest.raises(ValueError, match="at least 3 observations"):
        fit(times[:2], qs[:2])
    with pytest.raises(ValueError, match="strictly increasing"):
        fit(times[::-1], qs)
    with pytest.raises(ValueError, match="strictly increasing"):
        fit(np.array([0.0, 1.0, 1.0, 2.0, 3.0]), qs)
    with pytest.raises(ValueError, match="`times`"):
        fit(times[:4], qs)
    with pytest.raises(ValueError, match="`qs`"):
        fit(times, qs[:, :3])
    with pytest.raises(ValueError, match="`qs`"):
        fit(times, qs[None])
    with pytest.raises(ValueError, match="`weights`"):
        fit(times, qs, weights=np.ones(4))
    with pytest.raises(ValueError, match="`omega0`"):
        fit(times, qs, omega0=np.zeros(4))
    with pytest.raises(ValueError, match="`model`"):
        fit(times, qs, model="cubic")
    with pytest.raises(ValueError, match="`frame`"):
        fit(times, qs, frame="inertial")
    with pytest.raises(ValueError, match="`knots`"):
        fit(times, qs, model="spline", knots=3)
    with pytest.raises(ValueError, match="`knots`"):
        fit(times, qs, model="piecewise_linear", knots=np.array([0.0, 0.5, 0.5]))
    with pytest.raises(ValueError, match="`knots`"):
        fit(times, qs, knots=4)
    with pytest.raises(ValueError, match="`substeps`"):
        fit(times, qs, model="spline", knots=4, substeps=0)
    with pytest.raises(ValueError, match="`weights`"):
        fit(times, qs, weights=-np.ones(5))
    with pytest.raises(ValueError, match="`polish`"):
        fit(times, qs, polish=-1)
    with pytest.raises(ValueError, match="`knots`"):
        jaxquat.AngularVelocityCurve.through(times[:3], np.zeros((3, 3)), "spline")
    with pytest.raises(ValueError, match="`kind`"):
        jaxquat.AngularVelocityCurve.through(times, np.zeros((5, 3)), "constant")
    with pytest.raises(ValueError, match="at least 3 observations"):
        jaxquat.fit_rigid_body(times[:2], qs[:2])
    with pytest.raises(ValueError, match="strictly increasing"):
        jaxquat.fit_rigid_body(times[::-1], qs)
    with pytest.raises(ValueError, match="`inertia0`"):
        jaxquat.fit_rigid_body(times, qs, inertia0=np.array([1.0, -1.0, 2.0]))
    with pytest.raises(ValueError, match="`omega0`"):
        jaxquat.fit_rigid_body(times, qs, omega0=np.zeros((2, 3)))


def _knot_jacobian_rank(times, knots, model):
    """Numerical rank of d(fitted orientations)/d(knot values) at a generic ω(t), from jacfwd through
    the fit's own model (an independent look at what `_check_identifiable` predicts from ∫ B_i dt)."""
    from jaxquat._fitting import _curve_model

    times, knots = jnp.asarray(times), jnp.asarray(knots)
    values = jnp.asarray(np.random.default_rng(3).normal(size=(knots.shape[0], 3)))
    reference = jaxquat.identity()

    def fitted(values):
        return _curve_model((jnp.zeros(3), values), times, reference, knots, "world", model, 4)[2]

    jac = jax.jacfwd(fitted)(values).reshape(-1, values.size)
    singular = np.linalg.svd(np.asarray(jac), compute_uv=False)
    return int(np.sum(singular > 1e-8 * singular[0]))


@pytest.mark.parametrize(
    "model, knots, determined",
    [
        ("piecewise_linear", [0.0, 0.3, 0.6, 4.0], False),  # two knots inside (t0, t1)
        (
            "piecewise_linear",
            [0.0, 2.2, 2.4, 2.6, 5.0],
            True,
        ),  # three inside (t2, t3), yet told apart
        (
            "piecewise_linear",
            [0.0, 2.2, 2.4, 2.6, 2.8, 6.0],
            False,
        ),  # two hats only inside (t2, t3)
        ("piecewise_linear", [-10.0, -9.0, 0.0, 4.0], False),  # two knots before the observations
        ("piecewise_linear", [0.0, 1.5, 2.5, 4.0], True),
        ("spline", [0.0, 0.2, 0.4, 4.0], True),  # 4 knots: one global cubic, however bunched
        ("spline", [0.0, 1.5, 2.5, 3.5, 5.0], True),
    ],
)
def test_explicit_knots_bunched_between_observations_are_rejected(model, knots, determined):
    """Counting knots (K ≤ T − 1) is not enough: knots bunched between two neighbouring observations
    leave the knot values undetermined. The check agrees with the rank of the model's Jacobian with
    respect to the knot values (3K when determined, less otherwise), not with a count of knots per
    interval, and a determined setup still fits a constant ω exactly."""
    times = np.arange(knots[-1] + 1.0)  # observations at t = 0, 1, …, last knot
    knots = np.asarray(knots)
    rank = _knot_jacobian_rank(times, knots, model)
    assert (rank == 3 * knots.shape[0]) == determined, rank
    omega = np.array([0.3, -0.2, 0.5])
    qs = jaxquat.step(jaxquat.identity(), jnp.asarray(omega), jnp.asarray(times))
    if determined:
        fit = jaxquat.fit_angular_velocity(times, qs, model=model, knots=knots)
        np.testing.assert_allclose(
            fit.omega.values, np.broadcast_to(omega, (len(knots), 3)), atol=1e-9
        )
    else:
        with pytest.raises(ValueError, match="`knots`: the observation times do not determine"):
            jaxquat.fit_angular_velocity(times, qs, model=model, knots=knots)


@pytest.mark.parametrize(
    "knots, determined",
    [
        ([0.0, 0.5, 5.0], True),
        ([-3.0, 0.5, 5.0], True),
        ([0.0, 0.5, 5.0, 6.0], False),
        ([-2.0, -1.0, 0.5, 1.0], False),
    ],
)
def test_piecewise_linear_knots_outside_the_observed_times(knots, determined):
    """Observations on [0, 1]: the first knot past either end is determined through the curve's
    values inside (the fit recovers a constant ω exactly), a second past the same end is not (a
    ValueError counting the knots outside), as the rank of the model's Jacobian says."""
    times = np.linspace(0.0, 1.0, 21)
    knots = np.asarray(knots)
    rank = _knot_jacobian_rank(times, knots, "piecewise_linear")
    assert (rank == 3 * knots.shape[0]) == determined, rank
    omega = np.array([0.3, -0.2, 0.5])
    qs = jaxquat.step(jaxquat.identity(), jnp.asarray(omega), jnp.asarray(times))
    if determined:
        fit = jaxquat.fit_angular_velocity(times, qs, model="piecewise_linear", knots=knots)
        np.testing.assert_allclose(
            fit.omega.values, np.broadcast_to(omega, (len(knots), 3)), atol=1e-9
        )
    else:
        with pytest.raises(ValueError, match="do not determine.*2 knots lie outside the observed"):
            jaxquat.fit_angular_velocity(times, qs, model="piecewise_linear", knots=knots)


@pytest.mark.parametrize(
    "model, knots, determined",
    [
        ("piecewise_linear", 10, False),
        ("piecewise_linear", None, False),  # the default count, 7
        ("spline", 10, False),
        ("spline", None, True),  # 7 knots of one not-a-knot cubic spline: coupled across the gap
    ],
)
def test_evenly_spaced_knots_over_a_gap_in_the_observations(model, knots, determined):
    """Observations on [0, 1] and [9, 10]: evenly spaced knots (an int, or the default count) put
    knots inside the gap, whose values only the one rotation across it may constrain. The fit
    reported one of infinitely many exact solutions with converged=True (a probe of the command
    line); it is now the ValueError that explicit knot times in the gap already gave, exactly when
    the rank of the model's Jacobian w.r.t. the knot values is short. Determined setups, and knot
    times placed among the observations, fit a constant ω exactly."""
    times = np.concatenate([np.linspace(0.0, 1.0, 15), np.linspace(9.0, 10.0, 15)])
    omega = np.array([0.03, -0.02, 0.05])
    qs = jaxquat.step(jaxquat.identity(), jnp.asarray(omega), jnp.asarray(times))
    even = np.linspace(times[0], times[-1], 7 if knots is None else knots)
    assert (_knot_jacobian_rank(times, even, model) == 3 * len(even)) == determined
    if determined:
        fit = jaxquat.fit_angular_velocity(times, qs, model=model, knots=knots)
        np.testing.assert_allclose(fit.omega.values, np.broadcast_to(omega, (7, 3)), atol=1e-9)
    else:
        with pytest.raises(ValueError, match="do not determine.*evenly spaced.*pass fewer knots"):
            jaxquat.fit_angular_velocity(times, qs, model=model, knots=knots)
    placed = np.array([0.0, 0.5, 1.0, 9.0, 9.5, 10.0])
    assert _knot_jacobian_rank(times, placed, model) == 3 * len(placed)
    fit = jaxquat.fit_angular_velocity(times, qs, model=model, knots=placed)
    np.testing.assert_allclose(fit.omega.values, np.broadcast_to(omega, (6, 3)), atol=1e-9)


@pytest.mark.parametrize("frame", ["world", "body"])
@pytest.mark.parametrize("gap", [0.35, 1.3])
def test_constant_fit_across_a_gap_of_more_than_half_a_turn(frame, gap):
    """Samples 1 rad apart at 10 rad/s with one gap of 3.5 or 13 rad: the gap's shortest rotation
    points the other way, and its log-difference dragged the starting ω from 10 to 9; the fit then
    converged to 8.56 rad/s with residuals of 85° rms and converged=True (a review). The other
    intervals determine ω, so the fit must recover it, with and without noise."""
    times = np.concatenate([np.arange(30) * 0.1, 2.9 + gap + np.arange(30) * 0.1])
    omega = np.array([1.0, -2.0, 9.7])
    _assert_constant_fit_recovers(
        times, 10.0 * omega / np.linalg.norm(omega), [0.3, -1.1, 0.4], frame, 31
    )


def _assert_constant_fit_recovers(times, omega, rotvec0, frame, seed):
    """Exact data to 1e-9 and noisy data to 5× the Cramér–Rao bound, q/−q mixed, converged."""
    rng = np.random.default_rng(seed)
    exact = _constant_truth(rng, times, omega, _to_wxyz(Rotation.from_rotvec(rotvec0)), frame)
    bound = 5 * np.sqrt(np.max(np.linalg.eigvalsh(_constant_crb(times, omega))))
    for qs, tolerance in [(exact, 1e-9), (_add_noise(rng, exact), bound)]:
        fit = jaxquat.fit_angular_velocity(times, _flip_signs(rng, qs), frame=frame)
        assert fit.converged
        np.testing.assert_allclose(fit.omega, omega, atol=tolerance)
        assert float(np.max(fit.residual_angles)) < max(1e-9, 5 * SIGMA)


@pytest.mark.parametrize("frame", ["world", "body"])
def test_constant_fit_with_gaps_covering_most_of_the_span(frame):
    """40 intervals of 0.25 rad at 5 rad/s, then 4 gaps of 3.5–6.5 rad covering more than half the
    span: the duration-weighted median rate the start took its branches from was the gaps' (a review:
    ω 0.27 instead of 5, residuals of 3.06 rad, converged=True). The many short intervals fix ω."""
    times = np.concatenate([np.linspace(0.0, 2.0, 41), 2.0 + np.cumsum([0.9, 1.1, 1.3, 0.7])])
    omega = np.array([0.6, -0.8, 4.9])
    _assert_constant_fit_recovers(
        times, 5.0 * omega / np.linalg.norm(omega), [-0.4, 0.9, 0.2], frame, 44
    )


@pytest.mark.parametrize("model", ["piecewise_linear", "spline"])
def test_curve_fit_when_noise_flips_the_first_near_half_turn(model):
    """A body turning by 0.88–0.999π per interval about a tilted axis; observation 1 is 0.01 rad off,
    which flips the first interval's shortest rotation to the other way. The curve fits' branch chain
    started from that interval and took every near-π turn backwards (a review: residuals of 2.8 rad,
    converged=True). The fit must reach the minimum it reaches from the true ω."""
    rng = np.random.default_rng(0)
    axis = Rotation.from_rotvec([0.3, 0.2, 0.1]).apply([0.0, 0.0, 1.0])
    omega = np.pi * axis
    times = np.r_[0.0, np.cumsum(np.r_[0.999, rng.uniform(0.88, 0.99, 30)])]
    rotations = Rotation.from_rotvec(np.outer(times, omega)) * Rotation.from_rotvec(
        [0.2, -0.5, 1.0]
    )
    qs = _to_wxyz(rotations)
    qs[1] = _to_wxyz(Rotation.from_rotvec(0.01 * axis) * rotations[1])
    fit = jaxquat.fit_angular_velocity(times, qs, model=model, knots=4)
    from_truth = jaxquat.fit_angular_velocity(times, qs, model=model, knots=4, omega0=omega)
    assert fit.converged
    np.testing.assert_allclose(fit.loss, from_truth.loss, rtol=1e-6)
    assert float(np.max(fit.residual_angles)) < 0.02
    np.testing.assert_allclose(fit.omega(times), from_truth.omega(times), atol=1e-6)


@pytest.mark.parametrize("model", ["piecewise_linear", "spline"])
def test_time_varying_start_is_not_pulled_by_a_short_noisy_interval(model):
    """25 random times over 6 s (one interval of 1 ms), 0.01 rad of noise, constant ω: the start's
    least squares counted the short interval's rate (noise σ/Δt ≈ 10 rad/s) like any other, and the
    fit converged to a local minimum (loss 6.4; 5.7 for the same times in ms) (helper-53)."""
    rng = np.random.default_rng(0)
    times = np.sort(rng.uniform(0, 6, 25))
    times[0] = 0.0
    assert np.min(np.diff(times)) < 2e-3
    omega = np.array([0.4, -0.9, 0.6])
    q0 = np.array([0.3, -0.5, 0.7, 0.4]) / np.linalg.norm([0.3, -0.5, 0.7, 0.4])
    noise = Rotation.from_rotvec(0.01 * rng.normal(size=(25, 3)))
    truth = Rotation.from_rotvec(np.outer(times, omega)) * Rotation.from_quat(q0[[1, 2, 3, 0]])
    observed = (noise * truth).as_quat()[:, [3, 0, 1, 2]]
    for scale in (1.0, 1e3):
        fit = jaxquat.fit_angular_velocity(times * scale, observed, model=model, knots=5)
        assert bool(fit.converged)
        assert float(fit.loss) < 5e-3  # ½ Σ |ρ|² of 25 residuals of ~0.01 rad
        np.testing.assert_allclose(
            np.asarray(fit.omega.values) * scale, np.tile(omega, (5, 1)), atol=0.1
        )


@pytest.mark.parametrize("step, dtype", [(1e-310, np.float64), (1e-40, np.float32)])
def test_subnormal_time_steps_are_refused(step, dtype):
    # XLA flushes subnormal numbers to zero: strictly increasing times whose steps are subnormal
    # gave durations of 0 and a NaN fit (converged=False) instead of a ValueError.
    omega = jnp.array([0.3, 0.2, 0.1])
    times = np.concatenate([[0.0, step, 2 * step], np.linspace(1.0, 2.0, 7)])
    qs = np.asarray(jaxquat.step(jaxquat.identity(), omega, times), dtype)
    with pytest.raises(ValueError, match="`times` must increase by at least the smallest normal"):
        jaxquat.fit_angular_velocity(times.astype(dtype), qs)
    with pytest.raises(ValueError, match="`times` must increase by at least the smallest normal"):
        jaxquat.fit_angular_velocity(times, qs)  # float64 times, durations cast to the data's dtype


def test_subnormal_steps_of_float16_times_or_data():
    # The durations are cast to the data's dtype: float16 times with steps of 1e-5 (subnormal in
    # float16, exact in float32) fit float32 data (they were refused), and float16 data at such
    # steps gave a NaN fit with float32 times (it was not refused).
    omega = jnp.array([0.3, 0.2, 0.1])
    times = (np.arange(10) * 1e-5).astype(np.float16)
    qs = jaxquat.step(jaxquat.identity(), omega * 1e4, times.astype(np.float64))
    fit = jaxquat.fit_angular_velocity(times, np.asarray(qs, np.float32))
    np.testing.assert_allclose(np.asarray(fit.omega) / 1e4, omega, rtol=1e-5)
    with pytest.raises(ValueError, match="`times` must increase by at least the smallest normal"):
        jaxquat.fit_angular_velocity(times.astype(np.float32), np.asarray(qs, np.float16))
