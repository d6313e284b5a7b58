"""Mathematics of the kinematics: the seed's corrected rate, the exact step, and its inverse.

References used: the seed's equation evaluated directly with numpy-quaternion's Hamilton product,
SciPy's `Rotation` for composition, and closed forms computed in extended precision (longdouble).
"""

import jax
import jax.numpy as jnp
import mpmath
import numpy as np
import pytest
import quaternion as npq
from helpers import assert_quat_close, central_jacobian, random_unit
from scipy.spatial.transform import Rotation

import jaxquat as jq

FRAMES = ["world", "body"]


def _unit_vectors(key, n):
    v = np.asarray(jax.random.normal(key, (n, 3)))
    return v / np.linalg.norm(v, axis=-1, keepdims=True)


def _angles_below_pi():
    """Step angles θ = |ω|Δt in (0, π): tiny (series branch), moderate, and up to 1e-8 below π."""
    return np.concatenate(
        [
            [0.0, 1e-12, 1e-8, 1e-5, 1e-3, 0.03],
            np.linspace(0.1, 3.1, 16),
            np.pi - np.logspace(-1, -8, 8),
        ]
    )


def _seed_corrected_rate(q, omega, dt, frame):
    """The seed's equation, evaluated directly: tan(|ω|Δt/2)/(|ω|Δt) · ω̃ q (or q ω̃ in the body frame)."""
    out = np.empty_like(q)
    for i in range(q.shape[0]):
        theta = np.linalg.norm(omega[i]) * dt
        qq = npq.quaternion(*q[i])
        wq = npq.quaternion(0.0, *omega[i])
        prod = wq * qq if frame == "world" else qq * wq
        out[i] = np.tan(theta / 2) / theta * npq.as_float_array(prod)
    return out


@pytest.mark.parametrize("frame", FRAMES)
def test_step_is_the_renormalised_corrected_euler_step(frame, getkey):
    """Acceptance 1a: normalize(q + Δt q̇_Δt) == step(q, ω, Δt) to 1e-15 for every θ < π."""
    theta = _angles_below_pi()
    n = theta.shape[0]
    q = random_unit(getkey(), (n,))
    axis = _unit_vectors(getkey(), n)
    dt = 0.37
    omega = jnp.asarray(axis * (theta / dt)[:, None])
    euler = jq.normalize(q + dt * jq.corrected_rate(q, omega, dt, frame=frame))
    exact = jq.step(q, omega, dt, frame=frame)
    err = np.max(np.abs(np.asarray(euler - exact)))  # same sheet: no sign freedom allowed
    assert err <= 1e-15, err


@pytest.mark.parametrize("frame", FRAMES)
def test_corrected_euler_past_half_a_turn_flips_the_sheet(frame, getkey):
    """NUMERICS.md §1: the renormalised tan step is sgn(cos(θ/2))·exp(ωΔt)⊗q — same rotation."""
    theta = np.array([3.3, 4.0, 5.5, 6.0, 7.0, 8.5, 10.0])  # away from the poles θ = π, 3π
    q = random_unit(getkey(), theta.shape)
    omega = jnp.asarray(_unit_vectors(getkey(), theta.shape[0]) * theta[:, None])
    euler = jq.normalize(q + jq.corrected_rate(q, omega, 1.0, frame=frame))
    exact = jq.step(q, omega, 1.0, frame=frame)
    sign = np.sign(np.cos(theta / 2))[:, None]
    np.testing.assert_allclose(np.asarray(euler), sign * np.asarray(exact), atol=1e-14)


@pytest.mark.parametrize("frame", FRAMES)
def test_step_equals_closed_form_exp_within_10_ulp(frame, getkey):
    """Acceptance 1b: step == (cos(θ/2), sin(θ/2) n̂) ⊗ q (world) in extended precision, ≤ 10 ulp, θ ≤ 10."""
    theta = np.concatenate([[0.0, 1e-9, 1e-4, 0.02, 0.05], np.linspace(0.1, 10.0, 60)])
    n = theta.shape[0]
    q = np.asarray(random_unit(getkey(), (n,)))
    omega = _unit_vectors(getkey(), n) * (theta / 0.3)[:, None]
    dt = 0.3
    got = np.asarray(jq.step(q, omega, dt, frame=frame))

    ld = np.longdouble
    rotvec = omega.astype(ld) * ld(dt)
    angle = np.sqrt(np.sum(rotvec * rotvec, axis=-1))
    safe = np.where(angle > 0, angle, ld(1))
    scale = np.where(angle > 0, np.sin(angle / 2) / safe, ld(0.5))
    r = np.concatenate([np.cos(angle / 2)[:, None], scale[:, None] * rotvec], axis=-1)
    ql = q.astype(ld)
    ref = _ld_multiply(r, ql) if frame == "world" else _ld_multiply(ql, r)
    ulp = np.spacing(1.0)
    err = np.max(np.abs(got.astype(ld) - ref)) / ulp
    assert err <= 10, err


def _ld_multiply(p, q):
    pw, px, py, pz = (p[..., i] for i in range(4))
    qw, qx, qy, qz = (q[..., i] for i in range(4))
    return np.stack(
        [
            pw * qw - px * qx - py * qy - pz * qz,
            pw * qx + px * qw + py * qz - pz * qy,
            pw * qy - px * qz + py * qw + pz * qx,
            pw * qz + px * qy - py * qx + pz * qw,
        ],
        axis=-1,
    )


@pytest.mark.parametrize("frame", FRAMES)
def test_corrected_rate_matches_the_seed_formula(frame, getkey):
    """Acceptance 1c: corrected_rate == tan(θ/2)/θ · ω̃q evaluated directly, 1e-14 relative, off the poles."""
    theta = np.concatenate([np.logspace(-7, -1, 7), np.linspace(0.2, 9.0, 45)])
    theta = theta[
        np.abs(((theta - np.pi) / (2 * np.pi)) - np.round((theta - np.pi) / (2 * np.pi))) > 0.02
    ]
    n = theta.shape[0]
    q = np.asarray(random_unit(getkey(), (n,)))
    dt = 0.7
    omega = _unit_vectors(getkey(), n) * (theta / dt)[:, None]
    got = np.asarray(jq.corrected_rate(q, omega, dt, frame=frame))
    ref = _seed_corrected_rate(q, omega, dt, frame)
    rel = np.linalg.norm(got - ref, axis=-1) / np.linalg.norm(ref, axis=-1)
    assert np.max(rel) <= 1e-14, np.max(rel)


def test_corrected_rate_value_at_the_pole_is_finite_and_huge():
    """The docstring's promise at θ = π: the floating-point tan is returned (finite, ~1e16·ω̃q)."""
    q = jnp.array([1.0, 0.0, 0.0, 0.0])
    out = jq.corrected_rate(q, jnp.array([jnp.pi, 0.0, 0.0]), 1.0)
    assert np.all(np.isfinite(np.asarray(out)))
    assert abs(float(out[1])) > 1e15


@pytest.mark.parametrize("frame", FRAMES)
def test_corrected_rate_and_step_gradients_at_rest(frame, getkey):
    """At ω = 0: corrected_rate is ½ω̃q with the same Jacobian; step's Jacobian is ½Δt·[0; I₃]·q."""
    q = random_unit(getkey())
    dt = 0.25
    zero = jnp.zeros(3)
    basis = jnp.concatenate([jnp.zeros((3, 1)), jnp.eye(3)], axis=-1)  # pure quaternions e₁, e₂, e₃
    if frame == "world":
        columns = jq.multiply(basis, q)
    else:
        columns = jq.multiply(q, basis)
    expected_rate = 0.5 * np.asarray(columns).T  # (4, 3)
    for fn, scale in [
        (lambda w: jq.corrected_rate(q, w, dt, frame=frame), 1.0),
        (lambda w: jq.step(q, w, dt, frame=frame), dt),
    ]:
        fn = jax.jit(fn)
        for jac in (jax.jit(jax.jacfwd(fn))(zero), jax.jit(jax.jacrev(fn))(zero)):
            np.testing.assert_allclose(np.asarray(jac), scale * expected_rate, rtol=0, atol=1e-15)
        fd = central_jacobian(
            lambda w, fn=fn: np.asarray(fn(jnp.asarray(w))), np.zeros(3), eps=1e-5
        )
        np.testing.assert_allclose(fd, scale * expected_rate, rtol=0, atol=1e-9)


def test_step_agrees_with_scipy_composition(getkey):
    """World step = R(ωΔt)·R(q); body step = R(q)·R(ωΔt) (SciPy composes right factor first)."""
    n = 32
    q = random_unit(getkey(), (n,))
    omega = 3.0 * jax.random.normal(getkey(), (n, 3))
    dt = 0.4
    rq = Rotation.from_quat(np.asarray(jq.to_xyzw(q)))
    rw = Rotation.from_rotvec(np.asarray(omega) * dt)
    assert_quat_close(jq.step(q, omega, dt), jq.from_xyzw((rw * rq).as_quat()), atol=1e-14)
    assert_quat_close(
        jq.step(q, omega, dt, frame="body"), jq.from_xyzw((rq * rw).as_quat()), atol=1e-14
    )


def test_world_and_body_rates_describe_the_same_motion(getkey):
    """½ω̃q = ½q ω̃_b with ω_b = R(q)ᵀω, and q̇ is tangent to the sphere (q·q̇ = 0)."""
    q = random_unit(getkey(), (16,))
    omega = jax.random.normal(getkey(), (16, 3))
    body = jq.rotate(omega, jq.conjugate(q))
    world_rate = jq.rate(q, omega)
    np.testing.assert_allclose(world_rate, jq.rate(q, body, frame="body"), atol=1e-15)
    np.testing.assert_allclose(np.sum(np.asarray(world_rate * q), -1), 0.0, atol=1e-15)
    np.testing.assert_allclose(
        jq.step(q, omega, 0.9), jq.step(q, body, 0.9, frame="body"), atol=1e-14
    )


@pytest.mark.parametrize("frame", FRAMES)
def test_angular_velocity_inverts_step(frame, getkey):
    """angular_velocity recovers the piecewise-constant ω of a stepped trajectory (θ < π), ignoring signs."""
    steps, batch = 40, (3,)
    dts = 0.05 + 0.1 * jax.random.uniform(getkey(), (steps,))
    omega = jax.random.normal(getkey(), (steps, *batch, 3)) * 4.0
    omega = omega.at[5].set(0.0)  # a step at rest
    q = random_unit(getkey(), batch)
    step = jax.jit(lambda q, w, dt: jq.step(q, w, dt, frame=frame))
    qs = [q]
    for k in range(steps):
        q = step(q, omega[k], dts[k])
        qs.append(q)
    qs = jnp.stack(qs)
    assert float(jnp.max(jnp.linalg.norm(omega, axis=-1) * dts[:, None])) < np.pi
    flips = jnp.where(jax.random.bernoulli(getkey(), 0.5, qs.shape[:-1]), -1.0, 1.0)[..., None]
    recovered = jq.angular_velocity(qs * flips, dts, frame=frame)
    assert recovered.shape == omega.shape
    np.testing.assert_allclose(np.asarray(recovered), np.asarray(omega), rtol=0, atol=1e-12)
    # The same with a scalar dt.
    qs_uniform = jq.integrate(qs[0], jq.sampled(omega, 0.1), 0.1, steps, frame=frame)
    np.testing.assert_allclose(
        np.asarray(jq.angular_velocity(qs_uniform, 0.1, frame=frame)), np.asarray(omega), atol=1e-12
    )


def test_angular_velocity_gradient_is_finite_at_rest():
    """A constant trajectory has ω = 0 and a finite, correct gradient (d ω/d q₁ = 2/Δt [0 | I₃] q₀*)."""
    qs = jnp.stack([jq.identity(), jq.identity()])
    jac = jax.jit(jax.jacfwd(lambda qs: jq.angular_velocity(qs, 0.5)))(qs)
    expected = np.zeros((1, 3, 2, 4))
    expected[0, :, 1, 1:] = 4.0 * np.eye(3)
    expected[0, :, 0, 1:] = -4.0 * np.eye(3)
    np.testing.assert_allclose(np.asarray(jac), expected, atol=1e-15)


def test_float32_in_float32_out_and_accurate():
    """float32 inputs stay float32, and the step is accurate to float32 round-off (also near rest)."""
    q = jnp.asarray([0.5, 0.5, -0.5, 0.5], jnp.float32)
    for theta in [0.0, 1e-4, 0.3, 3.0]:
        omega = jnp.asarray([theta, 0.0, 0.0], jnp.float32)
        out = jq.step(q, omega, jnp.float32(1.0))
        rate = jq.corrected_rate(q, omega, jnp.float32(1.0))
        assert out.dtype == jnp.float32 and rate.dtype == jnp.float32
        ref = jq.step(q.astype(jnp.float64), omega.astype(jnp.float64), 1.0)
        assert_quat_close(out, ref, atol=3e-7)
        jac = jax.jacfwd(lambda w: jq.step(q, w, jnp.float32(1.0)))(omega)
        assert jac.dtype == jnp.float32 and bool(jnp.all(jnp.isfinite(jac)))


@pytest.mark.parametrize("dtype, rtol", [(jnp.float32, 2e-6), (jnp.float64, 2e-13)])
def test_corrected_rate_dt_derivative_against_mpmath(dtype, rtol):
    """∂/∂Δt of tan(θ/2)/θ·ω̃q is the factor's derivative alone, whose direct form cancels
    (relative error ~6ε/θ²): it was 7e-5 (float32) / 1.4e-12 (float64) wrong just past the
    series switch (helper-62)."""
    axis = np.array([0.3, -0.5, 0.8]) / np.linalg.norm([0.3, -0.5, 0.8])
    q = jnp.asarray([1.0, 0.0, 0.0, 0.0], dtype)
    dt = 0.7
    with mpmath.workdps(50):
        _check_corrected_rate_dt_derivative(axis, q, dt, dtype, rtol)


def _check_corrected_rate_dt_derivative(axis, q, dt, dtype, rtol):
    for theta in [1e-3, 0.02, 0.035, 0.05, 0.1, 0.2, 0.5, 0.7, 0.75, 1.0, 2.0, 3.0]:
        omega = jnp.asarray(axis * theta / dt, dtype)
        d = jnp.asarray(dt, dtype)
        w64 = np.asarray(omega, np.float64)
        size = mpmath.sqrt(sum(mpmath.mpf(float(x)) ** 2 for x in w64))
        slope = mpmath.diff(
            lambda s, size=size: mpmath.tan(size * s / 2) / (size * s), mpmath.mpf(float(d))
        )
        ref = np.array([0.0] + [float(slope * mpmath.mpf(float(x))) for x in w64])
        f = lambda s, omega=omega: jq.corrected_rate(q, omega, s)  # noqa: E731
        for jac in (jax.jacfwd, jax.jacrev):
            got = np.asarray(jac(f)(d), np.float64)
            err = np.max(np.abs(got - ref)) / np.max(np.abs(ref))
            assert err < rtol, (theta, jac.__name__, err)
