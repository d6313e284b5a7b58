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


@pytest.mark.parametrize("dtype, angle", [(jnp.float32, 1e-20), (jnp.float64, 1e-160)])
def test_tiny_rotations_keep_their_angle_and_axis(dtype, angle):
    """A rotation so small that |vec q|² underflows beside w = 1 (below ~2e-19 rad in float32,
    ~3e-154 in float64) still has its angle and axis: `to_axis_angle` gave angle 0 with the default
    axis (1, 0, 0), `angle_between` 0 (its docstring promises round-off accuracy for tiny angles).
    `to_rotvec` gives the reference; the closed form is the axis-angle the rotation was made from."""
    axis = jnp.array([0.0, 0.6, 0.8], dtype)
    q = jq.from_axis_angle(axis, jnp.asarray(angle, dtype))
    for fn in (lambda q: jq.to_axis_angle(q), jax.jit(jq.to_axis_angle)):
        got_axis, got_angle = fn(q)
        np.testing.assert_allclose(got_angle, angle, rtol=4 * np.finfo(dtype).eps)
        np.testing.assert_allclose(got_axis, axis, rtol=0, atol=4 * np.finfo(dtype).eps)
    identity = jq.identity((), dtype)
    for fn in (jq.angle_between, jax.jit(jq.angle_between)):
        np.testing.assert_allclose(fn(identity, q), angle, rtol=4 * np.finfo(dtype).eps)
        np.testing.assert_allclose(fn(q, identity), angle, rtol=4 * np.finfo(dtype).eps)
    np.testing.assert_allclose(
        jq.to_rotvec(q), angle * np.asarray(axis), rtol=4 * np.finfo(dtype).eps
    )
    # The derivative at the identity is still the safe norm's 0 (no NaN).
    assert np.all(jax.grad(lambda q: jq.angle_between(identity, q))(identity) == 0)
    assert np.all(jax.jacrev(lambda q: jq.to_axis_angle(q)[1])(identity) == 0)


@pytest.mark.parametrize(
    "call",
    [
        lambda q: jq.slerp(q, q, 1),
        lambda q: jq.squad(q, q, q, q, 0),
        lambda q: jq.from_axis_angle(q[1:], 1),
        lambda q: jq.from_axis_angle(q[1:], np.array(1)),
        lambda q: jq.slerp(q, q, np.array([0, 1])),
        lambda q: jq.rotate(np.array([3, 0, 0]), q),
        lambda q: jq.step(q, q[1:], 1),
        lambda q: jq.integrate(q, q[1:], 1, 3),
    ],
)
def test_integer_arguments_do_not_widen_float32(call):
    """Integer times, angles and vectors (a Python int or an integer array) are promoted as JAX
    promotes them, to a weakly typed float, so the float32 quaternions stay float32 with x64 on (as
    `q32 * jnp.asarray(1)` does): a strong float64 made every one of these float64 (a review)."""
    assert jax.config.jax_enable_x64
    q = jq.normalize(jnp.array([1.0, 0.2, 0.3, 0.4], jnp.float32))
    assert call(q).dtype == jnp.float32


def test_integer_only_input_is_the_default_float():
    """With nothing else to set the width, integers still give the default float dtype."""
    assert jq.to_matrix(np.array([1, 0, 0, 0])).dtype == jnp.float64
    assert jq.from_axis_angle([0, 0, 1], 1).dtype == jnp.float64
    np.testing.assert_allclose(
        jq.rotate(jnp.array([3, 0, 0]), jnp.array([1, 2, 3, 4])), [-2, 2, 1], atol=1e-15
    )


def test_integer_input_under_strict_promotion_and_in_four_bits():
    """Integers become floats without the user's promotion mode getting a say (the weak float came
    from `x * 1.0`, which "strict" promotion refused) and from four-bit integers (which do not
    promote at all)."""
    with jax.numpy_dtype_promotion("strict"):
        q = jq.from_rotvec(np.array([1, 2, 3]))
    np.testing.assert_allclose(q, jq.from_rotvec(np.array([1.0, 2.0, 3.0])), rtol=0, atol=0)
    for dtype in (jnp.int4, jnp.uint4):
        q = jq.from_rotvec(jnp.array([1, 2, 3], dtype))
        np.testing.assert_allclose(q, jq.from_rotvec(np.array([1.0, 2.0, 3.0])), rtol=0, atol=0)
