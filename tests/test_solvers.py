"""diffrax vector fields and Lie-group solvers: exactness, orders, adaptivity, dense output, gradients.

References are closed forms: the coning motion q(t) = exp(Ωt ẑ) exp(α x̂) exp(λt ẑ) (angular velocity in
both frames in closed form), exp(ωt) ⊗ q0 for constant ω, products of exponentials for sampled ω, and
stock `diffrax.Tsit5` at a tight tolerance as an independent check for the rigid body.
"""

from __future__ import annotations

import math

import diffrax
import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest
from helpers import random_unit
from jax.experimental import io_callback

import jaxquat as jq

SPIN, TILT, PRECESS = 1.3, 0.7, 2.1
T_END = 2.3  # not a whole number of periods: odd-order error terms stay visible


def coning_exact(t):
    """q(t) = exp(Ωt ẑ) ⊗ exp(α x̂) ⊗ exp(λt ẑ), for scalar or batched t."""
    t = jnp.asarray(t)
    zero = jnp.zeros_like(t)
    spin = jq.from_rotvec(jnp.stack([zero, zero, SPIN * t], -1))
    tilt = jq.from_rotvec(jnp.array([TILT, 0.0, 0.0], t.dtype))
    precess = jq.from_rotvec(jnp.stack([zero, zero, PRECESS * t], -1))
    return jq.multiply(jq.multiply(spin, tilt), precess)


class Coning(eqx.Module):
    """The coning angular velocity: world Ωẑ + R(exp(Ωt ẑ) exp(α x̂)) λẑ, body λẑ + R(…)ᵀ Ωẑ."""

    frame: str = eqx.field(static=True)

    def __call__(self, t, q):
        t = jnp.asarray(t)
        zero = jnp.zeros_like(t)
        z = jnp.stack([zero, zero, 1.0 + zero])
        tilt = jq.from_rotvec(jnp.stack([TILT + zero, zero, zero]))
        if self.frame == "world":
            spin = jq.from_rotvec(jnp.stack([zero, zero, SPIN * t]))
            return SPIN * z + jq.rotate(PRECESS * z, jq.multiply(spin, tilt))
        precess = jq.from_rotvec(jnp.stack([zero, zero, PRECESS * t]))
        return PRECESS * z + jq.rotate(SPIN * z, jq.conjugate(jq.multiply(tilt, precess)))


def angle(p, q):
    return np.asarray(jq.angle_between(p, q))


def slope(hs, errors):
    return float(np.polyfit(np.log(hs), np.log(errors), 1)[0])


# ----------------------------------------------------------------------------------------------------
# Vector fields


def test_vector_fields_are_the_rates():
    q = random_unit(jax.random.key(0), (5,))
    omega = jax.random.normal(jax.random.key(1), (5, 3))
    for frame in ("world", "body"):
        plain = jq.kinematic_vector_field(omega, frame=frame)
        corrected = jq.corrected_vector_field(omega, 0.3, frame=frame)
        np.testing.assert_allclose(
            plain(0.0, q, None), jq.rate(q, omega, frame=frame), rtol=0, atol=1e-15
        )
        np.testing.assert_allclose(
            corrected(0.0, q, None),
            jq.corrected_rate(q, omega, 0.3, frame=frame),
            rtol=0,
            atol=1e-15,
        )
    # Callables: omega(t, q) and omega(t, q, args) (then diffeqsolve's args are passed).
    field = jq.kinematic_vector_field(lambda t, q, args: args * omega)
    np.testing.assert_allclose(field(0.0, q, 2.0), jq.rate(q, 2.0 * omega), atol=1e-15)
    field = jq.kinematic_vector_field(lambda t, q: t * omega)
    np.testing.assert_allclose(field(3.0, q, None), jq.rate(q, 3.0 * omega), atol=1e-15)


def test_validation_errors():
    with pytest.raises(ValueError, match="omega"):
        jq.kinematic_vector_field(jnp.zeros(4))
    with pytest.raises(ValueError, match="frame"):
        jq.corrected_vector_field(jnp.zeros(3), 0.1, frame="inertial")
    with pytest.raises(ValueError, match="frame"):
        jq.Magnus4(frame="space")
    with pytest.raises(ValueError, match="frame"):
        jq.Magnus6(frame="space")
    with pytest.raises(ValueError, match="frame"):
        jq.Magnus8(frame="space")
    # The fields check the state they are given ...
    term = diffrax.ODETerm(jq.kinematic_vector_field(jnp.ones(3)))
    with pytest.raises(ValueError, match="`q` must have shape"):
        diffrax.diffeqsolve(term, jq.LieEuler(), 0.0, 1.0, 0.1, jnp.ones(3))
    # ... and the solvers theirs, for any term.
    term = diffrax.ODETerm(lambda t, y, args: y)
    with pytest.raises(ValueError, match="y0"):
        diffrax.diffeqsolve(term, jq.LieEuler(), 0.0, 1.0, 0.1, jnp.ones(3))
    with pytest.raises(ValueError, match="y0"):
        diffrax.diffeqsolve(term, jq.CF4(), 0.0, 1.0, 0.1, {"q": jq.identity()})
    # The Magnus solvers take `q` or `(q, x)` only (a longer tuple is e.g. BacksolveAdjoint's).
    for magnus in (jq.Magnus4(), jq.Magnus6(), jq.Magnus8()):
        with pytest.raises(ValueError, match="tuple of length 3"):
            y0 = (jq.identity(), jnp.zeros(2), jnp.zeros(1))
            diffrax.diffeqsolve(term, magnus, 0.0, 1.0, 0.1, y0)


# ----------------------------------------------------------------------------------------------------
# Acceptance 1: corrected field + NormalizedEuler = the seed's scheme = integrate(method="euler")


@eqx.filter_jit
def _seed_scheme(field, q0, h, n, ts):
    sol = diffrax.diffeqsolve(
        diffrax.ODETerm(field),
        jq.NormalizedEuler(),
        0.0,
        n * h,
        h,
        q0,
        saveat=diffrax.SaveAt(subs=[diffrax.SubSaveAt(steps=True), diffrax.SubSaveAt(ts=ts)]),
        max_steps=n,
    )
    return sol.ys


@pytest.mark.parametrize("frame", ["world", "body"])
def test_normalized_euler_corrected_field_is_the_seed_scheme(frame):
    n, h = 24, 0.37
    q0 = random_unit(jax.random.key(2), (3,))
    omega = jnp.array([[0.3, -2.0, 1.1], [4.0, 1.0, -0.5], [0.0, 0.0, 0.0]])  # |ω|h up to 1.5 rad
    ts = jnp.linspace(0.05, n * h - 0.05, 17)
    steps, dense = _seed_scheme(jq.corrected_vector_field(omega, h, frame=frame), q0, h, n, ts)
    # Closed form, at the steps and between them (the geodesic dense output is exact here).
    times = h * jnp.arange(1, n + 1)
    rot = jq.from_rotvec(times[:, None, None] * omega[None])
    exact = jq.multiply(rot, q0) if frame == "world" else jq.multiply(q0, rot)
    assert np.max(angle(steps, exact)) < 1e-13
    rot = jq.from_rotvec(ts[:, None, None] * omega[None])
    exact_dense = jq.multiply(rot, q0) if frame == "world" else jq.multiply(q0, rot)
    assert np.max(angle(dense, exact_dense)) < 1e-13
    reference = jq.integrate(q0, omega, h, n, frame=frame, method="euler")
    np.testing.assert_allclose(steps, reference[1:], rtol=0, atol=1e-13)

    # Piecewise-constant sampled ω: exact too, and equal to integrate(method="euler").
    omegas = 2.0 * jax.random.normal(jax.random.key(3), (n, 3, 3))
    steps, _ = _seed_scheme(
        jq.corrected_vector_field(jq.sampled(omegas, h), h, frame=frame), q0, h, n, ts
    )

    def product(q, omega):
        rot = jq.from_rotvec(h * omega)
        q = jq.multiply(rot, q) if frame == "world" else jq.multiply(q, rot)
        return q, q

    _, exact = jax.lax.scan(product, q0, omegas)
    assert np.max(angle(steps, exact)) < 1e-13
    reference = jq.integrate(q0, jq.sampled(omegas, h), h, n, frame=frame, method="euler")
    np.testing.assert_allclose(steps, reference[1:], rtol=0, atol=1e-13)


def test_corrected_field_with_a_general_solver_solves_another_ode():
    """Tsit5 on the corrected field integrates q̇ = κ·½ω̃q with κ = 2tan(θ/2)/θ: it rotates too fast by
    (κ − 1)|ω|T (closed form), where the plain field is right to ~1e-10."""
    omega, h, n = jnp.array([0.0, 0.6, 0.8]), 0.1, 80  # |ω| = 1, θ = 0.1, T = 8
    q0 = jq.identity()

    def final(field):
        return diffrax.diffeqsolve(diffrax.ODETerm(field), diffrax.Tsit5(), 0.0, n * h, h, q0).ys[
            -1
        ]

    exact = jq.from_rotvec(n * h * omega)
    wrong = float(angle(final(jq.corrected_vector_field(omega, h)), exact))
    right = float(angle(final(jq.kinematic_vector_field(omega)), exact))
    theta = h * 1.0
    predicted = (2.0 * math.tan(theta / 2) / theta - 1.0) * 1.0 * n * h
    assert abs(wrong - predicted) < 1e-2 * predicted  # 6.7e-3 rad
    assert right < 1e-9
    assert 6e-3 < wrong < 7e-3


# ----------------------------------------------------------------------------------------------------
# Acceptance 2 and 4: orders on a closed-form problem, |q| = 1, dense output on the sphere


ORDER_STEPS = np.array([12, 24, 48])
DENSE_TS = jnp.linspace(0.0, T_END, 40)[1:-1] + 0.013  # between steps for every step count


def _orders(solver, frame):
    """Errors at T for each step count, forwards (0 → T) and backwards (T → 0), plus dense output at
    DENSE_TS (forwards); one compilation (vmap over step size and direction)."""
    term = diffrax.ODETerm(jq.kinematic_vector_field(Coning(frame), frame=frame))

    @jax.jit
    @jax.vmap
    def run(n, backwards):
        t0 = jnp.where(backwards, T_END, 0.0)
        t1 = T_END - t0
        ts = jnp.where(backwards, DENSE_TS[::-1], DENSE_TS)  # in the direction of integration
        saveat = diffrax.SaveAt(subs=[diffrax.SubSaveAt(steps=True), diffrax.SubSaveAt(ts=ts)])
        sol = diffrax.diffeqsolve(
            term,
            solver,
            t0,
            t1,
            (t1 - t0) / n,
            coning_exact(t0),
            saveat=saveat,
            max_steps=int(ORDER_STEPS[-1]),
        )
        return sol.ys

    num = len(ORDER_STEPS)
    ns = jnp.asarray(np.concatenate([ORDER_STEPS, ORDER_STEPS]), dtype=jnp.float64)
    backwards = jnp.arange(2 * num) >= num
    steps, dense = run(ns, backwards)
    finals = jnp.stack([steps[i, n - 1] for i, n in enumerate(np.concatenate([ORDER_STEPS] * 2))])
    all_steps = np.concatenate(
        [np.asarray(steps[i, :n]) for i, n in enumerate(np.concatenate([ORDER_STEPS] * 2))]
    )
    errors = angle(finals[:num], coning_exact(T_END))
    errors_back = angle(finals[num:], coning_exact(0.0))
    dense_errors = np.max(angle(dense[:num], coning_exact(DENSE_TS)), axis=-1)
    dense_errors_back = np.max(angle(dense[num:], coning_exact(DENSE_TS[::-1])), axis=-1)
    assert np.all(dense_errors_back < 10.0 * dense_errors + 1e-12)
    norm_dev = np.max(np.abs(np.linalg.norm(all_steps, axis=-1) - 1.0))
    dense_norm_dev = np.max(np.abs(np.linalg.norm(np.asarray(dense), axis=-1) - 1.0))
    hs = T_END / ORDER_STEPS
    return (
        slope(hs, errors),
        slope(hs, errors_back),
        errors,
        slope(hs, dense_errors),
        norm_dev,
        dense_norm_dev,
    )


@pytest.mark.parametrize(
    "solver, frame, low, high",
    [
        (jq.LieEuler(), "body", 0.95, 1.1),
        (jq.ExpMidpoint(), "body", 1.95, 2.1),
        (jq.Magnus4(frame="body"), "body", 3.9, 4.2),
        (jq.Magnus4(frame="world"), "world", 3.9, 4.2),
        (jq.Magnus6(frame="body"), "body", 5.85, 6.2),
        (jq.Magnus6(frame="world"), "world", 5.85, 6.2),
        (jq.Magnus8(frame="body"), "body", 7.8, 8.3),
        (jq.Magnus8(frame="world"), "world", 7.8, 8.3),
        (jq.CF4(), "body", 3.9, 4.2),
        (jq.RKMK45(), "body", 4.8, 5.6),
    ],
)
def test_orders_norm_and_dense_output(solver, frame, low, high):
    order, order_back, errors, dense_order, norm_dev, dense_norm_dev = _orders(solver, frame)
    assert low <= order <= high, (order, errors)
    assert low <= order_back <= high, order_back
    assert norm_dev <= 1e-14
    assert dense_norm_dev <= 1e-12
    if isinstance(solver, jq.RKMK45):
        # Tsitouras' continuous extension in the Lie algebra: between steps as accurate as at them
        # (measured 5.4; the cubic Hermite interpolant it replaced gave 4.0).
        assert dense_order >= 4.8, dense_order
    elif isinstance(solver, (jq.Magnus6, jq.Magnus8)) and low > 5:
        assert dense_order >= 3.0, dense_order


# ----------------------------------------------------------------------------------------------------
# Acceptance 3: adaptive RKMK45 against stock Tsit5


def _adaptive(term, solver, y0, t1, tol):
    controller = diffrax.PIDController(rtol=tol, atol=tol)
    return diffrax.diffeqsolve(
        term, solver, 0.0, t1, None, y0, stepsize_controller=controller, max_steps=4096
    )


def test_rkmk45_adaptive_coning():
    term = diffrax.ODETerm(jq.kinematic_vector_field(Coning("body"), frame="body"))
    t1 = 7.3
    ours = _adaptive(term, jq.RKMK45(), coning_exact(0.0), t1, 1e-8)
    stock = _adaptive(term, diffrax.Tsit5(), coning_exact(0.0), t1, 1e-8)
    assert angle(ours.ys[-1], coning_exact(t1)) <= 1e-7
    assert int(ours.stats["num_accepted_steps"]) <= int(stock.stats["num_accepted_steps"])
    assert abs(float(jnp.linalg.norm(ours.ys[-1])) - 1.0) < 1e-14


INERTIA = jnp.array([1.0, 2.0, 3.5])


def _rigid_body(t, y, args):
    """Torque-free rigid body: q̇ = ½ q ω̃_b, I ω̇_b = (I ω_b) × ω_b (Euler's equations)."""
    q, omega = y
    return jq.rate(q, omega, frame="body"), jnp.cross(INERTIA * omega, omega) / INERTIA


def test_rkmk45_adaptive_rigid_body():
    term = diffrax.ODETerm(_rigid_body)
    y0 = (jq.from_rotvec(jnp.array([0.3, -0.2, 0.5])), jnp.array([0.5, 1.0, 2.0]))
    t1 = 9.7
    reference = _adaptive(term, diffrax.Tsit5(), y0, t1, jnp.asarray(1e-13)).ys
    ours = _adaptive(term, jq.RKMK45(), y0, t1, 1e-8)
    stock = _adaptive(term, diffrax.Tsit5(), y0, t1, jnp.asarray(1e-8))
    assert angle(ours.ys[0][-1], reference[0][-1]) <= 1e-7
    assert np.max(np.abs(ours.ys[1][-1] - reference[1][-1])) <= 1e-7
    assert int(ours.stats["num_accepted_steps"]) <= int(stock.stats["num_accepted_steps"])
    # Energy and |I ω| are conserved by the exact flow; the ω part is Tsit5 itself.
    energy = lambda w: float(jnp.sum(INERTIA * w * w))  # noqa: E731
    assert abs(energy(ours.ys[1][-1]) / energy(y0[1]) - 1.0) < 5e-8


def test_rkmk45_saveat_ts_is_as_accurate_as_its_steps():
    """`SaveAt(ts=...)` between adaptive steps: the dense output is the Lie-algebra form of Tsit5's
    continuous extension, so reading out at ts costs no accuracy (the cubic Hermite interpolant it
    replaced was 130× worse than the steps at tol 1e-10). Both leaves of a tuple state."""
    term = diffrax.ODETerm(jq.kinematic_vector_field(Coning("world"), frame="world"))
    t1, tol = 5.3, 1e-10
    ts = jnp.linspace(0.0, t1, 203)
    errors = {}
    for name, solver in (("ours", jq.RKMK45()), ("stock", diffrax.Tsit5())):
        sol = diffrax.diffeqsolve(
            term,
            solver,
            0.0,
            t1,
            None,
            coning_exact(0.0),
            stepsize_controller=diffrax.PIDController(rtol=tol, atol=tol),
            saveat=diffrax.SaveAt(ts=ts),
            max_steps=4096,
        )
        errors[name] = float(np.max(angle(sol.ys, coning_exact(ts))))
    assert errors["ours"] <= 2.0 * errors["stock"], errors  # measured 1.4e-10 vs 1.5e-10
    # The rigid body's ω leaf through the same extension, against Tsit5 at 1e-13.
    rigid = diffrax.ODETerm(_rigid_body)
    y0 = (jq.from_rotvec(jnp.array([0.3, -0.2, 0.5])), jnp.array([0.5, 1.0, 2.0]))
    ts = jnp.linspace(0.0, 9.7, 97)

    def solve(solver, tol):
        return diffrax.diffeqsolve(
            rigid,
            solver,
            0.0,
            9.7,
            None,
            y0,
            stepsize_controller=diffrax.PIDController(rtol=tol, atol=tol),
            saveat=diffrax.SaveAt(ts=ts),
            max_steps=4096,
        ).ys

    reference = solve(diffrax.Tsit5(), jnp.asarray(1e-13))
    ours, stock = solve(jq.RKMK45(), 1e-8), solve(diffrax.Tsit5(), jnp.asarray(1e-8))
    # Measured: attitude 7.3e-8 (Tsit5 7.5e-8), ω 1.05e-7 (Tsit5 9.9e-8) rad, the global error.
    assert np.max(angle(ours[0], reference[0])) <= 2.0 * np.max(angle(stock[0], reference[0]))
    assert np.max(np.abs(ours[1] - reference[1])) <= 2.0 * np.max(np.abs(stock[1] - reference[1]))


# ----------------------------------------------------------------------------------------------------
# Acceptance 5: jit, vmap over 10⁴ bodies, gradients


def test_vmap_ten_thousand_bodies():
    n = 10_000
    q0 = random_unit(jax.random.key(4), (n,))
    omega = 3.0 * jax.random.normal(jax.random.key(5), (n, 3))

    @jax.jit
    @jax.vmap
    def final(q0, omega):
        term = diffrax.ODETerm(jq.kinematic_vector_field(omega, frame="body"))
        return diffrax.diffeqsolve(term, jq.RKMK45(), 0.0, 1.5, 0.25, q0).ys[-1]

    exact = jq.multiply(q0, jq.from_rotvec(1.5 * omega))
    assert np.max(angle(final(q0, omega), exact)) < 1e-12


class Wobble(eqx.Module):
    """ω(t) = a + b sin(3t): parameters as a PyTree field (so every adjoint sees them)."""

    params: jax.Array

    def __call__(self, t, q):
        return self.params[:3] + self.params[3:] * jnp.sin(3.0 * t)


def _final_loss(params, solver, adjoint):
    term = diffrax.ODETerm(jq.kinematic_vector_field(Wobble(params)))
    q0 = jq.from_rotvec(jnp.array([0.2, 0.1, -0.4]))
    sol = diffrax.diffeqsolve(term, solver, 0.0, 1.7, 0.1, q0, adjoint=adjoint)
    target = jnp.array([0.5, -0.5, 0.5, 0.5])
    return jnp.dot(sol.ys[-1], target)


PARAMS = jnp.array([0.4, -1.1, 0.8, 0.9, 0.3, -0.6])
DIRECTION = jnp.array([0.3, -0.7, 0.2, 0.5, 0.1, -0.4])
_COMPILED = {}


def _compiled(solver):
    """(loss, reverse-mode gradient, forward-mode directional derivative), jitted once per solver."""
    key = type(solver).__name__
    if key not in _COMPILED:
        checkpoint = diffrax.RecursiveCheckpointAdjoint()
        loss = jax.jit(lambda p: _final_loss(p, solver, checkpoint))
        grad = jax.jit(jax.grad(lambda p: _final_loss(p, solver, checkpoint)))
        forward = jax.jit(
            lambda p, v: jax.jvp(
                lambda p_: _final_loss(p_, solver, diffrax.ForwardMode()), (p,), (v,)
            )[1]
        )
        _COMPILED[key] = (loss, grad, forward)
    return _COMPILED[key]


def _directional_fd(loss, p, v, eps=1e-5):
    # Fourth-order central difference: truncation ~eps⁴, round-off ~1e-16/eps.
    f = lambda s: float(loss(p + s * v))  # noqa: E731
    return (8.0 * (f(eps) - f(-eps)) - (f(2 * eps) - f(-2 * eps))) / (12.0 * eps)


@pytest.mark.parametrize(
    "solver", [jq.RKMK45(), jq.LieEuler(), jq.Magnus6(frame="world"), jq.Magnus8(frame="world")]
)
def test_gradients_match_finite_differences(solver):
    loss, grad, forward = _compiled(solver)
    for p in (PARAMS, jnp.zeros(6)):  # generic, and at rest (series branches; not NaN)
        fd = _directional_fd(loss, p, DIRECTION)
        reverse = float(jnp.dot(grad(p), DIRECTION))
        tangent = float(forward(p, DIRECTION))
        assert abs(reverse - fd) <= 1e-7 * abs(fd), (reverse, fd)
        assert abs(tangent - fd) <= 1e-7 * abs(fd), (tangent, fd)


def test_backsolve_adjoint():
    """RK-type solvers run under BacksolveAdjoint (the continuous adjoint: it agrees with the exact
    discrete gradient to the solver's accuracy); Magnus4 refuses with a message naming the working
    alternative, which then works."""
    _, grad, _ = _compiled(jq.RKMK45())
    exact = grad(PARAMS)
    backsolve = jax.grad(lambda p: _final_loss(p, jq.RKMK45(), diffrax.BacksolveAdjoint()))(PARAMS)
    assert np.max(np.abs(backsolve - exact)) <= 1e-6 * np.max(np.abs(exact))
    for magnus in (jq.Magnus4(), jq.Magnus6(), jq.Magnus8()):
        with pytest.raises(ValueError, match=r"BacksolveAdjoint\(solver=diffrax\.Tsit5\(\)\)"):
            jax.grad(lambda p, m=magnus: _final_loss(p, m, diffrax.BacksolveAdjoint()))(PARAMS)
    alternative = jax.grad(
        lambda p: _final_loss(p, jq.Magnus4(), diffrax.BacksolveAdjoint(solver=diffrax.Tsit5()))
    )(PARAMS)
    assert np.max(np.abs(alternative - exact)) <= 1e-4 * np.max(np.abs(exact))


def test_backsolve_adjoint_with_a_non_unit_q0_needs_normalize_inside_the_gradient():
    """BacksolveAdjoint differentiates the ODE, not the first step's normalisation of a non-unit q0:
    it returns ∇(L∘Φ) at q0/|q0| (Φ = exp(ωT), the flow). With `jaxquat.normalize(q0)` inside the
    differentiated function, as the module docstring says, the gradient is exact: compared with the
    closed form L(Φ ⊗ q0/|q0|), constant ω (RKMK45 is exact for it)."""
    omega = jnp.array([0.3, -0.7, 1.1])
    target = jq.from_rotvec(jnp.array([0.5, 0.2, -0.1]))
    q0 = 1.3 * jq.normalize(jnp.array([0.9, 0.3, -0.5, 0.4]))

    def loss_of(q):
        return jnp.sum((q - target) ** 2)

    def flow(q):
        return loss_of(jq.multiply(jq.from_rotvec(2.0 * omega), q))

    def solved(q, normalise):
        sol = diffrax.diffeqsolve(
            diffrax.ODETerm(jq.kinematic_vector_field(omega)),
            jq.RKMK45(),
            0.0,
            2.0,
            0.05,
            jq.normalize(q) if normalise else q,
            adjoint=diffrax.BacksolveAdjoint(),
        )
        return loss_of(sol.ys[-1])

    exact = jax.grad(lambda q: flow(jq.normalize(q)))(q0)
    right = jax.grad(solved)(q0, True)
    np.testing.assert_allclose(right, exact, rtol=0, atol=1e-10 * float(jnp.max(jnp.abs(exact))))
    unnormalised = jax.grad(solved)(q0, False)
    np.testing.assert_allclose(unnormalised, jax.grad(flow)(q0 / 1.3), rtol=0, atol=1e-10)
    assert float(jnp.max(jnp.abs(unnormalised - exact))) > 0.1  # what the docstring warns of
    # At a unit q0 the tangent part is right, but a radial part remains (gradient steps leave the
    # sphere) unless q0 is normalised inside, as the README says (helper-54).
    unit = q0 / 1.3
    exact = jax.grad(lambda q: flow(jq.normalize(q)))(unit)
    assert abs(float(exact @ unit)) < 1e-12
    right = jax.grad(solved)(unit, True)
    np.testing.assert_allclose(right, exact, rtol=0, atol=1e-10 * float(jnp.max(jnp.abs(exact))))
    unnormalised = jax.grad(solved)(unit, False)
    assert abs(float(unnormalised @ unit)) > 0.1
    tangent = unnormalised - (unnormalised @ unit) * unit
    np.testing.assert_allclose(tangent, exact, rtol=0, atol=1e-10 * float(jnp.max(jnp.abs(exact))))


@pytest.mark.parametrize("dtype, bound", [(jnp.float64, 5e-14), (jnp.float32, 2e-5)])
def test_rkmk45_constant_omega_within_the_documented_step_size(dtype, bound):
    """One RKMK45 step of constant ω is the exponential up to the round-off its dexp⁻¹ series
    amplifies across ω (about θ²/12 + θ⁴/720 per stage, θ = |ω|h): within the docstring's bounds
    up to θ = 5 rad, against exp(ωh) ⊗ q0 formed in float64 from the same inputs. (A review found
    1.1e-4 rad in float64 at θ = 40 and, on one axis, 0.25 rad in float32 at θ = 20; the docstring
    gives the worst of 20 draws, 1.2 rad.)"""
    rng = np.random.default_rng(7)
    worst = 0.0
    for trial, theta in enumerate(np.repeat([0.5, 1.0, 3.14, 5.0], 5)):
        axis = rng.normal(size=3)
        omega = jnp.asarray(theta * axis / np.linalg.norm(axis), dtype)
        q0 = jq.random(jax.random.key(trial)).astype(dtype)
        field = diffrax.ODETerm(jq.kinematic_vector_field(omega))
        t0, t1 = jnp.asarray(0.0, dtype), jnp.asarray(1.0, dtype)  # (Python times: float64 state)
        q1 = diffrax.diffeqsolve(field, jq.RKMK45(), t0, t1, t1, q0).ys[-1]
        assert q1.dtype == dtype
        exact = jq.step(q0.astype(jnp.float64), omega.astype(jnp.float64), 1.0)
        worst = max(worst, float(jq.angle_between(q1.astype(jnp.float64), exact)))
    assert worst <= bound, worst


def test_rkmk45_stages_in_a_loop_match_the_unrolled_stages():
    """`RKMK45` traces its stages once inside a loop; `unroll_stages=True` traces each. Both give the
    same steps, dense output, other leaves and gradient to round-off (x depends on q, so the other
    leaves' stage increments are exercised)."""
    calls = []

    def field(t, y, args):
        calls.append(t)
        q, x = y
        omega = jnp.array([0.6 * jnp.cos(t), -0.4, 0.9 * jnp.sin(2.0 * t)]) * args
        return jq.rate(q, omega, frame="body"), jq.rotate(x, q)

    y0 = (jq.from_rotvec(jnp.array([0.2, 0.1, -0.4])), jnp.array([1.0, -0.5, 0.25]))
    ts = jnp.linspace(0.0, 3.0, 11)

    def solve(scale, solver, adjoint=None):
        sol = diffrax.diffeqsolve(
            diffrax.ODETerm(field),
            solver,
            0.0,
            3.0,
            0.1,
            y0,
            args=scale,
            saveat=diffrax.SaveAt(ts=ts),
            stepsize_controller=diffrax.PIDController(rtol=1e-9, atol=1e-9),
            adjoint=adjoint or diffrax.RecursiveCheckpointAdjoint(),
        )
        return sol.ys, sol.stats["num_steps"]

    looped, unrolled = jq.RKMK45(), jq.RKMK45(unroll_stages=True)
    (q_l, x_l), steps_l = jax.jit(lambda s: solve(s, looped))(1.3)
    (q_u, x_u), steps_u = jax.jit(lambda s: solve(s, unrolled))(1.3)
    assert int(steps_l) == int(steps_u) > 10
    np.testing.assert_allclose(q_l, q_u, rtol=0, atol=1e-14)
    np.testing.assert_allclose(x_l, x_u, rtol=0, atol=1e-13)
    # Forward mode (reverse mode through the loop is checked against finite differences above).
    loss = lambda s, solver: jnp.sum(solve(s, solver, diffrax.ForwardMode())[0][1][-1])  # noqa: E731
    g_l = jax.jvp(lambda s: loss(s, looped), (1.3,), (1.0,))[1]
    g_u = jax.jvp(lambda s: loss(s, unrolled), (1.3,), (1.0,))[1]
    assert abs(g_l - g_u) <= 1e-12 * abs(g_u), (g_l, g_u)
    # One traced stage in the loop against six unrolled (the first comes from the solver state).
    term = diffrax.ODETerm(field)
    for solver, traced in ((looped, 1), (unrolled, 6)):
        state = solver.init(term, 0.0, 0.1, y0, 1.0)
        calls.clear()
        jax.make_jaxpr(lambda y, s, step=solver.step: step(term, 0.0, 0.1, y, 1.0, s, False))(
            y0, state
        )
        assert len(calls) == traced, (solver, len(calls))


# ----------------------------------------------------------------------------------------------------
# Acceptance 6: float32 stays float32


@pytest.mark.parametrize(
    "solver",
    [
        jq.NormalizedEuler(),
        jq.LieEuler(),
        jq.ExpMidpoint(),
        jq.Magnus4(frame="body"),
        jq.Magnus6(frame="body"),
        jq.Magnus8(frame="body"),
        jq.CF4(),
        jq.RKMK45(),
    ],
)
def test_float32_stays_float32(solver):
    f32 = jnp.float32
    omega = jnp.array([0.3, -1.0, 0.7], f32)

    magnus = isinstance(solver, (jq.Magnus4, jq.Magnus6, jq.Magnus8))

    def field(t, y, args):
        q, x = y
        # Magnus needs rates that are functions of time only (it refuses ẋ = −x).
        return jq.rate(q, omega, frame="body"), (-t * jnp.ones_like(x) if magnus else -x)

    y0 = (jq.identity(dtype=f32), jnp.ones(2, f32))
    ts = jnp.linspace(0.0, 2.0, 7, dtype=f32)
    controller = (
        diffrax.PIDController(rtol=1e-5, atol=1e-5)
        if isinstance(solver, jq.RKMK45)
        else diffrax.ConstantStepSize()
    )
    sol = diffrax.diffeqsolve(
        diffrax.ODETerm(field),
        solver,
        f32(0.0),
        f32(2.0),
        f32(0.1),
        y0,
        saveat=diffrax.SaveAt(ts=ts),
        stepsize_controller=controller,
    )
    q, x = sol.ys
    assert q.dtype == f32 and x.dtype == f32
    assert np.max(np.abs(np.linalg.norm(np.asarray(q, np.float64), axis=-1) - 1.0)) < 1e-6
    exact = jq.from_rotvec(ts[:, None] * omega[None])
    assert np.max(angle(q.astype(jnp.float64), exact.astype(jnp.float64))) < 2e-2


@pytest.mark.parametrize("frame", ["world", "body"])
@pytest.mark.parametrize(
    "solver, method, power", [(jq.Magnus6, "magnus6", 5), (jq.Magnus8, "magnus8", 7)]
)
def test_magnus_solver_equals_integrate(frame, solver, method, power):
    """The diffrax solvers and `integrate(method=...)` take the same step (to round-off), with a tuple
    state whose x-part is Gauss quadrature: three points for Magnus6 (exact for a quintic in t), four
    for Magnus8 (exact for a septic)."""
    omega = Coning(frame)
    steps, t1 = 37, 2.3
    h = t1 / steps

    def field(t, y, args):
        q, x = y
        return jq.rate(q, omega(t, q), frame=frame), jnp.stack([t**power, jnp.cos(t)])

    y0 = (coning_exact(0.0), jnp.zeros(2))
    sol = diffrax.diffeqsolve(
        diffrax.ODETerm(field),
        solver(frame=frame),
        0.0,
        t1,
        h,
        y0,
        saveat=diffrax.SaveAt(t1=True),
        stepsize_controller=diffrax.ConstantStepSize(),
    )
    direct = jq.integrate(
        coning_exact(0.0),
        omega,
        h,
        steps,
        frame=frame,
        method=method,
        save="final",
    )
    np.testing.assert_allclose(sol.ys[0][-1], direct, atol=1e-13)
    np.testing.assert_allclose(sol.ys[1][-1, 0], t1 ** (power + 1) / (power + 1), rtol=1e-12)
    np.testing.assert_allclose(sol.ys[1][-1, 1], np.sin(t1), atol=1e-11)


@pytest.mark.parametrize("solver", [jq.Magnus4, jq.Magnus6, jq.Magnus8])
def test_magnus_solvers_refuse_a_field_of_the_other_frame(solver):
    """A body-frame jaxquat field under the default frame="world" ran at order 2 (Magnus4 on coning:
    1.3e-2 rad at 20 steps against 3.4e-6 with frame="body"); the field knows its frame, so the solver
    refuses the mismatch at trace time, both ways."""
    q0 = coning_exact(0.0)
    for field_frame, solver_frame in [("body", "world"), ("world", "body")]:
        term = diffrax.ODETerm(jq.kinematic_vector_field(Coning(field_frame), frame=field_frame))
        with pytest.raises(ValueError, match=rf"pass `frame='{field_frame}'`"):
            diffrax.diffeqsolve(term, solver(frame=solver_frame), 0.0, 1.0, 0.1, q0)


@pytest.mark.parametrize("solver", [jq.Magnus4, jq.Magnus6])
def test_magnus_solvers_refuse_a_state_dependent_tuple_field(solver):
    """jaxquat's rigid body (q, ω_b): ω_b evolves, and frozen at the step start Magnus ran at order 1
    (0.114 → 0.061 → 0.032 rad for 30 → 120 steps) without a word. A tuple state whose other leaves
    follow a function of time still runs."""
    q0 = jq.from_rotvec(jnp.array([0.3, -0.2, 0.5]))
    term = diffrax.ODETerm(jq.rigid_body_vector_field(jnp.array([1.0, 2.0, 3.0])))
    with pytest.raises(ValueError, match=rf"other leaves `x`.*{solver.__name__}.*CF4 or RKMK45"):
        diffrax.diffeqsolve(term, solver(frame="body"), 0.0, 3.0, 0.1, (q0, jnp.ones(3)))

    def timed(t, y, args):  # q̇ from ω(t) in the body frame, and x = ∫ ω dt alongside
        omega = jnp.array([jnp.cos(t), jnp.sin(t), 0.5])
        return jq.rate(y[0], omega, frame="body"), omega

    sol = diffrax.diffeqsolve(
        diffrax.ODETerm(timed), solver(frame="body"), 0.0, 3.0, 0.1, (q0, jnp.zeros(3))
    )
    np.testing.assert_allclose(
        sol.ys[1][-1], [np.sin(3.0), 1.0 - np.cos(3.0), 1.5], rtol=0, atol=1e-7
    )  # Gauss quadrature: 4.6e-8 for Magnus4's two points at h = 0.1


@pytest.mark.parametrize("solver", [jq.Magnus4, jq.Magnus8])
def test_magnus_solvers_refuse_other_leaves_whose_derivative_reads_q(solver):
    """(q, p) with p' = rotate(v, q) (a position carried in the body): Magnus evaluates p' with q frozen
    at the step start, and a review measured order 1 (4.25e-2 → 2.11e-2 for h = 0.1 → 0.05, where CF4
    gives 2.9e-8 → 1.8e-9) without a word. Only a dependence on x itself was refused."""

    def carried(t, y, args):
        q, _ = y
        return jq.rate(q, jnp.array([0.0, 0.0, 1.0])), jq.rotate(jnp.array([1.0, 0.0, 0.0]), q)

    y0 = (jq.identity(), jnp.zeros(3))
    with pytest.raises(ValueError, match=rf"`x`.*depends on q.*{solver.__name__}.*CF4 or RKMK45"):
        diffrax.diffeqsolve(diffrax.ODETerm(carried), solver(), 0.0, 1.0, 0.1, y0)
    # CF4 takes it, at its order: p(1) = (sin 1, 1 − cos 1, 0).
    sol = diffrax.diffeqsolve(diffrax.ODETerm(carried), jq.CF4(), 0.0, 1.0, 0.1, y0)
    np.testing.assert_allclose(sol.ys[1][-1], [np.sin(1.0), 1.0 - np.cos(1.0), 0.0], atol=1e-7)


@pytest.mark.parametrize("speed", [7.0, 13.0, -20.0])
def test_cf4_dense_output_of_steps_turning_more_than_a_full_turn(speed):
    """A CF4 step of 7 rad (|ω|h > 2π) ended exactly but was interpolated through the principal
    logarithm's 7 − 4π: 1.96 and 2.40 rad off at t = 0.25 and 0.37 (a review, against exp(ωt)). The
    interpolant now ends on the branch the step's increments point to. Exact for constant ω, like
    the steps; the derivative through the dense output at ω = 0 is the closed form ½ t [0; I₃]."""
    omega = jnp.array([0.0, 0.3 * np.sign(speed), speed])
    ts = jnp.array([0.25, 0.37, 0.8, 1.0])
    term = diffrax.ODETerm(jq.kinematic_vector_field(omega))
    sol = diffrax.diffeqsolve(
        term, jq.CF4(), 0.0, 1.0, 1.0, jq.identity(), saveat=diffrax.SaveAt(ts=ts)
    )
    exact = jq.from_rotvec(ts[:, None] * omega[None, :])
    assert float(jnp.max(jq.angle_between(sol.ys, exact))) < 1e-13

    def dense(w):
        field = diffrax.ODETerm(jq.kinematic_vector_field(w))
        saveat = diffrax.SaveAt(ts=jnp.array([0.3]))
        return diffrax.diffeqsolve(field, jq.CF4(), 0.0, 1.0, 0.5, jq.identity(), saveat=saveat).ys[
            0
        ]

    expected = 0.15 * np.concatenate([np.zeros((1, 3)), np.eye(3)])
    np.testing.assert_allclose(jax.jacrev(dense)(jnp.zeros(3)), expected, atol=1e-15)


@pytest.mark.parametrize("solver", [jq.Magnus4, jq.Magnus6, jq.Magnus8])
def test_magnus_solvers_refuse_an_omega_that_depends_on_q(solver):
    """Magnus methods evaluate ω at the Gauss points with q frozen: an ω(t, q) silently dropped them to
    order 2 (Magnus8: 8.7e-3 → 5.4e-4 rad for 10 → 40 steps). Like `integrate`, the solver refuses it at
    trace time, forwards and backwards, for the plain and the corrected field; ω(t) (a function or
    sampled data) still runs."""
    q0 = jnp.array([1.0, 0.0, 0.0, 0.0])
    depends = lambda t, q: jq.rotate(jnp.array([jnp.cos(t), jnp.sin(t), 1.0]), q)  # noqa: E731
    for field in [jq.kinematic_vector_field(depends), jq.corrected_vector_field(depends, 0.1)]:
        for t0, t1, dt0 in [(0.0, 1.0, 0.1), (1.0, 0.0, -0.1)]:
            with pytest.raises(ValueError, match=rf"depends on q, but {solver.__name__}"):
                diffrax.diffeqsolve(diffrax.ODETerm(field), solver(), t0, t1, dt0, q0)
    for omega in [
        lambda t, q: jnp.array([jnp.cos(t), jnp.sin(t), 1.0]),
        jq.sampled(jnp.ones((20, 3)), 0.1),
    ]:
        solution = diffrax.diffeqsolve(
            diffrax.ODETerm(jq.kinematic_vector_field(omega)), solver(), 1.0, 0.0, -0.1, q0
        )
        assert np.all(np.isfinite(solution.ys))


def _plain_term(frame, reads_q=0.0):
    """A plain `ODETerm` (no jaxquat field for the solver to inspect) of q̇ = ½ω̃q (world) or ½qω̃
    (body), with ω(t) + `reads_q`·vec(q)."""

    def field(t, q, args):
        w = jq.from_vector(jnp.array([jnp.cos(t), 0.5, jnp.sin(2.0 * t)]) + reads_q * q[1:])
        return 0.5 * (jq.multiply(w, q) if frame == "world" else jq.multiply(q, w))

    return diffrax.ODETerm(field)


def test_magnus_solvers_check_a_plain_term_at_run_time():
    """A plain `ODETerm` whose ω reads q, or whose ω is in the other frame, silently dropped the
    Magnus methods to order 1 (Magnus6, ω + ½vec(q): 1.6e-2 → 8.1e-3 rad for 16 → 32 steps) or 2
    (body-frame rates to the world-frame solver: 3.0e-3 → 7.4e-4; helper-71). The solver cannot see
    inside such a term, so it probes it at the first step and raises at run time (each solver; and,
    for Magnus4, in both frames, backwards, under `jit` when only part of the output is used and
    under `vmap` when one body of two is wrong); a term that is right gives the jaxquat field's
    steps."""
    q0 = jq.normalize(jnp.array([0.9, 0.1, -0.3, 0.2]))
    message = (
        r"\(frame=.*\): the term's rate, read as an angular velocity in that frame, depends on q"
    )
    for solver in [jq.Magnus6, jq.Magnus8]:
        with pytest.raises(eqx.EquinoxRuntimeError, match=solver.__name__ + message):
            diffrax.diffeqsolve(_plain_term("world", reads_q=0.5), solver(), 0.0, 2.0, 0.25, q0)
    message = "Magnus4" + message
    for frame, term, t0, t1, dt0 in [
        ("world", _plain_term("world", reads_q=0.5), 0.0, 2.0, 0.25),
        ("world", _plain_term("body"), 2.0, 0.0, -0.25),
        ("body", _plain_term("world"), 0.0, 2.0, 0.25),
    ]:
        with pytest.raises(eqx.EquinoxRuntimeError, match=message):
            diffrax.diffeqsolve(term, jq.Magnus4(frame=frame), t0, t1, dt0, q0)

    @jax.jit
    @jax.vmap
    def first_component(c):
        term = _plain_term("world", reads_q=c)
        return diffrax.diffeqsolve(term, jq.Magnus4(), 0.0, 2.0, 0.25, q0).ys[-1, 0]

    with pytest.raises(Exception, match=message):
        first_component(jnp.array([0.0, 1e-3]))
    assert np.all(np.isfinite(first_component(jnp.zeros(2))))

    omega = lambda t, q: jnp.array([jnp.cos(t), 0.5, jnp.sin(2.0 * t)])  # noqa: E731
    for frame in ["world", "body"]:
        plain = diffrax.diffeqsolve(
            _plain_term(frame), jq.Magnus4(frame=frame), 2.0, 0.0, -0.25, q0
        )
        field = diffrax.ODETerm(jq.kinematic_vector_field(omega, frame=frame))
        ours = diffrax.diffeqsolve(field, jq.Magnus4(frame=frame), 2.0, 0.0, -0.25, q0)
        np.testing.assert_allclose(plain.ys, ours.ys, atol=1e-15)


@pytest.mark.parametrize(
    "solver",
    [
        jq.LieEuler,
        jq.ExpMidpoint,
        jq.CF4,
        jq.RKMK45,
        jq.NormalizedEuler,
        jq.Magnus4,
        jq.Magnus6,
        jq.Magnus8,
    ],
)
@pytest.mark.parametrize("scale", [1.0 + 1e-6, 2.0])
def test_a_non_unit_initial_state_is_normalised_by_the_first_step(solver, scale):
    """jaxquat's solvers keep q on the unit sphere. A review found RKMK45 losing its exactness for
    constant ω when |q0| ≠ 1: its first-same-as-last stage was evaluated at |q| = |q0| and recovered
    in the next step against the unit q1, scaling that step's rotation by |q0| (1.1e-8 rad at
    |q0| = 1 + 1e-6, 1.1e-2 at 2; 2.8e-8 with a PID controller at rtol 1e-10). And every solver's
    dense output kept |q0| within the first step, then jumped to 1 at its end. Now: every step and
    every dense value is exp(ωt) ⊗ q0/|q0| to round-off, unit, with no jump at the steps."""
    omega = jnp.array([0.4, -1.1, 0.7])
    unit = random_unit(jax.random.key(7), ())
    q0 = scale * unit
    field = jq.corrected_vector_field(omega, 0.1) if solver is jq.NormalizedEuler else None
    term = diffrax.ODETerm(field or jq.kinematic_vector_field(omega))
    steps = jnp.linspace(0.0, 0.5, 6)
    ts = jnp.sort(jnp.concatenate([steps, steps[:-1] + 0.037, steps[1:] - 1e-9]))
    sol = diffrax.diffeqsolve(
        term, solver(), 0.0, 0.5, 0.1, q0, saveat=diffrax.SaveAt(ts=ts), max_steps=64
    )
    exact = jq.multiply(jq.from_rotvec(ts[:, None] * omega[None, :]), unit[None, :])
    assert float(jnp.max(jq.angle_between(sol.ys, exact))) < 1e-14
    np.testing.assert_allclose(jnp.linalg.norm(sol.ys, axis=-1), 1.0, atol=1e-15)
    if solver is jq.RKMK45:
        controller = diffrax.PIDController(rtol=1e-10, atol=1e-10)
        sol = diffrax.diffeqsolve(
            term, solver(), 0.0, 2.0, 0.1, q0, stepsize_controller=controller, max_steps=64
        )
        exact = jq.multiply(jq.from_rotvec(2.0 * omega), unit)
        assert float(jq.angle_between(sol.ys[-1], exact)) < 1e-14


def test_steps_past_a_half_turn_dense_output_the_documented_way():
    """NormalizedEuler with the corrected field: past |ω|Δt = π the steps are still the exact
    rotations, but its dense output turns the short way (documented; a review measured 3.1 rad off
    mid-step at |ω|Δt = 3.5). The remedy the docstring names, LieEuler with the plain field, is exact
    between the steps too, at 3.5 rad a step and at more than a full turn."""
    ts = jnp.array([0.25, 0.5, 1.0, 1.3, 1.5, 2.0])
    for speed in [3.5, 7.0]:
        omega = jnp.array([0.2, -0.1, speed])
        exact = jq.from_rotvec(ts[:, None] * omega[None, :])
        saveat = diffrax.SaveAt(ts=ts)
        lie = diffrax.diffeqsolve(
            diffrax.ODETerm(jq.kinematic_vector_field(omega)),
            jq.LieEuler(),
            0.0,
            2.0,
            1.0,
            jq.identity(),
            saveat=saveat,
        )
        assert float(jnp.max(jq.angle_between(lie.ys, exact))) < 1e-13
        seed = diffrax.diffeqsolve(
            diffrax.ODETerm(jq.corrected_vector_field(omega, 1.0)),
            jq.NormalizedEuler(),
            0.0,
            2.0,
            1.0,
            jq.identity(),
            saveat=saveat,
        )
        errors = np.asarray(jq.angle_between(seed.ys, exact))
        np.testing.assert_allclose(errors[[2, 5]], 0.0, atol=1e-13)  # the steps
        if speed < 2 * math.pi:
            # Mid-step, the short way round: (θ − 2π)/2 instead of θ/2, a half-turn apart.
            np.testing.assert_allclose(errors[1], np.pi, atol=1e-12)


def _wrapped(omega):
    """`omega(t, q)` wrapped as users wrap functions: jit, an equinox Module under filter_jit,
    checkpoint, and a lax.cond on t (each a nested jaxpr in the caller's trace)."""

    class Spin(eqx.Module):
        scale: jax.Array

        def __call__(self, t, q):
            return self.scale * omega(t, q)

    def branching(t, q):
        return jax.lax.cond(t < 0.5, omega, lambda t_, q_: 1.0 * omega(t_, q_), t, q)

    return {
        "jit": jax.jit(omega),
        "filter_jit Module": eqx.filter_jit(Spin(jnp.array(1.0))),
        "checkpoint": jax.checkpoint(omega),
        "cond": branching,
    }


@pytest.mark.parametrize("method", ["magnus4", "magnus6"])
def test_magnus_accepts_a_wrapped_omega_of_t_and_refuses_a_wrapped_omega_of_q(method):
    """The q-dependence check read a nested call (jax.jit, eqx.filter_jit, checkpoint, cond) as using
    all of its inputs: a jitted ω(t), which never reads q, was refused by every Magnus method. The
    check now follows the data flow inside; a wrapped ω that does read q is still refused. The
    accepted runs equal the unwrapped one's."""
    q0 = jnp.array([1.0, 0.0, 0.0, 0.0])
    of_t = lambda t, q: jnp.array([jnp.cos(t), jnp.sin(2 * t), 0.5])  # noqa: E731
    of_q = lambda t, q: jq.rotate(jnp.array([jnp.cos(t), 0.0, 1.0]), q)  # noqa: E731
    expected = jq.integrate(q0, of_t, 0.05, 20, method=method, save="final")
    solver = {"magnus4": jq.Magnus4, "magnus6": jq.Magnus6}[method]()
    for name, omega in _wrapped(of_t).items():
        got = jq.integrate(q0, omega, 0.05, 20, method=method, save="final")
        np.testing.assert_allclose(got, expected, atol=1e-14, err_msg=name)
        ensemble = jq.simulate_ensemble(q0[None], omega, 0.05, 20, method=method).final[0]
        np.testing.assert_allclose(ensemble, expected, atol=1e-14, err_msg=name)
        term = diffrax.ODETerm(jq.kinematic_vector_field(omega))
        sol = diffrax.diffeqsolve(term, solver, 0.0, 1.0, 0.05, q0)
        np.testing.assert_allclose(sol.ys[-1], expected, atol=1e-12, err_msg=name)
    for omega in _wrapped(of_q).values():
        _assert_refused_by_magnus(omega, method, solver)


def _assert_refused_by_magnus(omega, method, solver):
    """`integrate`, `simulate_ensemble` and the diffrax `solver` each refuse ω as depending on q."""
    q0 = jnp.array([1.0, 0.0, 0.0, 0.0])
    with pytest.raises(ValueError, match="depends on q"):
        jq.integrate(q0, omega, 0.05, 4, method=method)
    with pytest.raises(ValueError, match="depends on q"):
        jq.simulate_ensemble(q0[None], omega, 0.05, 4, method=method)
    term = diffrax.ODETerm(jq.kinematic_vector_field(omega))
    with pytest.raises(ValueError, match="depends on q"):
        diffrax.diffeqsolve(term, solver, 0.0, 0.2, 0.05, q0)


def _through_a_side_effect(wrap, load_first):
    """ω(t, q) that hands q back through a side effect: an ordered `io_callback` stores q, another
    with no operands returns it (each passed through `wrap`), after the store or before it (then
    it returns the q of the previous call; the first call finds the identity's)."""
    box = {"q": np.array([1.0, 0.0, 0.0, 0.0])}

    def store(q):
        box["q"] = np.asarray(q)

    def load():
        return box["q"][1:].astype(np.float64)

    def omega(t, q):
        shape = jax.ShapeDtypeStruct((3,), q.dtype)
        loaded = wrap(lambda: io_callback(load, shape, ordered=True))() if load_first else None
        wrap(lambda q_: io_callback(store, None, q_, ordered=True))(q)
        if not load_first:
            loaded = wrap(lambda: io_callback(load, shape, ordered=True))()
        return loaded + jnp.array([0.0, 0.0, t])

    return omega


@pytest.mark.parametrize("load_first", [False, True], ids=["store-load", "load-store"])
@pytest.mark.parametrize("wrap", [lambda f: f, jax.jit], ids=["plain", "jit"])
def test_magnus_refuses_an_omega_that_reads_q_through_a_side_effect(wrap, load_first):
    """A dependence on q carried by a side effect rather than by data flow (helper-46's and
    helper-47's repros): the forward walk saw no path from q to the output and let magnus4 run it
    silently. Once q has reached any effect, every effect that returns a value counts as depending
    on q, before it (a load of the previous call's q) or after it. Printing q with
    `jax.debug.print` alone still does not, and the runs that are refused are run by cf4."""
    q0 = jnp.array([1.0, 0.0, 0.0, 0.0])
    omega = _through_a_side_effect(wrap, load_first)
    _assert_refused_by_magnus(omega, "magnus4", jq.Magnus4())
    _assert_refused_by_magnus(omega, "magnus6", jq.Magnus6())
    # The callback really does feed q back: cf4 runs it and its result differs from the same run
    # with ω = (0, 0, t) alone.
    fed_back = jq.integrate(q0, omega, 0.05, 4, method="cf4", save="final")
    alone = jq.integrate(
        q0, lambda t, q: jnp.array([0.0, 0.0, t]), 0.05, 4, method="cf4", save="final"
    )
    assert float(jnp.max(jnp.abs(fed_back - alone))) > 1e-6

    def printed(t, q):
        jax.debug.print("q = {}", q)
        # (An effect that returns a value, after q was printed: refused at 3a5f764, helper-50.)
        from_t = io_callback(
            lambda t: np.array([0.0, 0.0, 0.5]), jax.ShapeDtypeStruct((3,), q.dtype), t
        )
        return jnp.array([jnp.cos(t), 0.0, 0.0]) + from_t

    got = jq.integrate(q0, printed, 0.05, 4, method="magnus4", save="final")
    expected = jq.integrate(q0, printed, 0.05, 4, method="cf4", save="final")
    np.testing.assert_allclose(got, expected, atol=1e-6)


def test_magnus_refuses_an_omega_that_reads_q_through_a_global_reference():
    """A global `jax.new_ref` read, then written with q: the value read is the previous call's q
    (helper-47's repro; the walk saw the write only after the read). A reference read alone is a
    function of t only and runs."""
    q0 = jnp.array([1.0, 0.0, 0.0, 0.0])
    ref = jax.new_ref(jnp.zeros(3))

    def through(t, q):
        previous = ref[...]
        ref[...] = q[1:]
        return previous + jnp.array([0.0, 0.0, t])

    with pytest.raises(ValueError, match="depends on q"):
        jq.integrate(q0, through, 0.05, 4, method="magnus4")
    read_only = lambda t, q: ref[...] + jnp.array([jnp.cos(t), 0.0, 0.5])  # noqa: E731
    got = jq.integrate(q0, read_only, 0.05, 4, method="magnus4", save="final")
    expected = jq.integrate(q0, read_only, 0.05, 4, method="cf4", save="final")
    np.testing.assert_allclose(got, expected, atol=1e-6)


def test_normalized_euler_refuses_steps_other_than_the_corrected_fields_dt():
    """The seed's recipe is exact for steps of dt only: a last step clipped to t1 = 1.05 (or
    uneven StepTo steps) turned the body 0.074 rad too little at |ω| = 10, silently (helper-54).
    Steps of dt, forwards, backwards or far from t = 0, under jit and vmap, still run exactly."""
    from helpers import quat_distance
    from scipy.spatial.transform import Rotation

    omega, h = jnp.array([0.0, 0.0, 10.0]), 0.1
    term = diffrax.ODETerm(jq.corrected_vector_field(omega, h))
    solver = jq.NormalizedEuler()
    match = "NormalizedEuler: a step t1 - t0 differs from the `dt` of its corrected_vector_field"
    with pytest.raises(Exception, match=match):
        diffrax.diffeqsolve(term, solver, 0.0, 1.05, h, jq.identity())
    uneven = diffrax.StepTo(jnp.array([0.0, 0.1, 0.25, 0.3]))
    with pytest.raises(Exception, match=match):
        diffrax.diffeqsolve(term, solver, 0.0, 0.3, None, jq.identity(), stepsize_controller=uneven)
    for t0, t1, dt0 in ((0.0, 1.0, h), (1.0, 0.0, -h), (1000.0, 1003.0, h)):
        sol = diffrax.diffeqsolve(term, solver, t0, t1, dt0, jq.identity())
        expected = Rotation.from_rotvec(np.asarray(omega) * (t1 - t0)).as_quat()[[3, 0, 1, 2]]
        assert quat_distance(sol.ys[-1], expected) < 1e-12

    @jax.jit
    @jax.vmap
    def final(rate):
        field = diffrax.ODETerm(jq.corrected_vector_field(rate * omega, h))
        return diffrax.diffeqsolve(field, solver, 0.0, 1.0, h, jq.identity()).ys[-1]

    rates = jnp.array([0.5, 1.0, 2.0])
    expected = Rotation.from_rotvec(np.outer(np.asarray(rates), omega)).as_quat()[:, [3, 0, 1, 2]]
    assert quat_distance(final(rates), expected) < 1e-12


@pytest.mark.parametrize(
    "turns, dtype, tol",
    [(1.0, jnp.float64, 1e-12), (2.0, jnp.float64, 1e-12), (1.0, jnp.float32, 5e-6)],
)
def test_cf4_dense_output_of_steps_of_whole_turns_keeps_the_axis(turns, dtype, tol):
    # A CF4 step turning by exactly 2π (or 4π) leaves vec(q1 ⊗ q0*) at round-off, whose direction was
    # taken as the interpolant's axis: mid-step 0.26 rad (2π) and 1.3 rad (4π) off in float64.
    axis = np.array([0.3, -0.5, 0.8]) / np.linalg.norm([0.3, -0.5, 0.8])
    w = jnp.asarray(2 * np.pi * turns * axis, dtype)
    q0 = jq.normalize(jnp.array([0.9, 0.1, -0.3, 0.2], dtype))
    ts = jnp.array([0.25, 0.5, 0.75, 1.5], dtype)
    term = diffrax.ODETerm(jq.kinematic_vector_field(w))
    sol = diffrax.diffeqsolve(term, jq.CF4(), 0.0, 2.0, 1.0, q0, saveat=diffrax.SaveAt(ts=ts))
    exact = jq.multiply(jq.from_rotvec(ts[:, None] * w[None, :]), q0[None, :])
    err = jnp.minimum(
        jnp.linalg.norm(sol.ys - exact, axis=-1), jnp.linalg.norm(sol.ys + exact, axis=-1)
    )
    assert sol.ys.dtype == dtype
    assert float(jnp.max(err)) < tol


@pytest.mark.parametrize(
    "dtype, theta, atol",
    [(jnp.float64, 1e-12, 1e-14), (jnp.float64, 1e-18, 1e-14), (jnp.float64, 1e-30, 1e-14)]
    + [(jnp.float32, 1e-3, 3e-7), (jnp.float32, 1e-6, 3e-7), (jnp.float32, 1e-10, 3e-7)],
)
def test_cf4_dense_output_derivative_at_tiny_steps(dtype, theta, atol):
    """CF4's dense output took the step's rotation vector apart along its own estimate ĝ even for a
    tiny step, putting 1/|ω|h into the derivative (helper-62): jacrev 5e-6 off at |ω|h = 1e-12, 1.0 at 1e-18,
    1e12 at 1e-30 (float64); 6.6e-6 at 1e-3, 1e-2 at 1e-6, 15 at 1e-10 (float32). The exact
    Jacobian is that of `step` (constant ω)."""
    # float32 with x64 off: with x64 on, diffrax's float64 times promote the steps to float64.
    with jax.enable_x64(dtype == jnp.float64):
        _check_cf4_dense_derivative(dtype, theta, atol)


def _check_cf4_dense_derivative(dtype, theta, atol):
    q0 = jnp.asarray([0.4, -0.2, 0.7, 0.55], dtype)
    q0 = q0 / jnp.linalg.norm(q0)
    axis = jnp.asarray(np.array([0.3, -0.5, 0.8]) / np.linalg.norm([0.3, -0.5, 0.8]), dtype)
    h = 0.25
    omega = axis * jnp.asarray(theta / h, dtype)

    ts = jnp.asarray([0.37, 0.5], dtype)

    def dense(w, forward):
        sol = diffrax.diffeqsolve(
            diffrax.ODETerm(jq.kinematic_vector_field(w)),
            jq.CF4(),
            0.0,
            1.0,
            h,
            q0,
            saveat=diffrax.SaveAt(dense=True),
            adjoint=diffrax.ForwardMode() if forward else diffrax.RecursiveCheckpointAdjoint(),
        )
        return jnp.stack([sol.evaluate(t) for t in ts])

    exact = jax.jacfwd(lambda w: jq.step(q0, w, ts))(omega)
    rev = jax.jacrev(lambda w: dense(w, False))(omega)
    fwd = jax.jacfwd(lambda w: dense(w, True))(omega)
    np.testing.assert_allclose(rev, exact, atol=atol)
    np.testing.assert_allclose(fwd, exact, atol=atol)


def test_magnus_probe_has_no_blind_axis_and_works_in_half_precision():
    """The probe turns q0 about two axes: body-frame rates along the first turn's axis (1, 2, 3)
    at the first midpoint, given to the world-frame solver from the identity, were not flagged
    with one turn; and in float16/bfloat16 a tolerance of 1024 ε ≥ 1 could never fail (helper-77)."""
    axis = jnp.array([1.0, 2.0, 3.0])

    def body(t, q, args):
        w = axis * (1.0 + (t - 0.125)) + (t - 0.125) * jnp.array([1.0, 0.0, 0.0])
        return 0.5 * jq.multiply(q, jq.from_vector(w.astype(q.dtype)))

    identity = jnp.array([1.0, 0.0, 0.0, 0.0])
    with pytest.raises(eqx.EquinoxRuntimeError, match="depends on q"):
        diffrax.diffeqsolve(diffrax.ODETerm(body), jq.Magnus4(), 0.0, 2.0, 0.25, identity)
    q0 = jq.normalize(jnp.array([0.9, 0.1, -0.3, 0.2]))
    for dtype in [jnp.float16, jnp.bfloat16]:
        y0, t1, dt0 = q0.astype(dtype), dtype(2.0), dtype(0.25)
        with pytest.raises(eqx.EquinoxRuntimeError, match="depends on q"):
            diffrax.diffeqsolve(diffrax.ODETerm(body), jq.Magnus4(), dtype(0.0), t1, dt0, y0)
        ys = diffrax.diffeqsolve(
            diffrax.ODETerm(body), jq.Magnus4(frame="body"), dtype(0.0), t1, dt0, y0
        ).ys
        assert ys.dtype == dtype and np.all(np.isfinite(np.asarray(ys, np.float32)))
