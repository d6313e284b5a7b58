"""Scale: results that do not depend on an input's scale (or scale with it) must not depend on
how far that scale is from 1, in float32 and float64, nor must their gradients (helper-52 and
helper-53 found intermediates such as |q|²·|v|, |ω|²·dt², (Iω) × ω, Σ mᵢxᵢ and an eigenvector
solve's deflation term leaving the dtype's range while the true result was ordinary)."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from helpers import quat_distance
from scipy.spatial.transform import Rotation

import jaxquat as jq


def f32(x):
    return jnp.asarray(x, jnp.float32)


@pytest.mark.parametrize(
    "v, q, expected",
    [
        ([1e30, 0, 0], [1e5, 0, 0, 1e5], [0, 1e30, 0]),  # a quarter turn about z, |q|²|v| = 2e40
        ([1e-30, 0, 0], [1e-5, 0, 1e-5, 0], [0, 0, -1e-30]),  # about y, |q|²|v| = 2e-40
    ],
)
def test_rotate_by_a_non_unit_q_at_any_scale(v, q, expected):
    out = jq.rotate(f32(v), f32(q))
    np.testing.assert_allclose(out, expected, rtol=0, atol=1e-6 * np.max(np.abs(v)))


@pytest.mark.parametrize("scale", [3e19, 1e-19])
def test_corrected_rate_depends_on_omega_dt_only(scale):
    """q̇_Δt(sω, Δt/s) = s q̇_Δt(ω, Δt): θ = |ω|Δt is the same; |ω|² alone left float32's range."""
    q = np.array([0.5, 0.5, -0.5, 0.5])
    omega, dt = np.array([1.2, -0.4, 0.6]), 0.7
    expected = scale * np.asarray(jq.corrected_rate(q, omega, dt))
    out = jq.corrected_rate(f32(q), f32(scale * omega), f32(dt / scale))
    np.testing.assert_allclose(out, expected, rtol=2e-6, atol=0)
    theta = np.linalg.norm(omega) * dt  # the seed's closed form for q = 1: tan(θ/2)/θ · (0, ω)
    np.testing.assert_allclose(
        jq.corrected_rate([1.0, 0, 0, 0], omega, dt)[1:],
        np.tan(theta / 2) / (theta * dt) * omega * dt,
    )


@pytest.mark.parametrize("method", ["magnus4", "magnus6", "magnus8", "cf4", "euler"])
def test_integrate_with_huge_omega_and_tiny_step(method):
    """One step of a constant ω is the rotation by ωΔt whatever the split between ω and Δt. ω is
    an argument of the callable (time-dependent through `t`), not a constant XLA may fold: with
    a constant, XLA rewrites |hω|² as h²·|ω|², and euler/midpoint give NaN at 1e20 in float32."""
    omega = np.array([0.6, 0.0, 0.8])
    expected = Rotation.from_rotvec(omega).as_quat()[[3, 0, 1, 2]]
    for dtype, scale in ((jnp.float32, 1e20), (jnp.float64, 1e154)):
        rates = jnp.asarray(scale * omega, dtype)
        for field in (rates, lambda t, q, w=rates: w + 0 * t):
            out = jq.integrate(
                jnp.asarray([1.0, 0, 0, 0], dtype),
                field,
                jnp.asarray(1 / scale, dtype),
                1,
                method=method,
            )
            assert quat_distance(out[-1], expected) < 1e-6, (method, dtype)


def test_euler_equations_of_a_float32_nanoparticle():
    """I ≈ 1e-32 kg m², |ω| ≈ 1e-3 rad/s: (Iω) × ω ≈ 1e-38 is below float32's normal range."""
    inertia = np.array([[1.0, 0.1, 0.0], [0.1, 2.0, 0.0], [0.0, 0.0, 2.5]])
    omega = np.array([1e-3, 2e-3, -1e-3])
    expected = np.linalg.solve(inertia, np.cross(inertia @ omega, omega))
    for moments in (inertia, np.diag(inertia)):
        mine = moments if moments.ndim == 2 else moments
        rhs = jq.euler_equations(f32(omega), f32(1e-32 * mine))
        reference = expected if moments.ndim == 2 else np_principal(moments, omega)
        np.testing.assert_allclose(rhs, reference, rtol=1e-5)
    qs, omegas = jq.simulate_rigid_body(
        f32([1.0, 0, 0, 0]), f32(omega), f32(1e-32 * inertia), 10.0, 200, save_every=200
    )
    q_ref, w_ref = jq.simulate_rigid_body(
        np.array([1.0, 0, 0, 0]), omega, inertia, 10.0, 200, save_every=200
    )
    assert quat_distance(qs[-1], q_ref[-1]) < 1e-4
    np.testing.assert_allclose(omegas[-1], w_ref[-1], rtol=1e-4)


def np_principal(moments, omega):
    i1, i2, i3 = moments
    w1, w2, w3 = omega
    return np.array([(i2 - i3) * w2 * w3 / i1, (i3 - i1) * w3 * w1 / i2, (i1 - i2) * w1 * w2 / i3])


@pytest.mark.parametrize("scale", [1e20, 1e-20])
def test_center_of_mass_and_inertia_at_any_scale(scale):
    masses = np.array([1.0, 3.0, 2.0])
    points = np.array([[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.5, -0.5, 2.0]])
    centre = masses @ points / masses.sum()
    np.testing.assert_allclose(
        jq.center_of_mass(f32(scale * masses), f32(scale * points)), scale * centre, rtol=1e-6
    )
    # I ∝ m r²: masses 1e20 at 1e-20 (|r|² underflows float32) and 1e-20 at 1e20 (overflows).
    relative = points - centre
    expected = sum(
        m * (r @ r * np.eye(3) - np.outer(r, r)) for m, r in zip(masses, relative, strict=True)
    )
    out = jq.inertia_tensor(f32(scale * masses), f32(points / scale))
    np.testing.assert_allclose(
        out, expected / scale, rtol=1e-5, atol=1e-6 * np.max(expected) / scale
    )


def test_principal_axes_gradient_for_a_space_station_in_float32():
    """A 1e8 kg m² inertia: JAX's eigh derivative rounded 1 + λⱼ − λᵢ to 0 and gave NaN."""
    inertia = np.diag([1.1e8, 1.3e8, 2.0e8]) + np.array(
        [[0, 1e6, 2e6], [1e6, 0, -3e6], [2e6, -3e6, 0]]
    )

    def first(i):
        moments, q = jq.principal_axes(i)
        return q[0] + moments[1] * 1e-8

    expected = jax.grad(first)(inertia)
    out = jax.grad(first)(f32(inertia))
    np.testing.assert_allclose(out, expected, rtol=2e-3, atol=2e-3 * np.max(np.abs(expected)))


@pytest.mark.parametrize(
    "dtype, scales", [(jnp.float32, (1e5, 1e-10)), (jnp.float64, (1e16, 1e-60))]
)
def test_mean_gradient_does_not_depend_on_the_weights_scale(dtype, scales):
    """The weighted mean is invariant under w → sw, so its gradient w.r.t. w scales as 1/s (weights
    of 1/σ² for σ ≈ 3 mrad are about 1e5)."""
    q = np.asarray(
        Rotation.from_rotvec(
            [[0.1, 0.2, 0.0], [0.0, -0.3, 0.1], [0.2, 0.0, -0.1], [0.05, 0.1, 0.3]]
        ).as_quat()[:, [3, 0, 1, 2]]
    )
    weights = np.array([1.0, 2.0, 0.5, 1.5])

    def loss(w):
        return jnp.sum(
            jq.mean(jnp.asarray(q, w.dtype), w) * jnp.asarray([0.3, 1.0, -0.7, 0.2], w.dtype)
        )

    expected = jax.grad(loss)(weights)  # float64 at scale 1; checked against differences below
    step = 1e-6
    central = [
        (loss(weights + step * e) - loss(weights - step * e)) / (2 * step) for e in np.eye(4)
    ]
    np.testing.assert_allclose(expected, central, rtol=1e-6, atol=1e-9)
    for scale in scales:
        out = jax.grad(loss)(jnp.asarray(scale * weights, dtype))
        _assert_gradient_scales(out, scale, expected)


@pytest.mark.parametrize("dtype, scale", [(jnp.float32, 1e-9), (jnp.float64, 1e-20)])
def test_from_matrix_gradient_of_a_scaled_rotation(dtype, scale):
    rotation = Rotation.from_rotvec([0.3, -0.2, 0.5]).as_matrix()
    pick = jnp.asarray([0.2, -1.0, 0.4, 0.7])

    def loss(m):
        return jnp.sum(jq.from_matrix(m) * pick.astype(m.dtype))

    expected = jax.grad(loss)(rotation)
    out = jax.grad(loss)(jnp.asarray(scale * rotation, dtype))
    _assert_gradient_scales(out, scale, expected)


@pytest.mark.parametrize("scale", [1e30, 1e-30])
def test_euler_equations_with_torque_scale_with_the_inertia(scale):
    """ω̇ = I⁻¹(τ + (Iω) × ω) is unchanged when I and τ are scaled together (τ is scaled by the
    same power of two as I inside)."""
    omega, torque = np.array([0.3, -1.2, 0.5]), np.array([0.7, 0.1, -0.4])
    inertia = np.array([[2.0, 0.1, 0.0], [0.1, 3.0, 0.2], [0.0, 0.2, 4.0]])
    for moments in (inertia, np.diag(inertia)):
        expected = jq.euler_equations(omega, moments, torque)
        out = jq.euler_equations(f32(omega), f32(scale * moments), f32(scale * torque))
        np.testing.assert_allclose(out, expected, rtol=2e-5, atol=1e-6)


def _assert_gradient_scales(out, scale, expected):
    """The gradient at an input scaled by s is the unscaled one over s (float32: to 1e-3)."""
    single = out.dtype == jnp.float32
    np.testing.assert_allclose(
        scale * np.asarray(out, np.float64),
        expected,
        rtol=1e-3 if single else 1e-8,
        atol=1e-4 if single else 1e-10,
    )
