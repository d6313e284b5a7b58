"""Regressions for defects found in review: dtype preservation, argument-naming errors, float32 gimbal lock."""

import warnings

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from scipy.spatial.transform import Rotation

import jaxquat as jq


def test_rigid_body_keeps_float32_with_list_inertia():
    q0 = jnp.array([1.0, 0.0, 0.0, 0.0], jnp.float32)
    omega0 = jnp.array([0.1, 0.2, 0.3], jnp.float32)
    qs, omegas = jq.simulate_rigid_body(q0, omega0, [1.0, 2.0, 3.5], 0.01, 3)
    assert qs.dtype == jnp.float32 and omegas.dtype == jnp.float32


def test_deformable_body_keeps_float32_with_list_masses():
    base = jnp.array([[1.0, 0.0, 0.0], [-1.0, 0.0, 0.0], [0.0, 1.0, 0.0]], jnp.float32)

    def positions(t):
        return base * (1.0 + 0.1 * jnp.sin(t))

    q0 = jnp.array([1.0, 0.0, 0.0, 0.0], jnp.float32)
    qs, world = jq.simulate_deformable_body([1.0, 2.0, 3.0], positions, q0, 0.01, 3)
    assert qs.dtype == jnp.float32 and world.dtype == jnp.float32


@pytest.mark.parametrize(
    "call, names",
    [
        (lambda: jq.multiply(jnp.ones((2, 4)), jnp.ones((3, 4))), ("`p`", "`q`")),
        (lambda: jq.rotate(jnp.ones((2, 3)), jnp.ones((3, 4))), ("`v`", "`q`")),
        (lambda: jq.step(jnp.ones((2, 4)), jnp.ones((3, 3)), 0.1), ("`q`", "`omega`")),
        (
            lambda: jq.integrate(jnp.ones((2, 4)), jq.sampled(jnp.ones((3, 3, 3)), 0.1), 0.1, 3),
            ("`omegas`", "`q0`"),
        ),
    ],
)
def test_batch_mismatch_errors_name_the_arguments(call, names):
    with pytest.raises(ValueError) as info:
        call()
    for name in names:
        assert name in str(info.value)


def test_angular_velocity_reports_the_dt_shape_given():
    with pytest.raises(ValueError, match=r"got \(3,\)\.$"):
        jq.angular_velocity(jnp.ones((5, 2, 4)), jnp.ones(3))


def test_angular_velocity_of_a_non_finite_dt_is_nan():
    """ω = rotation/Δt: an infinite Δt gave a plausible ω = 0, silently (a review). Non-finite Δt now
    propagate as NaN, per sample for an array Δt, as bad values do in every math function (DESIGN);
    a zero Δt gives non-finite values, and a negative Δt is a backward trajectory, still valid."""
    qs = jq.integrate(jq.identity(), jnp.array([0.0, 0.0, 1.0]), 0.1, 4)
    for dt in [np.inf, -np.inf, np.nan]:
        assert np.all(np.isnan(jq.angular_velocity(qs, dt)))
    omega = np.asarray(jq.angular_velocity(qs, jnp.array([0.1, 0.1, np.inf, 0.1])))
    assert np.all(np.isnan(omega[2])) and np.all(np.isfinite(omega[[0, 1, 3]]))
    np.testing.assert_allclose(omega[[0, 1, 3]], np.tile([0.0, 0.0, 1.0], (3, 1)), atol=1e-6)
    assert not np.any(np.isfinite(jq.angular_velocity(qs, 0.0)[:, 2]))
    np.testing.assert_allclose(
        jq.angular_velocity(qs, -0.1), np.tile([0.0, 0.0, -1.0], (4, 1)), atol=1e-6
    )
    # The derivative in Δt where it is finite: −ω/Δt.
    d = jax.jacfwd(lambda dt: jq.angular_velocity(qs, dt))(0.1)
    np.testing.assert_allclose(d, np.tile([0.0, 0.0, -10.0], (4, 1)), rtol=1e-5)


@pytest.mark.parametrize("seq", ["zxz", "ZXZ", "xyx", "YZY"])
def test_float32_gimbal_lock_at_pi_follows_scipys_rule(seq):
    angles = np.array([0.3, np.pi, 0.7])
    q = jq.from_euler(seq, jnp.asarray(angles, jnp.float32))
    got = np.asarray(jq.to_euler(q, seq), np.float64)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", UserWarning)  # SciPy warns that the lock was detected
        expected = Rotation.from_euler(seq, angles).as_euler(seq)
    # SciPy's rule at a lock: the third angle is set to 0 and the first carries the whole turn.
    assert got[2] == 0.0 and expected[2] == 0.0
    assert abs(np.angle(np.exp(1j * (got[0] - expected[0])))) < 1e-5
    roundtrip = jq.from_euler(seq, got)
    assert jq.angle_between(roundtrip, jnp.asarray(q, jnp.float64)) < 1e-6
