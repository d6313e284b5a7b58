"""Mathematics of the fixed-step integrators: closed forms, convergence orders, exactness on sampled
data, long-run round-off, gradients (incl. exactly at rest), bounded reverse-mode memory, errors.

References: per-step closed forms of every method for constant ω, a closed-form coning motion
(checked against the kinematic equation with exact derivatives before use), SciPy's `Rotation`
composition, stability polynomials of the Runge–Kutta schemes, and central finite differences.
"""

import dataclasses
import functools
import os
import subprocess
import sys
import textwrap

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest
from helpers import assert_quat_close, count_lowerings, quat_distance, random_unit
from scipy.spatial.transform import Rotation

import jaxquat as jq
from jaxquat._integrate import lie_step, scan_steps

FRAMES = ["world", "body"]
LIE = ["euler", "midpoint", "magnus4", "magnus6", "magnus8", "cf4"]
ALL = LIE + ["naive", "rk4"]
ORDERS = {
    "euler": 1,
    "midpoint": 2,
    "magnus4": 4,
    "magnus6": 6,
    "magnus8": 8,
    "cf4": 4,
    "naive": 1,
    "rk4": 4,
}


def angle(p, q):
    """Geodesic angle between rotations p and q (sign-invariant), computed in numpy float64."""
    p = np.asarray(p, np.float64)
    q = np.asarray(q, np.float64)
    chord = np.minimum(np.linalg.norm(p - q, axis=-1), np.linalg.norm(p + q, axis=-1))
    return 4.0 * np.arcsin(np.minimum(chord / 2.0, 1.0))


# ----------------------------------------------------------------------------------------------------
# A closed-form coning motion: q(t) = exp(Ωt ẑ) ⊗ exp(νt n̂₀) ⊗ q₀.
# Then q̇ = ½ω̃q with ω_world(t) = Ωẑ + ν R_z(Ωt) n̂₀, and ω_body(t) = R(q₀)ᵀ(Ω R(b(t))ᵀ ẑ + ν n̂₀),
# b(t) = exp(νt n̂₀). The spin axis cones about ẑ; ω is time-varying and q-independent.

CONE_RATE, SPIN_RATE, HALF_ANGLE = 2.0, 3.0, 0.6
SPIN_AXIS = jnp.array([np.sin(HALF_ANGLE), 0.0, np.cos(HALF_ANGLE)])
Z_AXIS = jnp.array([0.0, 0.0, 1.0])
CONE_Q0 = jq.normalize(jnp.array([0.9, 0.2, -0.3, 0.25]))


def coning_attitude(t):
    a = jq.from_rotvec(CONE_RATE * t * Z_AXIS)
    b = jq.from_rotvec(SPIN_RATE * t * SPIN_AXIS)
    return jq.multiply(a, jq.multiply(b, CONE_Q0))


def coning_omega_world(t, q=None):
    return CONE_RATE * Z_AXIS + SPIN_RATE * jq.rotate(
        SPIN_AXIS, jq.from_rotvec(CONE_RATE * t * Z_AXIS)
    )


def coning_omega_body(t, q=None):
    b = jq.from_rotvec(SPIN_RATE * t * SPIN_AXIS)
    v = CONE_RATE * jq.rotate(Z_AXIS, jq.conjugate(b)) + SPIN_RATE * SPIN_AXIS
    return jq.rotate(v, jq.conjugate(CONE_Q0))


CONING_OMEGA = {"world": coning_omega_world, "body": coning_omega_body}


def test_coning_closed_form_solves_the_kinematic_equation():
    """The reference itself: d/dt of the closed form equals rate(q, ω(t)) (exact AD derivative)."""
    ts = jnp.linspace(0.0, 3.0, 7)
    for t in ts:
        dq = jax.jacfwd(coning_attitude)(t)
        q = coning_attitude(t)
        np.testing.assert_allclose(dq, jq.rate(q, coning_omega_world(t)), atol=2e-15)
        np.testing.assert_allclose(dq, jq.rate(q, coning_omega_body(t), frame="body"), atol=2e-15)


@pytest.mark.parametrize("frame", FRAMES)
def test_convergence_orders_on_coning(frame):
    """Acceptance 3: slope of log error vs log dt over 3 refinements, T = 2.3 (not a whole number of
    periods): euler 1, midpoint 2, magnus4 4, magnus6 6, magnus8 8, cf4 4, naive 1, rk4 4, each
    within ±0.15 (magnus8, 5 to 40 steps: 8.00 world, 7.98 body).

    The four resolutions run as one vmapped loop of `lie_step` (the step `integrate` scans; one
    compilation per method), and `integrate` is checked against it at the finest resolution."""
    horizon = 2.3
    reference = coning_attitude(horizon)
    omega = CONING_OMEGA[frame]
    for method in ALL:
        # The naive step's O(h²) lag (θ³/12 per step) hides its first-order term at coarse steps.
        # magnus6 and magnus8 reach round-off within 8x refinement from 40 steps; they start lower.
        base = {"naive": 640, "magnus6": 10, "magnus8": 5}.get(method, 40)
        steps = np.array([base, 2 * base, 4 * base, 8 * base])

        def run(n, method=method):
            h = horizon / n

            def body(k, q):
                return lie_step(
                    method, lambda t, q, x: (omega(t), None), k * h, q, None, h, frame=frame
                )[0]

            return jax.lax.fori_loop(0, n, body, CONE_Q0)

        finals = jax.jit(jax.vmap(run))(jnp.asarray(steps))
        errors = angle(finals, reference)
        slope = -np.polyfit(np.log(steps), np.log(errors), 1)[0]
        assert abs(slope - ORDERS[method]) <= 0.15, (method, slope, errors)
        assert errors[-1] > 1e-12, (
            method,
            errors,
        )  # still above round-off: the slope is meaningful
        if method in ("cf4", "magnus6", "magnus8") and frame == "world":
            direct = jq.integrate(
                CONE_Q0,
                omega,
                horizon / steps[-1],
                int(steps[-1]),
                frame=frame,
                method=method,
                save="final",
            )
            assert_quat_close(direct, finals[-1], atol=1e-13)


# ----------------------------------------------------------------------------------------------------
# Constant ω: per-step closed forms of every method.


def _per_step_angle(method, theta):
    """The rotation angle one step of `method` makes for constant ω with θ = |ω|Δt."""
    if method in LIE:
        return theta
    if method == "naive":  # normalize(1 + (θ/2) n̂): the seed's "quarter of the way round" limit
        return 2.0 * np.arctan(theta / 2.0)
    # RK4: the degree-4 Taylor polynomial of exp((θ/2) ñ) = (1 − θ²/8 + θ⁴/384) + (θ/2)(1 − θ²/24) ñ
    return 2.0 * np.arctan2(
        theta / 2.0 * (1.0 - theta**2 / 24.0), 1.0 - theta**2 / 8.0 + theta**4 / 384.0
    )


@pytest.mark.parametrize(
    "method,frame",
    [
        ("euler", "world"),
        ("midpoint", "body"),
        ("magnus4", "world"),
        ("magnus6", "body"),
        ("magnus8", "world"),
        ("magnus8", "body"),
        ("cf4", "body"),
        ("naive", "world"),
        ("rk4", "body"),
    ],
)
def test_constant_omega_matches_each_methods_closed_form(method, frame, getkey):
    """Lie methods are exact for constant ω at any step size (also past half a turn per step); naive
    turns by 2·atan(θ/2) per step, RK4 + normalise by the angle of its Taylor polynomial."""
    thetas = np.array([0.0, 1e-6, 1e-3, 0.5, 2.5, 4.0, 9.0])
    axes = np.array(jax.random.normal(getkey(), (thetas.size, 3)))
    axes /= np.linalg.norm(axes, axis=-1, keepdims=True)
    dt, steps = 0.5, 50
    omega = jnp.asarray(axes * (thetas / dt)[:, None])
    q0 = random_unit(getkey(), (thetas.size,))
    q = jq.integrate(q0, omega, dt, steps, frame=frame, method=method, save="final")
    total = steps * _per_step_angle(method, thetas)
    rotation = jq.from_rotvec(jnp.asarray(axes * total[:, None]))
    expected = jq.multiply(rotation, q0) if frame == "world" else jq.multiply(q0, rotation)
    assert_quat_close(q, expected, atol=2e-13)
    np.testing.assert_allclose(np.linalg.norm(np.asarray(q), axis=-1), 1.0, atol=1e-15)


@pytest.mark.parametrize("frame", FRAMES)
def test_piecewise_constant_sampled_omega_is_exact(frame, getkey):
    """Acceptance 3b: sampled ω + euler is exact to round-off (SciPy composition of the per-step
    rotations, also with θ up to ~3 rad per step and t0 ≠ 0); the interior stages of midpoint,
    magnus4, magnus6 and magnus8 see the same sample, so they are exact too."""
    steps, dt, t0 = 200, 0.05, 1000.3
    omegas = 20.0 * jax.random.normal(getkey(), (steps, 2, 3))
    q0 = random_unit(getkey(), (2,))
    current = Rotation.from_quat(np.asarray(jq.to_xyzw(q0)))
    increments = Rotation.from_rotvec(np.asarray(omegas).reshape(-1, 3) * dt)
    trajectory = [current.as_quat()]
    for k in range(steps):
        r = increments[2 * k : 2 * k + 2]
        current = r * current if frame == "world" else current * r
        trajectory.append(current.as_quat())
    trajectory = np.roll(np.stack(trajectory), 1, axis=-1)  # xyzw -> wxyz
    source = jq.sampled(omegas, dt, t0=t0)
    for method in ["euler", "midpoint", "magnus4", "magnus6", "magnus8"]:
        qs = jq.integrate(q0, source, dt, steps, frame=frame, method=method, t0=t0)
        assert qs.shape == (steps + 1, 2, 4)
        assert_quat_close(qs, trajectory, atol=1e-12)


@pytest.mark.parametrize("frame", ["world", "body"])
def test_sampled_omega_integrated_backwards_undoes_the_forward_run(frame, getkey):
    """Backwards (dt < 0) a step starts at the later end of its interval, where the zero-order hold
    forwards already holds the next sample: the step must hold the sample of the interval it crosses.
    Euler (fast path, and the general scan via save_every), the interior-stage methods, sub-steps of a
    sample and a traced dt all return exactly to q₀, and each backward step is the inverse rotation."""
    samples, ds = 6, 0.5
    omegas = 2.0 * jax.random.normal(getkey(), (samples, 3))
    q0 = random_unit(getkey(), ())
    source = jq.sampled(omegas, ds, t0=2.0)
    t_end = 2.0 + samples * ds
    for per_sample in [1, 3]:
        h, n = ds / per_sample, samples * per_sample
        q_end = jq.integrate(q0, source, h, n, frame=frame, t0=2.0, save="final")
        expected = Rotation.from_quat(np.asarray(jq.to_xyzw(q0)))
        for k in range(samples):  # the closed form of the forward run
            r = Rotation.from_rotvec(np.asarray(omegas[k]) * ds)
            expected = r * expected if frame == "world" else expected * r
        assert_quat_close(jq.to_xyzw(q_end), expected.as_quat(), atol=1e-13)
        for method, save_every in [("euler", 1), ("euler", 2), ("midpoint", 1), ("magnus4", 1)]:
            back = jq.integrate(
                q_end, source, -h, n, frame=frame, t0=t_end, method=method, save_every=save_every
            )
            assert_quat_close(back[-1], q0, atol=1e-13)
        backward = functools.partial(jq.integrate, frame=frame, t0=t_end, save="final")
        traced = jax.jit(backward, static_argnums=3)(q_end, source, -jnp.asarray(h), n)
        assert_quat_close(traced, q0, atol=1e-13)


def test_sampled_called_at_an_array_of_times():
    """`Sampled(t)` takes times of any shape, as `AngularVelocityCurve` does (a TypeError from
    `dynamic_slice` before); each entry is the scalar lookup."""
    omegas = jnp.arange(12.0).reshape(4, 3)
    source = jq.sampled(omegas, 0.1, t0=1.0)
    times = jnp.array([[0.5, 1.0, 1.15], [1.2999999999, 1.3, 9.0]])
    out = source(times)
    assert out.shape == (2, 3, 3)
    scalar = np.stack([source(t) for t in times.reshape(-1)]).reshape(2, 3, 3)
    np.testing.assert_array_equal(out, scalar)
    np.testing.assert_array_equal(out[:, :, 0], [[0.0, 0.0, 3.0], [6.0, 9.0, 9.0]])


def test_sampled_dense_output_between_the_steps():
    """On the sampling grid diffrax's Magnus4 is exact at and between the steps; LieEuler's steps are
    exact, but its Hermite dense output reads the next sample for its end slope (documented in
    `sampled`: up to ≈ 0.15·Δt·|Δω| between the steps)."""
    import diffrax

    rng = np.random.default_rng(3)
    num, h = 10, 0.1
    omegas = rng.normal(size=(num, 3))
    q0 = jq.identity()
    ts = np.linspace(0.0, num * h, 83)
    expected = []
    for t in ts:
        k = min(int(np.floor(t / h + 1e-9)), num - 1)
        rot = Rotation.from_rotvec(omegas[k] * (t - k * h))
        for j in range(k - 1, -1, -1):
            rot = rot * Rotation.from_rotvec(omegas[j] * h)
        expected.append(rot.as_quat())
    expected = np.stack(expected)
    term = diffrax.ODETerm(jq.kinematic_vector_field(jq.sampled(jnp.asarray(omegas), h)))

    def dense(solver, where):
        sol = diffrax.diffeqsolve(
            term,
            solver,
            0.0,
            num * h,
            h,
            q0,
            saveat=diffrax.SaveAt(ts=jnp.asarray(ts)),
            max_steps=20,
        )
        return quat_distance(jq.to_xyzw(sol.ys)[where], expected[where])

    everywhere = np.ones(ts.shape, bool)
    on_steps = np.isclose(np.mod(ts / h + 0.5, 1.0), 0.5)
    assert dense(jq.Magnus4(), everywhere) < 1e-13
    assert dense(jq.LieEuler(), on_steps) < 1e-13
    jump = np.max(np.linalg.norm(np.diff(omegas, axis=0), axis=-1))
    assert dense(jq.LieEuler(), ~on_steps) < 0.15 * h * jump


def test_sampled_float32_lookup_at_large_times():
    """float32 times near 10³ s resolve ~6e-5 s; looking samples up by absolute time put Magnus8's
    outer Gauss node (6.9% of a step before the boundary) in the next sample (4e-3 rad wrong) and
    mis-held fine sub-steps. `integrate` looks samples up relative to the first one: every method,
    on and off the grid and with traced steps, is exact to float32 round-off against float64 SciPy."""
    rng = np.random.default_rng(4)
    samples, ds, t0 = 200, np.float32(0.01), np.float32(1000.0)
    omegas = rng.normal(0.0, 1.0, (samples, 3)).astype(np.float32)
    q0 = jnp.array([1.0, 0.0, 0.0, 0.0], jnp.float32)
    expected = Rotation.identity()
    for k in range(samples):
        expected = Rotation.from_rotvec(omegas[k].astype(np.float64) * float(ds)) * expected
    expected = expected.as_quat()
    source = jq.sampled(jnp.asarray(omegas), jnp.asarray(ds), t0=jnp.asarray(t0))

    def run(h, n, method):
        return jq.integrate(q0, source, h, n, t0=jnp.asarray(t0), method=method, save="final")

    for method in ["euler", "midpoint", "magnus4", "magnus6", "magnus8"]:
        q = jax.jit(run, static_argnums=(1, 2))(jnp.asarray(ds), samples, method)
        assert q.dtype == jnp.float32
        assert quat_distance(jq.to_xyzw(q), expected) < 2e-6, method
    q = jax.jit(run, static_argnums=(1, 2))(jnp.asarray(ds / np.float32(50)), 50 * samples, "euler")
    assert quat_distance(jq.to_xyzw(q), expected) < 2e-5


# ----------------------------------------------------------------------------------------------------
# Coupled state (the interface `lie_step` offers the dynamics).


@pytest.mark.parametrize("method", ["euler", "midpoint", "cf4", "naive", "rk4"])
def test_lie_step_coupled_state_uses_consistent_stages(method):
    """With a clock state ẋ = 1 driving ω(x), each stage's x equals its stage time, so the coupled
    run equals integrate with ω(t) to round-off; on ẋ = x the x-part is the scheme's stability
    polynomial R(h)^N (Euler 1 + h, midpoint + h²/2, RK4 through h⁴/24)."""
    steps, h = 60, 0.04

    def clock_field(t, q, x):
        return coning_omega_world(x[0]), (jnp.ones(1), -x[1])

    def step_fn(k, carry):
        q, x = carry
        return lie_step(method, clock_field, 0.0 * k, q, x, h, frame="world")

    (q, (clock, decay)), _ = scan_steps(
        step_fn, (CONE_Q0, (jnp.zeros(1), jnp.ones(()))), steps, save="final"
    )
    direct = jq.integrate(CONE_Q0, coning_omega_world, h, steps, method=method, save="final")
    assert_quat_close(q, direct, atol=1e-14)
    np.testing.assert_allclose(clock, steps * h, rtol=1e-14)
    z = -h
    stability = {
        "euler": 1 + z,
        "naive": 1 + z,
        "midpoint": 1 + z + z**2 / 2,
        "cf4": 1 + z + z**2 / 2 + z**3 / 6 + z**4 / 24,
        "rk4": 1 + z + z**2 / 2 + z**3 / 6 + z**4 / 24,
    }[method]
    np.testing.assert_allclose(decay, stability**steps, rtol=1e-13)


@pytest.mark.parametrize("method", ["magnus4", "magnus6", "magnus8"])
def test_lie_step_magnus_rejects_a_coupled_state(method):
    with pytest.raises(ValueError, match=method):
        lie_step(
            method,
            lambda t, q, x: (jnp.zeros(3), x),
            0.0,
            jq.identity(),
            jnp.ones(2),
            0.1,
            frame="world",
        )


@pytest.mark.parametrize("frame", FRAMES)
def test_magnus_constant_omega_is_exact_in_float32(frame, getkey):
    """For constant ω the Magnus increments are exactly hω: the commutator corrections vanish (the
    Gauss-point rates are equal), so magnus8, magnus6 and magnus4 take bit-identical float32 steps, and
    they stay within float32 round-off of the float64 closed form (also at θ = 2.5 rad per step, and
    far past the series' convergence, 10 and 100 rad per step: magnus8's exponent is exact there
    only if B₂'s part off B₀ is formed as α(Σuᵢ − 4B₀), which XLA cannot contract into a fused
    multiply-add; as αΣuᵢ − κB₀ a review measured 1.4e-3 rad at 100 rad per step)."""
    thetas = np.array([0.0, 1e-4, 0.3, 2.5, 10.0, 100.0])
    axes = np.array(jax.random.normal(getkey(), (thetas.size, 3)))
    axes /= np.linalg.norm(axes, axis=-1, keepdims=True)
    dt, steps = 0.25, 40
    w32 = jnp.asarray(axes * (thetas / dt)[:, None], jnp.float32)
    q32 = jnp.asarray(random_unit(getkey(), (thetas.size,)), jnp.float32)
    m6 = jq.integrate(q32, w32, dt, steps, frame=frame, method="magnus6", save="final")
    m4 = jq.integrate(q32, w32, dt, steps, frame=frame, method="magnus4", save="final")
    m8 = jq.integrate(q32, w32, dt, steps, frame=frame, method="magnus8", save="final")
    assert m6.dtype == m8.dtype == jnp.float32
    np.testing.assert_array_equal(np.asarray(m6), np.asarray(m4))
    np.testing.assert_array_equal(np.asarray(m8), np.asarray(m4))
    w64 = np.asarray(w32, np.float64)
    q64 = jq.normalize(jnp.asarray(q32, jnp.float64))
    rotation = Rotation.from_rotvec(steps * dt * w64).as_quat()  # SciPy, xyzw
    rotation = jnp.asarray(np.roll(rotation, 1, axis=-1))
    expected = jq.multiply(rotation, q64) if frame == "world" else jq.multiply(q64, rotation)
    # float32 round-off of the rotation: ~ε per radian turned (4,000 rad at 100 rad per step).
    tolerance = 2e-5 + steps * thetas * np.finfo(np.float32).eps
    assert np.all(angle(m6, expected) <= tolerance)


@pytest.mark.parametrize("method", ["magnus4", "magnus6", "magnus8"])
def test_magnus_body_frame_is_the_world_frame_of_the_inverse(method):
    """q̇ = ½q ω̃_b is q̇* = ½(−ω̃_b) q*, and a ↦ −a maps the body bracket b × a onto the world
    bracket a × b, so a body-frame Magnus run is the conjugate of the world-frame run with −ω_b from
    q₀* (to round-off; with the bracket of either frame reversed they differ by ~2e-2 here)."""

    def omega_body(t, q=None):
        return jnp.array([1.3, -0.4, 0.9]) + jnp.array([0.5, 2.0, -1.1]) * jnp.sin(2.6 * t + 0.3)

    h, steps = 0.11, 37
    body = jq.integrate(CONE_Q0, omega_body, h, steps, frame="body", method=method, t0=0.4)
    world = jq.integrate(
        jq.conjugate(CONE_Q0), lambda t, q: -omega_body(t), h, steps, method=method, t0=0.4
    )
    assert_quat_close(jq.conjugate(body), world, atol=1e-14)


def test_scan_steps_indices_saving_and_checkpointing():
    """step_fn sees k = 0 … n−1; saved holds the carries at 0, s, 2s, …; checkpointing changes neither
    values nor gradients."""

    def step_fn(k, carry):
        total, x = carry
        return total + k, jnp.sin(x) * 1.01 + 0.001 * k

    carry = (jnp.asarray(0, jnp.int32), jnp.asarray(0.3))
    n = 150  # > the plain-scan limit: exercises the nested, checkpointed structure and its tail
    final, saved = scan_steps(step_fn, carry, n, save="all", save_every=10)
    assert int(final[0]) == n * (n - 1) // 2
    np.testing.assert_array_equal(
        np.asarray(saved[0]), [k * (k - 1) // 2 for k in range(0, n + 1, 10)]
    )
    xs = [0.3]
    for k in range(n):
        xs.append(np.sin(xs[-1]) * 1.01 + 0.001 * k)
    np.testing.assert_allclose(np.asarray(saved[1]), xs[::10], rtol=1e-13)
    final_only, none = scan_steps(step_fn, carry, n, save="final")
    assert none is None and float(final_only[1]) == float(final[1])

    def loss(x0, checkpoint):
        return scan_steps(step_fn, (carry[0], x0), n, save="final", checkpoint=checkpoint)[0][1]

    g1 = jax.grad(loss)(0.3, True)
    g2 = jax.grad(loss)(0.3, False)
    np.testing.assert_allclose(g1, g2, rtol=1e-14)


# ----------------------------------------------------------------------------------------------------
# Long runs and float32.


def test_long_run_constant_omega_float64_and_float32():
    """Acceptance 2: 10⁶ steps of 10⁻³ rad. float64 error ≤ 1e-10 rad; float32 (compensated increment
    form, automatic for float32) ≤ 2e-4 rad, where plain float32 stepping is much worse."""
    steps, dt = 10**6, 1e-3
    axes = np.array([[0.6, 0.0, 0.8], [-0.28, 0.96, 0.0], [0.0, 0.6, -0.8]])  # |ω| = 1 rad/s
    q0 = np.asarray(
        jq.normalize(
            jnp.array([[0.3, -0.4, 0.5, 0.7], [1.0, 0.0, 0.0, 0.0], [0.1, 0.9, -0.2, 0.3]])
        )
    )
    for frame in FRAMES:
        rotation = jq.from_rotvec(
            jnp.asarray(axes.astype(np.float32).astype(np.float64) * steps * dt)
        )
        q0_32 = jnp.asarray(q0, jnp.float32)
        q0_ref = jq.normalize(q0_32.astype(jnp.float64))  # the rotations of the float32 inputs
        expected = (
            jq.multiply(rotation, q0_ref) if frame == "world" else jq.multiply(q0_ref, rotation)
        )
        q64 = jq.integrate(
            q0_ref, axes.astype(np.float32).astype(np.float64), dt, steps, frame=frame, save="final"
        )
        assert np.max(angle(q64, expected)) <= 1e-10
        w32 = jnp.asarray(axes, jnp.float32)
        q32 = jq.integrate(q0_32, w32, dt, steps, frame=frame, save="final")
        assert q32.dtype == jnp.float32
        err32 = np.max(angle(q32, expected))
        assert err32 <= 2e-4, err32
        plain = jq.integrate(
            q0_32,
            w32,
            dt,
            steps,
            frame=frame,
            save="final",
            compensated=False,
            renormalize_every=None,
        )
        assert np.max(angle(plain, expected)) > 5 * err32


def test_float32_long_run_about_random_axes_is_within_the_readme_bound():
    """README: 10⁶ float32 steps of 1e-3 rad about random axes stay within about 1.3e-4 rad (ε times the
    10³ rad turned) of the exact rotation by the float32 inputs' ω·Δt·10⁶, with median 3.5e-5 eagerly
    and 7.5e-5 under jit. It said 3e-5, then 1e-4 (median 4e-5); reviewers broke both: over 10 seeds
    of 64 axes I measured max 1.23e-4 eagerly and 1.26e-4 under jit, medians 2.8–3.9e-5 and
    7.0–8.4e-5. This seed: max 8.8e-5 / 1.04e-4, median 3.4e-5 / 7.4e-5."""
    rng = np.random.default_rng(3)
    axes = rng.normal(size=(64, 3))
    omega = (axes / np.linalg.norm(axes, axis=1, keepdims=True)).astype(np.float32)
    q0 = rng.normal(size=(64, 4))
    q0 = (q0 / np.linalg.norm(q0, axis=1, keepdims=True)).astype(np.float32)
    steps, dt = 10**6, np.float32(1e-3)
    exact = jq.multiply(
        jq.from_rotvec(jnp.asarray(omega.astype(np.float64) * float(dt) * steps)),
        jnp.asarray(q0.astype(np.float64)),
    )
    run = jax.jit(lambda q, w: jq.integrate(q, w, dt, steps, save="final"))
    for q, median in [
        (jq.integrate(jnp.asarray(q0), jnp.asarray(omega), dt, steps, save="final"), 5e-5),
        (run(jnp.asarray(q0), jnp.asarray(omega)), 1e-4),
    ]:
        error = np.asarray(jq.angle_between(q.astype(jnp.float64), exact))
        assert q.dtype == jnp.float32
        assert error.max() <= 1.5e-4 and np.median(error) <= median, (error.max(), np.median(error))


def test_float32_compensated_mode_is_the_default_and_keeps_dtype():
    """float32 states use the compensated increment form by default: it tracks the float64 solution to
    float32 round-off, where plain float32 products let |q| drift (no renormalisation within 300 steps)."""
    q0 = jnp.asarray([1.0, 0.0, 0.0, 0.0], jnp.float32)
    w = jnp.asarray([0.3, 0.2, -0.1], jnp.float32)
    auto = jq.integrate(q0, w, 0.01, 300, method="cf4")
    explicit = jq.integrate(q0, w, 0.01, 300, method="cf4", compensated=True)
    off = jq.integrate(q0, w, 0.01, 300, method="cf4", compensated=False)
    assert auto.dtype == explicit.dtype == off.dtype == jnp.float32
    np.testing.assert_array_equal(np.asarray(auto), np.asarray(explicit))
    exact = jq.integrate(q0.astype(jnp.float64), w.astype(jnp.float64), 0.01, 300, method="cf4")
    assert quat_distance(auto, exact) <= 1e-7
    assert quat_distance(off, exact) > 1e-6
    for method in ALL:
        assert jq.integrate(q0, w, 0.01, 5, method=method, save="final").dtype == jnp.float32


# ----------------------------------------------------------------------------------------------------
# Gradients.


class Wobble(eqx.Module):
    """ω(t, q) = a + b sin(2t) (+ c × vec(q) when coupled): a callable with PyTree parameters."""

    a: jax.Array
    b: jax.Array
    c: jax.Array
    coupled: bool = eqx.field(static=True)

    def __call__(self, t, q):
        w = self.a + self.b * jnp.sin(2.0 * t)
        if self.coupled:
            w = w + jq.rotate(self.c, q)
        return w


def _fd_jacobian(f, x, eps):
    x = np.asarray(x, np.float64)
    columns = []
    for i in range(x.size):
        dx = np.zeros_like(x)
        dx[i] = eps[i]
        columns.append((np.asarray(f(x + dx)) - np.asarray(f(x - dx))) / (2 * eps[i]))
    return np.stack(columns, axis=-1)


def _check_jacobians(f, x, eps, forward_mode=True, rtol=1e-7):
    """jacrev (and jacfwd) of f at x against central differences, relative per column."""
    f = jax.jit(f)
    reverse = np.asarray(jax.jit(jax.jacrev(f))(x))
    fd = _fd_jacobian(f, x, eps)
    scale = np.maximum(np.linalg.norm(fd, axis=0), 1e-3)
    if forward_mode:
        forward = np.asarray(jax.jit(jax.jacfwd(f))(x))
        np.testing.assert_array_less(np.linalg.norm(forward - reverse, axis=0) / scale, 1e-12)
    err = np.linalg.norm(reverse - fd, axis=0) / scale
    assert np.all(err <= rtol), err
    return reverse


def _tangent_basis(q):
    """Three unit 4-vectors orthogonal to q and to each other."""
    m = np.linalg.svd(np.eye(4) - np.outer(q, q))[0]
    return m[:, :3]


@pytest.mark.parametrize(
    "method,frame,source",
    [
        ("euler", "world", "constant"),
        ("cf4", "body", "coupled"),
        ("magnus4", "world", "callable"),
        ("magnus6", "body", "callable"),
        ("magnus8", "world", "callable"),
    ],
)
def test_gradients_agree_with_finite_differences(method, frame, source, getkey):
    """Acceptance 4: d q_final / d(ω or the callable's parameters, q₀ tangentially, dt, t0) over 1,000
    steps: jacfwd == jacrev, and both equal central differences to 1e-7 relative (per column)."""
    steps = 1000
    q0 = np.asarray(random_unit(getkey()))
    basis = _tangent_basis(q0)
    if source == "constant":
        params = np.asarray(jax.random.normal(getkey(), (3,)))
    else:
        params = np.asarray(jax.random.normal(getkey(), (9,)))
    x = np.concatenate([params, np.zeros(3), [2e-3, 0.4]])

    def final(x):
        p, s, dt, t0 = x[:-5], x[-5:-2], x[-2], x[-1]
        q = jq.normalize(q0 + basis @ s)
        if source == "constant":
            omega = p
        else:
            omega = Wobble(p[:3], p[3:6], p[6:9], coupled=source == "coupled")
        # The default (checkpointed) structure for the first case; the others compile faster without it
        # (test_scan_steps_indices_saving_and_checkpointing shows it does not change gradients).
        return jq.integrate(
            q, omega, dt, steps, frame=frame, method=method, t0=t0, save="final", checkpoint=default
        )

    default = source == "constant"
    eps = np.concatenate([np.full(params.size, 1e-5), np.full(3, 1e-5), [1e-8, 1e-5]])
    # magnus6 also checks jacfwd == jacrev (a plain scan in both modes; a few seconds).
    forward_mode = default or method == "magnus6"
    jac = _check_jacobians(final, jnp.asarray(x), eps, forward_mode=forward_mode)
    if source == "constant":  # ω constant: q_T does not depend on t0 at all
        assert np.all(jac[:, -1] == 0.0)


def test_gradient_exactly_at_rest(getkey):
    """Acceptance 4b: at ω = 0, d q_T/dω = ½·T·[0; I₃]·q₀ (world) or ½·T·q₀·[0; I₃] (body), T = NΔt,
    for every method (jacfwd), in reverse mode, for a callable's parameters, and by central differences."""
    steps, dt = 1000, 2e-3
    q0 = random_unit(getkey())
    basis = jnp.concatenate([jnp.zeros((3, 1)), jnp.eye(3)], axis=-1)
    expected = {
        "world": 0.5 * steps * dt * np.asarray(jq.multiply(basis, q0)).T,
        "body": 0.5 * steps * dt * np.asarray(jq.multiply(q0, basis)).T,
    }
    zero = jnp.zeros(3)

    def final(w, method="euler", frame="world", checkpoint=True):
        return jq.integrate(
            q0, w, dt, steps, frame=frame, method=method, save="final", checkpoint=checkpoint
        )

    frames = (["world", "body"] * len(ALL))[: len(ALL)]  # alternate frames over all methods
    for method, frame in zip(ALL, frames, strict=True):
        # Forward mode does not use the checkpointed structure; the plain scan compiles faster.
        jac = jax.jit(jax.jacfwd(lambda w, m=method, f=frame: final(w, m, f, False)))(zero)
        np.testing.assert_allclose(jac, expected[frame], atol=1e-14, err_msg=method)
    for method, frame in [("cf4", "world"), ("euler", "body")]:
        jac = jax.jit(jax.jacrev(lambda w, m=method, f=frame: final(w, m, f)))(zero)
        np.testing.assert_allclose(jac, expected[frame], atol=1e-14)
    fd = _fd_jacobian(jax.jit(final), np.zeros(3), np.full(3, 1e-6))
    np.testing.assert_allclose(fd, expected["world"], atol=1e-10)

    def through_callable(p):
        omega = Wobble(p, jnp.zeros(3), jnp.zeros(3), coupled=False)
        return jq.integrate(q0, omega, dt, steps, save="final")

    np.testing.assert_allclose(
        jax.jit(jax.jacrev(through_callable))(zero), expected["world"], atol=1e-14
    )


@pytest.mark.parametrize("dtype, eps, rtol", [("float64", 1e-6, 1e-7), ("float32", 1e-2, 2e-4)])
def test_magnus8_gradients_near_half_a_turn_per_step_and_in_float32(dtype, eps, rtol):
    """magnus8's Jacobian w.r.t. a callable's parameters: jacrev == jacfwd and both equal central
    differences at rest, generically, and at 0.999·π rad per step (measured: float64 1e-9 relative,
    float32 7e-5)."""
    q0 = jq.normalize(jnp.array([0.6, -0.2, 0.3, 0.5])).astype(dtype)

    def final(p):
        omega = lambda t, q: p[:3] + p[3:] * jnp.sin(1.7 * t)  # noqa: E731
        return jq.integrate(q0, omega, 0.1, 20, method="magnus8", save="final")

    f = jax.jit(final)
    half_turn = np.pi / 0.1 * 0.999 / np.sqrt(3.0)
    for point in ([0.0] * 6, [0.3, -1.2, 0.8, 0.5, 0.2, -0.4], [half_turn] * 3 + [0.1, -0.2, 0.05]):
        p = jnp.asarray(point, dtype)
        reverse = np.asarray(jax.jit(jax.jacrev(final))(p), np.float64)
        forward = np.asarray(jax.jit(jax.jacfwd(final))(p), np.float64)
        columns = []
        for e in np.eye(6):
            step = jnp.asarray(eps * e, dtype)
            plus, minus = np.asarray(f(p + step), np.float64), np.asarray(f(p - step), np.float64)
            columns.append((plus - minus) / (2.0 * float(step[np.argmax(e)])))
        fd = np.stack(columns, axis=-1)
        scale = max(np.abs(fd).max(), 1e-3)
        assert np.abs(reverse - forward).max() <= 10 * np.finfo(dtype).eps * scale, point
        error = np.abs(reverse - fd).max() / scale
        assert error <= rtol, (point, error)


def test_gradient_flows_to_samples():
    """d q_T / d omegas[k] for sampled data: each sample acts for one step of Δt; at rest the Jacobian
    w.r.t. every sample is ½Δt·[0; I₃]·q₀ (world)."""
    steps, dt = 50, 0.1
    q0 = jq.normalize(jnp.array([0.5, 0.1, 0.2, -0.3]))
    basis = jnp.concatenate([jnp.zeros((3, 1)), jnp.eye(3)], axis=-1)
    expected = 0.5 * dt * np.asarray(jq.multiply(basis, q0)).T
    jac = jax.jit(
        jax.jacrev(lambda om: jq.integrate(q0, jq.sampled(om, dt), dt, steps, save="final"))
    )(jnp.zeros((steps, 3)))
    assert jac.shape == (4, steps, 3)
    for k in range(steps):
        np.testing.assert_allclose(jac[:, k], expected, atol=1e-15)


# ----------------------------------------------------------------------------------------------------
# Memory.

_MEMORY_SCRIPT = textwrap.dedent(
    """
    import resource, sys
    import jax, jax.numpy as jnp
    jax.config.update("jax_enable_x64", True)
    import jaxquat as jq

    bodies = 100
    q0 = jq.normalize(jax.random.normal(jax.random.key(0), (bodies, 4)))
    w = jax.random.normal(jax.random.key(1), (bodies, 3))
    target = jq.normalize(jax.random.normal(jax.random.key(2), (bodies, 4)))

    def peak_after(steps):
        def loss(w):
            q = jq.integrate(q0, w, 1e-3, steps, save="final")
            return jnp.sum(1.0 - jnp.sum(q * target, -1) ** 2)
        g = jax.jit(jax.grad(loss))(w)
        assert bool(jnp.all(jnp.isfinite(g)))
        return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0

    small = peak_after(10_000)
    large = peak_after(100_000)
    print(small, large)
    """
)


def test_reverse_mode_memory_does_not_grow_with_num_steps():
    """Acceptance 5 (scaled down): grad of a final-orientation loss for 100 bodies over 10⁴ and then
    10⁵ steps. Storing every step would need ≥ 100·9·10⁴·32 B ≈ 290 MB more; the checkpointed nested
    scan must add < 40 MB. (The full 1,000 bodies × 10⁵ steps peaks at ~0.4 GB, see the report.)"""
    env = dict(os.environ, JAX_PLATFORMS="cpu")
    out = subprocess.run(
        [sys.executable, "-c", _MEMORY_SCRIPT], capture_output=True, text=True, env=env, check=True
    )
    small, large = map(float, out.stdout.split())
    assert large - small < 40.0, (small, large)


# ----------------------------------------------------------------------------------------------------
# Batching, tracing, dtype, saving.


def test_vmap_equals_loop_and_batches_broadcast(getkey):
    """Acceptance 6: vmap over bodies == a loop; q0 and ω batch shapes broadcast; saving every k-th."""
    q0 = random_unit(getkey(), (5,))
    w = jax.random.normal(getkey(), (5, 3))
    run = lambda q, w: jq.integrate(q, w, 0.1, 20, method="cf4")  # noqa: E731
    batched = jax.vmap(run, out_axes=1)(q0, w)
    looped = jnp.stack([run(q0[i], w[i]) for i in range(5)], axis=1)
    np.testing.assert_allclose(batched, looped, atol=1e-15)
    np.testing.assert_allclose(jq.integrate(q0, w, 0.1, 20, method="cf4"), looped, atol=1e-15)
    # One orientation, many angular velocities; and (2, 1) × (3,) batches.
    assert jq.integrate(q0[0], w, 0.1, 20).shape == (21, 5, 4)
    q_grid = random_unit(getkey(), (2, 1))
    w_grid = jax.random.normal(getkey(), (3, 3))
    out = jq.integrate(q_grid, w_grid, 0.1, 20, save="final")
    assert out.shape == (2, 3, 4)
    np.testing.assert_allclose(
        out[1, 2], jq.integrate(q_grid[1, 0], w_grid[2], 0.1, 20, save="final"), atol=1e-15
    )
    # A callable whose output batch is larger than q0's.
    out = jq.integrate(q0[0], lambda t, q: w * jnp.cos(t), 0.1, 20, save="final")
    assert out.shape == (5, 4)
    # save_every.
    every = jq.integrate(q0, w, 0.1, 20, save_every=5)
    assert every.shape == (5, 5, 4)
    # save="all" with a constant ω forms the products blockwise (r^i ⊗ r^(jK) ⊗ q₀, _fastpath), so the
    # two agree to round-off rather than bit for bit.
    np.testing.assert_allclose(
        np.asarray(every), np.asarray(jq.integrate(q0, w, 0.1, 20))[::5], rtol=0, atol=4e-15
    )


def test_compiles_once_per_shape():
    """Acceptance 6: repeated calls (eager or under jit) with new values but the same shapes do not
    retrace the angular-velocity callable."""
    traces = []

    def omega(t, q):
        traces.append(1)
        return jnp.stack([jnp.sin(t), jnp.cos(t), 0.5 * t])

    q0 = jq.identity()
    jq.integrate(q0, omega, 0.1, 10, method="cf4")
    first = len(traces)
    for dt, t0 in [(0.2, 1.0), (0.05, -3.0)]:
        jq.integrate(q0 * 1.0, omega, dt, 10, method="cf4", t0=t0)
    assert len(traces) == first
    jitted = jax.jit(lambda q, dt: jq.integrate(q, omega, dt, 10, method="cf4"))
    jitted(q0, 0.1)
    after_jit = len(traces)
    jitted(jq.from_rotvec(jnp.array([0.1, 0.2, 0.3])), 0.3)
    assert len(traces) == after_jit


def test_time_is_an_integer_step_count_times_dt():
    """ω(t) = t about a fixed axis under euler: the angle is Σ_k (t0 + kΔt)Δt exactly (closed form);
    an accumulated t += Δt would drift."""
    steps, dt, t0 = 20_000, 1e-3, 5.0
    q = jq.integrate(
        jq.identity(), lambda t, q: jnp.stack([t, 0.0 * t, 0.0 * t]), dt, steps, t0=t0, save="final"
    )
    total = steps * t0 * dt + dt * dt * steps * (steps - 1) / 2
    expected = jq.from_rotvec(jnp.array([total, 0.0, 0.0]))
    assert_quat_close(q, expected, atol=1e-12)


# ----------------------------------------------------------------------------------------------------
# Errors.


def test_bad_arguments_raise_value_errors_naming_them():
    """Acceptance 7."""
    q0, w = jq.identity(), jnp.ones(3)
    cases = [
        (dict(method="rk5"), "method"),
        (dict(frame="inertial"), "frame"),
        (dict(save="some"), "save"),
        (dict(save_every=3), "save_every"),
        (dict(save_every=0), "save_every"),
        (dict(compensated=True, method="rk4"), "compensated"),
    ]
    for kwargs, name in cases:
        with pytest.raises(ValueError, match=name):
            jq.integrate(q0, w, 0.1, 10, **kwargs)
    with pytest.raises(ValueError, match="omega"):
        jq.integrate(q0, jnp.ones(4), 0.1, 10)
    with pytest.raises(ValueError, match="omega"):
        jq.integrate(jq.identity((2,)), jnp.ones((3, 3)), 0.1, 10)
    with pytest.raises(ValueError, match="omega"):
        jq.integrate(q0, lambda t, q: jnp.ones(2), 0.1, 10)
    with pytest.raises(ValueError, match="omega"):  # magnus4 needs a q-independent ω
        jq.integrate(q0, lambda t, q: q[..., 1:] + t, 0.1, 10, method="magnus4")
    for method in ("magnus6", "magnus8"):
        with pytest.raises(ValueError, match=method):
            jq.integrate(q0, lambda t, q: q[..., 1:] + t, 0.1, 10, method=method)
    with pytest.raises(ValueError, match="q0"):
        jq.integrate(jnp.ones(3), w, 0.1, 10)
    with pytest.raises(ValueError, match="num_steps"):
        jq.integrate(q0, w, 0.1, 10.0)
    with pytest.raises(ValueError, match="dt"):
        jq.integrate(q0, w, jnp.ones(2), 10)
    with pytest.raises(ValueError, match="omegas"):
        jq.sampled(jnp.ones(3), 0.1)


@pytest.mark.parametrize(
    ("dt", "t0"),
    [(np.nan, 0.0), (np.inf, 0.0), (-np.inf, 0.0), (0.1, np.nan), (0.1, np.inf)],
)
def test_non_finite_dt_or_t0_is_a_value_error(dt, t0):
    """A NaN t0 with sampled ω once clipped to sample 0 and returned a plausible rotation (0.5 rad);
    a non-finite dt returned NaN. Every ω form: array, callable, samples."""
    name = "dt" if not np.isfinite(dt) else "t0"
    omegas = jnp.ones((10, 3))
    for omega in (jnp.ones(3), lambda t, q: jnp.ones(3) * t, jq.sampled(omegas, 0.1)):
        for method in ("euler", "midpoint"):
            with pytest.raises(ValueError, match=f"`{name}` must be finite"):
                jq.integrate(jq.identity(), omega, dt, 5, t0=t0, method=method, save="final")
    if name == "t0":
        with pytest.raises(ValueError, match="`t0`.*must be finite"):
            jq.sampled(omegas, 0.1, t0=t0)
        # Traced, nothing is checked (DESIGN: non-finite inputs propagate as NaN), but the samples'
        # lookup must not turn the NaN into a plausible rotation.
        for method in ("euler", "midpoint"):
            q = jax.jit(
                lambda t0, m=method: jq.integrate(
                    jq.identity(), jq.sampled(omegas, 0.1), 0.1, 5, t0=t0, method=m
                )
            )(t0)
            assert np.all(np.isnan(np.asarray(q[1:])))


@pytest.mark.parametrize("method", ["euler", "midpoint", "magnus4"])
@pytest.mark.parametrize("save_every", [1, 2])
def test_sampled_grid_is_one_rule_on_every_path(method, save_every, getkey):
    """A float32 Δt of 0.7 (0.699999988) against samples every float64 0.7: `integrate` counts the grids
    as one (within a few ulp of the coarser dtype), so step k holds sample k on every path — the
    Lie–Euler fast path once read sample k − 1 from step 1 on (1.04 rad off), and under `jit` with Δt
    traced every path did. Reference: SciPy's composition of the steps' rotations."""
    steps = 6
    omegas = jax.random.normal(getkey(), (steps, 3))
    samples = jq.sampled(omegas, 0.7)
    dt32 = np.float32(0.7)
    rotation = Rotation.identity()
    for k in range(steps):
        rotation = Rotation.from_rotvec(np.asarray(omegas[k]) * float(dt32)) * rotation
    expected = jq.from_xyzw(jnp.asarray(rotation.as_quat()))

    def run(dt):
        return jq.integrate(
            jq.identity(), samples, dt, steps, method=method, save="all", save_every=save_every
        )[-1]

    for q in (run(dt32), jax.jit(run)(dt32)):
        assert quat_distance(q, expected) <= 1e-6


def test_sampled_on_the_grid_equals_the_time_lookup(getkey):
    """Samples on the integration grid are scanned over as per-step inputs (cheap reverse mode); the
    result and its gradient equal the time lookup of `Sampled.__call__` (forced here by a traced dt),
    including CF4's end-of-step stage (next sample) and the held last sample."""
    steps, dt = 80, 0.05
    omegas = 3.0 * jax.random.normal(getkey(), (steps - 5, 2, 3))  # fewer samples: the last is held
    q0 = random_unit(getkey(), (2,))

    def loss(om, sample_dt):
        q = jq.integrate(q0, jq.sampled(om, sample_dt), dt, steps, method="cf4", save="final")
        return jnp.sum(q @ jnp.array([0.1, 0.4, -0.3, 0.2]))

    on_grid = jax.jit(jax.value_and_grad(lambda om: loss(om, dt)))(omegas)
    by_time = jax.jit(jax.value_and_grad(loss))(omegas, jnp.asarray(dt))
    np.testing.assert_allclose(on_grid[0], by_time[0], rtol=1e-13)
    np.testing.assert_allclose(on_grid[1], by_time[1], atol=1e-13)


@pytest.mark.parametrize("frame", ["world", "body"])
@pytest.mark.parametrize("renormalize_every", [None, 7, 30])
def test_sampled_euler_forward_and_derivatives_agree(renormalize_every, frame, getkey):
    """Sampled ω + euler, final state: evaluated it is one flat scan, differentiated it is a tangent
    scan (forward mode) or an adjoint stepping back with inverse rotations (reverse mode;
    _fastpath._sampled_final, more in test_sampled_derivatives.py). Values agree with the composition of exact
    step rotations; jacfwd, jacrev and central differences agree for the samples and q₀; the primal of
    jvp equals the plain evaluation."""
    steps, dt = 30, 0.07
    omegas = 2.0 * jax.random.normal(getkey(), (steps, 2, 3))
    q0 = random_unit(getkey(), (2,))

    def final(om, q, h):
        return jq.integrate(
            q,
            jq.sampled(om, dt),
            h,
            steps,
            save="final",
            frame=frame,
            renormalize_every=renormalize_every,
        )

    value = jax.jit(lambda om: final(om, q0, dt))(omegas)
    expected = q0
    for k in range(steps):
        step = jq.from_rotvec(omegas[k] * dt)
        expected = jq.multiply(step, expected) if frame == "world" else jq.multiply(expected, step)
    assert_quat_close(value, expected, atol=1e-14)
    primal, _ = jax.jvp(lambda om: final(om, q0, dt), (omegas,), (jnp.ones_like(omegas),))
    np.testing.assert_allclose(primal, value, atol=1e-15)

    fwd = jax.jit(jax.jacfwd(lambda om: final(om, q0, dt)))(omegas)
    rev = jax.jit(jax.jacrev(lambda om: final(om, q0, dt)))(omegas)
    np.testing.assert_allclose(fwd, rev, atol=1e-13)
    direction = jax.random.normal(getkey(), omegas.shape)
    eps = 1e-6
    fd = (final(omegas + eps * direction, q0, dt) - final(omegas - eps * direction, q0, dt)) / (
        2 * eps
    )
    np.testing.assert_allclose(jnp.tensordot(rev, direction, axes=3), fd, atol=1e-8)
    # q₀, in a tangential direction.
    tangent = jq.multiply(q0, jnp.array([0.0, 0.3, -0.2, 0.5]))
    _, dq = jax.jvp(lambda q: final(omegas, q, dt), (q0,), (tangent,))
    fd_q = (final(omegas, q0 + eps * tangent, dt) - final(omegas, q0 - eps * tangent, dt)) / (
        2 * eps
    )
    np.testing.assert_allclose(dq, fd_q, atol=1e-8)


@functools.partial(jax.jit, static_argnames=("frame", "renormalize_every"))
def _closed_form_and_general_derivatives(q0, w, dt, target, direction, *, frame, renormalize_every):
    """For `test_constant_omega_closed_form_derivative`, one compilation per (frame, renormalisation)
    for all its cases (the data are arguments): the fast path's value, jacfwd and jacrev w.r.t. q₀, ω
    and Δt, AD (jacrev) through the general scan given the same ω as a callable, and a loss's
    Hessian-vector product with its central difference."""
    steps, eps = 37, 1e-5

    def fast(q, w, h):
        return jq.integrate(
            q, w, h, steps, save="final", frame=frame, renormalize_every=renormalize_every
        )

    def general(q, w, h):
        return jq.integrate(
            q,
            lambda t, _: w * jnp.ones_like(t),
            h,
            steps,
            save="final",
            frame=frame,
            renormalize_every=renormalize_every,
        )

    args = (q0, w, dt)
    out = {"fast": fast(*args), "general": general(*args)}
    for argnum in range(3):
        out[f"reference{argnum}"] = jax.jacrev(general, argnums=argnum)(*args)
        out[f"jacfwd{argnum}"] = jax.jacfwd(fast, argnums=argnum)(*args)
        out[f"jacrev{argnum}"] = jax.jacrev(fast, argnums=argnum)(*args)

    def loss(w):
        return jnp.sum(jq.multiply(jq.conjugate(target), fast(q0, w, dt))[..., 1:] ** 2)

    out["hvp"] = jax.jvp(jax.grad(loss), (w,), (direction,))[1]
    out["fd"] = (jax.grad(loss)(w + eps * direction) - jax.grad(loss)(w - eps * direction)) / (
        2 * eps
    )
    return out


@pytest.mark.parametrize("frame", ["world", "body"])
@pytest.mark.parametrize("renormalize_every", [None, 7])
@pytest.mark.parametrize("case", ["random", "rest", "near_pi", "non_unit_q0"])
def test_constant_omega_closed_form_derivative(frame, renormalize_every, case, getkey):
    """Constant ω + euler, final state: the derivative is the closed form of d(r^T ⊗ q₀) (doubling sums
    of Ad_{r^m}, _fastpath._constant_final), not AD through the loop. jacfwd and jacrev w.r.t. q₀, ω
    and Δt equal AD through the general scan (the same ω given as a callable), at rest, with a step
    of nearly π, and for a non-unit q₀ with and without renormalisation. Second order goes through
    the rule too: the Hessian-vector product of a loss matches central differences."""
    dt = 0.1
    q0 = random_unit(getkey(), (2,)) * (1.7 if case == "non_unit_q0" else 1.0)
    w = jax.random.normal(getkey(), (2, 3))
    if case == "rest":
        w = jnp.zeros_like(w)
    if case == "near_pi":
        w = w / jnp.linalg.norm(w, axis=-1, keepdims=True) * (np.pi - 1e-3) / dt
    target = random_unit(getkey(), (2,))
    direction = jax.random.normal(getkey(), w.shape)
    out = _closed_form_and_general_derivatives(
        q0, w, jnp.asarray(dt), target, direction, frame=frame, renormalize_every=renormalize_every
    )
    np.testing.assert_allclose(out["fast"], out["general"], atol=1e-13)
    for argnum in range(3):
        reference = out[f"reference{argnum}"]
        np.testing.assert_allclose(out[f"jacfwd{argnum}"], reference, atol=1e-10)
        np.testing.assert_allclose(out[f"jacrev{argnum}"], reference, atol=1e-10)
    np.testing.assert_allclose(out["hvp"], out["fd"], atol=1e-6)
    # The eager call (no outer jit) takes the same path.
    if case == "random":
        eager = jq.integrate(
            q0, w, dt, 37, save="final", frame=frame, renormalize_every=renormalize_every
        )
        np.testing.assert_allclose(eager, out["fast"], atol=1e-13)


@pytest.mark.parametrize("frame", FRAMES)
def test_constant_omega_final_state_matches_scipy(frame):
    """Constant ω, final state (the powers r^k = a_k + b_k v stepped in the plane of 1 and v, then
    applied to q₀ once, _fastpath._constant_final): T = 1,000 steps equal SciPy's single rotation
    exp(T ω Δt) composed with q₀, for steps from 0 to near π, with and without renormalisation, and
    keep a non-unit q₀'s norm exactly when nothing renormalises."""
    steps, dt = 1000, 0.01
    rng = np.random.default_rng(7)
    q0 = rng.normal(size=(6, 4))
    q0 /= np.linalg.norm(q0, axis=-1, keepdims=True)
    w = rng.normal(size=(6, 3))
    w[0] = 0.0  # at rest
    w[1] = w[1] / np.linalg.norm(w[1]) * (np.pi - 1e-3) / dt  # nearly half a turn per step
    w[2] = w[2] / np.linalg.norm(w[2]) * 1e-7 / dt  # a tiny step
    rotation = Rotation.from_rotvec(w * dt * steps)
    start = Rotation.from_quat(q0[:, [1, 2, 3, 0]])
    expected = (rotation * start if frame == "world" else start * rotation).as_quat()
    expected = expected[:, [3, 0, 1, 2]]
    for renormalize_every in [None, 1, 7, 1000]:
        q = jq.integrate(
            q0, w, dt, steps, frame=frame, save="final", renormalize_every=renormalize_every
        )
        # Each step's rotation carries a round-off ~ε, so T steps drift by ~Tε (here ≲ 1e-13 rad).
        assert np.max(angle(q, expected)) <= 2e-13
        np.testing.assert_allclose(np.linalg.norm(q, axis=-1), 1.0, atol=2e-13)
    scaled = jq.integrate(2.5 * q0, w, dt, steps, frame=frame, save="final", renormalize_every=None)
    np.testing.assert_allclose(scaled, 2.5 * np.asarray(q), atol=1e-12)
    # A step count that is not a multiple of the unroll factor, and the shortest runs.
    for n in [1, 2, 3, 67]:
        rotation = Rotation.from_rotvec(w * dt * n)
        want = (rotation * start if frame == "world" else start * rotation).as_quat()
        want = want[:, [3, 0, 1, 2]]
        got = jq.integrate(q0, w, dt, n, frame=frame, save="final", renormalize_every=None)
        assert np.max(angle(got, want)) <= 1e-13


def test_constant_omega_derivative_float32_matches_float64(getkey):
    """The closed-form derivative in float32 stays within float32 round-off of the float64 one."""
    steps, dt = 200, 0.01
    q0 = random_unit(getkey(), (3,))
    w = 3.0 * jax.random.normal(getkey(), (3, 3))

    def final(q, w):
        return jq.integrate(q, w, dt, steps, save="final")

    j64 = jax.jacrev(final, argnums=1)(q0, w)
    j32 = jax.jacrev(final, argnums=1)(q0.astype(jnp.float32), w.astype(jnp.float32))
    assert j32.dtype == jnp.float32
    np.testing.assert_allclose(j32, j64, atol=2e-4 * float(jnp.max(jnp.abs(j64))))


@pytest.mark.parametrize("frame", ["world", "body"])
@pytest.mark.parametrize("renormalize_every", [None, 1, 4, 10, 11])
def test_constant_omega_trajectory_renormalises_like_stepping(frame, renormalize_every, getkey):
    """save="all" with a constant ω forms the trajectory blockwise (_fastpath._constant_trajectory);
    for a non-unit q₀ its rows and their gradients w.r.t. q₀ and ω equal stepping's (the general scan,
    the same ω as a callable), which renormalises after every `renormalize_every`-th step only."""
    steps, dt = 10, 0.2
    q0 = 1.7 * random_unit(getkey(), (2,))
    w = jax.random.normal(getkey(), (2, 3))
    weights = jax.random.normal(getkey(), (steps + 1, 2, 4))

    def run(q, w, callable_omega):
        omega = (lambda t, _: w * jnp.ones_like(t)) if callable_omega else w
        traj = jq.integrate(
            q, omega, dt, steps, save="all", frame=frame, renormalize_every=renormalize_every
        )
        return traj, jnp.sum(traj * weights)

    fast, _ = run(q0, w, False)
    general, _ = run(q0, w, True)
    np.testing.assert_allclose(fast, general, atol=1e-14)
    for argnum in range(2):
        grad_fast = jax.grad(lambda *a: run(*a, False)[1], argnums=argnum)(q0, w)
        grad_general = jax.grad(lambda *a: run(*a, True)[1], argnums=argnum)(q0, w)
        np.testing.assert_allclose(grad_fast, grad_general, atol=1e-13)


@pytest.mark.parametrize("frame", ["world", "body"])
@pytest.mark.parametrize("renormalize_every", [1000, None])
def test_uncompensated_float32_trajectory_of_a_slow_rotation_matches_the_closed_form(
    frame, renormalize_every
):
    """save="all", constant ω, float32 without compensation (the blockwise trajectory): 10⁴ steps of
    1e-6 rad stay within 1e-6 rad of the exact rotation by the float32 inputs at every saved row.
    Measured 1.4-1.7e-7; when the block rows Q_j were a 101-step scan of float32 quaternions, 7e-6."""
    rng = np.random.default_rng(3)
    steps, dt = 10_000, np.float32(1e-3)
    w = rng.normal(size=(64, 3))
    w = (w / np.linalg.norm(w, axis=1, keepdims=True) * 1e-3).astype(np.float32)
    q0 = rng.normal(size=(64, 4))
    q0 = (q0 / np.linalg.norm(q0, axis=1, keepdims=True)).astype(np.float32)
    traj = jq.integrate(
        jnp.asarray(q0),
        jnp.asarray(w),
        dt,
        steps,
        save="all",
        frame=frame,
        compensated=False,
        renormalize_every=renormalize_every,
    )
    assert traj.dtype == jnp.float32 and traj.shape == (steps + 1, 64, 4)
    rows = np.arange(0, steps + 1, 97)
    rotation = jq.from_rotvec(jnp.asarray(w.astype(np.float64) * float(dt) * rows[:, None, None]))
    start = jnp.asarray(q0.astype(np.float64))[None]
    exact = jq.multiply(rotation, start) if frame == "world" else jq.multiply(start, rotation)
    error = np.asarray(jq.angle_between(traj[rows].astype(jnp.float64), exact))
    assert error.max() <= 1e-6, error.max()


@pytest.mark.parametrize("method", ["euler", "midpoint", "cf4", "magnus4"])
@pytest.mark.parametrize("save", ["final", "all"])
@pytest.mark.parametrize("renormalize_every", [1000, None])
def test_a_zero_padded_body_leaves_the_other_bodies_gradients_finite(
    method, save, renormalize_every
):
    """A zero quaternion (a padded body) in the batch: the renormalisation select's unused branch
    q/|q| was NaN there, and its derivative times a zero cotangent made the gradient w.r.t. a shared
    ω NaN (even in a run too short to renormalise). The gradient must be that of the batch without
    the padded body, which is its closed form for constant ω: d q_T/dω of exp(ω t) ⊗ q₀. (A run that
    does renormalise turns a zero body into NaN, as documented: nothing is invented for q/|q|.)"""
    q_body = jnp.array([0.5, 0.5, 0.5, 0.5])
    padded = jnp.stack([q_body, jnp.zeros(4)])
    omega = jnp.array([0.3, -0.2, 0.5])
    dt, steps = 0.1, 10

    def loss(w, q0):  # the first body only (the padded one is masked out)
        qs = jq.integrate(
            q0, w, dt, steps, method=method, save=save, renormalize_every=renormalize_every
        )
        return jnp.sum(qs[..., 0, :] @ jnp.array([1.0, -2.0, 0.5, 3.0]))

    got = np.asarray(jax.grad(loss)(omega, padded))
    want = np.asarray(jax.grad(loss)(omega, q_body[None]))
    assert np.all(np.isfinite(got))
    np.testing.assert_allclose(got, want, rtol=1e-12, atol=1e-14)

    def exact(w):  # closed form of the same loss (constant ω: every method is exact up to rounding)
        times = dt * (jnp.arange(steps + 1) if save == "all" else jnp.array([steps]))
        qs = jax.vmap(lambda t: jq.multiply(jq.from_rotvec(w * t), q_body))(times)
        return jnp.sum(qs @ jnp.array([1.0, -2.0, 0.5, 3.0]))

    np.testing.assert_allclose(got, np.asarray(jax.grad(exact)(omega)), rtol=1e-9, atol=1e-12)


@pytest.mark.parametrize("frame", ["world", "body"])
def test_constant_euler_final_derivative_at_a_zero_initial_state(frame):
    """Without renormalisation q_T is linear in q₀ (r^T ⊗ q₀ or q₀ ⊗ r^T), so at q₀ = 0 its Jacobian is
    the multiplication matrix of r^T = exp(ω T Δt) (it was NaN: r^T was formed as q_T ⊗ q₀⁻¹)."""
    omega = jnp.array([0.3, -0.2, 0.5])
    dt, steps = 0.1, 10

    def f(q):
        return jq.integrate(q, omega, dt, steps, frame=frame, save="final", renormalize_every=None)

    power = np.asarray(jq.from_rotvec(omega * dt * steps))
    w, x, y, z = power
    left = np.array([[w, -x, -y, -z], [x, w, -z, y], [y, z, w, -x], [z, -y, x, w]])
    right = np.array([[w, -x, -y, -z], [x, w, z, -y], [y, -z, w, x], [z, y, -x, w]])
    want = left if frame == "world" else right
    for jacobian in (jax.jacfwd, jax.jacrev):
        np.testing.assert_allclose(np.asarray(jacobian(f)(jnp.zeros(4))), want, atol=1e-14)
    # A batch mixing a zero and a unit body: the unit body's Jacobian is unchanged.
    batch = jnp.stack([jnp.zeros(4), jnp.array([0.5, 0.5, 0.5, 0.5])])
    jac = np.asarray(jax.jacfwd(f)(batch))
    np.testing.assert_allclose(jac[0, :, 0], want, atol=1e-14)
    np.testing.assert_allclose(jac[1, :, 1], want, atol=1e-14)


@dataclasses.dataclass
class _DataclassSpin:  # eq=True sets __hash__ to None: it cannot be a static argument
    rate: float

    def __call__(self, t, q):
        return jnp.array([0.0, self.rate, 0.0])


class _NumpyAxisSpin(eqx.Module):  # a NumPy field the call uses with NumPy (not traceable)
    axis: np.ndarray

    def __call__(self, t, q):
        return jnp.asarray(np.asarray(self.axis) * np.float64(1.0))


class _ScalarSpin(eqx.Module):  # a NumPy scalar field (indexing a NumPy array gives one)
    rate: float

    def __call__(self, t, q):
        return jnp.array([0.0, 0.0, float(self.rate)])


class _ListSpin(eqx.Module):  # parameters kept in a list: ω(t) = sin(t) (w₀ + w₁)
    ws: list

    def __call__(self, t, q):
        return jnp.sin(t) * (self.ws[0] + self.ws[1])


class _ArraySpin(eqx.Module):
    w: jax.Array

    def __call__(self, t, q):
        return jnp.sin(t) * self.w


def _about_x(angle):
    return np.array([np.cos(angle / 2), np.sin(angle / 2), 0.0, 0.0])


@pytest.mark.parametrize("method", ["euler", "cf4"])
def test_callables_a_cache_cannot_hold_are_compiled_at_each_call(method):
    """A callable that does not hash (a dataclass with eq=True) once failed with JAX's "Non-hashable
    static arguments", and a Module calling NumPy on its NumPy field with a tracer conversion error:
    both now run, compiled for each call, with each call's values. Closed form: a constant ω about
    one axis for 1 s turns by |ω| (a rotation about y by a: (cos a/2, 0, sin a/2, 0)), exact for both
    methods."""
    q0 = jnp.array([1.0, 0.0, 0.0, 0.0])

    def final(omega):
        return jq.integrate(q0, omega, 0.01, 100, method=method, save="final")

    for rate in (0.4, -1.2):  # (y axis)
        expected = np.array([np.cos(rate / 2), 0.0, np.sin(rate / 2), 0.0])
        np.testing.assert_allclose(final(_DataclassSpin(rate)), expected, atol=1e-13)
    for axis in ([0.0, 0.0, 0.8], [0.0, 0.0, -2.5]):  # (z axis)
        angle = axis[2]
        expected = np.array([np.cos(angle / 2), 0.0, 0.0, np.sin(angle / 2)])
        np.testing.assert_allclose(final(_NumpyAxisSpin(np.array(axis))), expected, atol=1e-13)
    for rate in np.array([0.3, -1.1]):  # np.float64 fields, used with float() (traced, they failed)
        expected = np.array([np.cos(rate / 2), 0.0, 0.0, np.sin(rate / 2)])
        np.testing.assert_allclose(final(_ScalarSpin(rate)), expected, atol=1e-13)
    grad = jax.grad(lambda rate: final(_DataclassSpin(rate))[2])(0.6)  # d/da sin(a/2) = cos(a/2)/2
    np.testing.assert_allclose(grad, 0.5 * np.cos(0.3), rtol=1e-10)


def test_module_and_sampled_omega_compile_once():
    """New array values in an `equinox.Module` ω or in `jaxquat.sampled` data reuse the compiled run:
    no program is lowered on the repeat. The results follow the new values: ω(t) = sin(t)·w about a
    fixed axis turns by (1 − cos T)|w| (cf4's error at Δt = 0.01 is ~1e-10), sampled steps about x
    by Σ ω_k Δt."""
    q0 = jnp.array([1.0, 0.0, 0.0, 0.0])

    def spin(w):
        return jq.integrate(q0, _ArraySpin(jnp.asarray(w)), 0.01, 200, method="cf4", save="final")

    def held(samples):
        omega = jq.sampled(jnp.stack([samples, 0 * samples, 0 * samples], -1), 0.01)
        return jq.integrate(q0, omega, 0.01, 200, save="final")

    def listed(w):
        spin = _ListSpin([jnp.asarray(w), jnp.asarray(w)])  # (its arrays in a list)
        return jq.integrate(q0, spin, 0.01, 200, method="cf4", save="final")

    spin([1.0, 0.0, 0.0]), held(jnp.ones(200)), listed([1.0, 0.0, 0.0])  # compiled here
    rates = jnp.linspace(-1.0, 2.0, 200)
    with count_lowerings() as lowered:
        turned = spin([1.5, 0.0, 0.0])
        sampled_turn = held(rates)
        listed_turn = listed([0.25, 0.0, 0.0])
    assert lowered == [], f"{len(lowered)} programs compiled again"
    np.testing.assert_allclose(turned, _about_x(1.5 * (1 - np.cos(2.0))), atol=1e-9)
    np.testing.assert_allclose(listed_turn, _about_x(0.5 * (1 - np.cos(2.0))), atol=1e-9)
    np.testing.assert_allclose(sampled_turn, _about_x(float(jnp.sum(rates)) * 0.01), atol=1e-13)
