"""Quaternion algebra against the Hamilton table, the seed's definitions, SciPy composition,
numpy-quaternion's exp/log and the matrix exponential."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest
import quaternion as npq  # numpy-quaternion: an independent implementation
import scipy.linalg
from helpers import random_unit
from scipy.spatial.transform import Rotation

import jaxquat as jq

ONE, I, J, K = np.eye(4)


@pytest.fixture(scope="module")
def general():
    """Non-unit quaternions (two sets of 1000)."""
    rng = np.random.default_rng(21)
    return rng.normal(size=(1000, 4)), rng.normal(size=(1000, 4))


def test_hamilton_table():
    def mul(p, q):
        return np.asarray(jq.multiply(p, q))

    for unit in (I, J, K):
        np.testing.assert_array_equal(mul(unit, unit), -ONE)
    np.testing.assert_array_equal(mul(mul(I, J), K), -ONE)  # ijk = −1
    np.testing.assert_array_equal(mul(I, J), K)
    np.testing.assert_array_equal(mul(J, I), -K)
    np.testing.assert_array_equal(mul(J, K), I)
    np.testing.assert_array_equal(mul(K, J), -I)
    np.testing.assert_array_equal(mul(K, I), J)
    np.testing.assert_array_equal(mul(I, K), -J)
    np.testing.assert_array_equal(mul(ONE, I), I)


def test_multiply_matches_numpy_quaternion_and_scipy(general):
    p, q = general
    expected = npq.as_float_array(npq.from_float_array(p) * npq.from_float_array(q))
    np.testing.assert_allclose(jq.multiply(p, q), expected, rtol=0, atol=1e-13)
    u, v = (
        np.asarray(random_unit(jax.random.key(1), (1000,))),
        np.asarray(random_unit(jax.random.key(2), (1000,))),
    )
    composed = Rotation.from_quat(v, scalar_first=True) * Rotation.from_quat(u, scalar_first=True)
    np.testing.assert_allclose(
        jq.to_matrix(jq.multiply(v, u)), composed.as_matrix(), rtol=0, atol=1e-12
    )  # multiply(q2, q1) applies q1 first


def test_algebraic_identities(general):
    p, q = general
    r = np.roll(p, 1, axis=0)
    np.testing.assert_allclose(
        jq.multiply(jq.multiply(p, q), r), jq.multiply(p, jq.multiply(q, r)), rtol=0, atol=1e-12
    )
    np.testing.assert_allclose(jq.norm(jq.multiply(p, q)), jq.norm(p) * jq.norm(q), rtol=1e-14)
    np.testing.assert_allclose(
        jq.conjugate(jq.multiply(p, q)), jq.multiply(jq.conjugate(q), jq.conjugate(p)), atol=1e-13
    )
    np.testing.assert_allclose(jq.multiply(p, jq.inverse(p)), np.tile(ONE, (1000, 1)), atol=1e-14)
    np.testing.assert_allclose(jq.multiply(jq.inverse(p), p), np.tile(ONE, (1000, 1)), atol=1e-14)
    # The seed's dot product: commutative, w₁w₂ + x₁x₂ + y₁y₂ + z₁z₂; |q|² = q·q = w(q q*).
    # (to round-off: a sum of four products has an error up to ~4 eps Σ|pᵢqᵢ|, whatever the order)
    bound = 4 * np.finfo(np.float64).eps * np.sum(np.abs(p * q), -1)
    assert np.all(np.abs(jq.dot(p, q) - np.sum(p * q, -1)) <= bound)
    np.testing.assert_array_equal(jq.dot(p, q), jq.dot(q, p))
    np.testing.assert_allclose(jq.norm(p) ** 2, jq.multiply(p, jq.conjugate(p))[:, 0], rtol=1e-14)
    np.testing.assert_allclose(jq.norm(jq.normalize(p)), 1.0, atol=1e-15)
    np.testing.assert_array_equal(jq.conjugate(p), p * [1, -1, -1, -1])
    np.testing.assert_array_equal(
        jq.from_vector(p[:, 1:]), np.concatenate([np.zeros((1000, 1)), p[:, 1:]], 1)
    )
    np.testing.assert_array_equal(jq.vector_part(p), p[:, 1:])


def test_exp_and_log_match_numpy_quaternion_and_expm(general):
    p, _ = general
    expected = npq.as_float_array(np.exp(npq.from_float_array(p)))
    np.testing.assert_allclose(jq.exp(p), expected, rtol=1e-13, atol=1e-13)
    expected = npq.as_float_array(np.log(npq.from_float_array(p)))
    np.testing.assert_allclose(jq.log(p), expected, rtol=1e-13, atol=1e-13)
    # exp via the matrix exponential of the left-multiplication matrix L(q): exp(q) = expm(L(q)) e₀.
    left = np.asarray(
        jax.vmap(jax.jacfwd(lambda r, q: jq.multiply(q, r)), in_axes=(None, 0))(ONE, p[:50])
    )
    via_expm = np.stack([scipy.linalg.expm(m)[:, 0] for m in left])
    np.testing.assert_allclose(jq.exp(p[:50]), via_expm, rtol=1e-12, atol=1e-13)
    # Inverse pair on the principal branch.
    np.testing.assert_allclose(jq.exp(jq.log(p)), p, rtol=0, atol=1e-13)
    v = p.copy()
    v[:, 1:] *= (3.0 / np.linalg.norm(v[:, 1:], axis=-1, keepdims=True)) * np.random.default_rng(
        0
    ).uniform(size=(1000, 1))
    np.testing.assert_allclose(jq.log(jq.exp(v)), v, rtol=0, atol=1e-12)  # |vec| < π


def test_exp_log_at_and_near_the_singular_points():
    np.testing.assert_array_equal(jq.exp(jnp.zeros(4)), ONE)
    np.testing.assert_allclose(jq.exp(np.array([0.5, 0, 0, 0])), np.exp(0.5) * ONE, rtol=1e-15)
    np.testing.assert_array_equal(jq.log(ONE), np.zeros(4))
    # A negative real has no axis of its own: the x axis, as numpy-quaternion, so exp(log q) = q.
    for w in [-1.0, -2.0, -1e-300, -3e300]:
        q = w * ONE
        want = npq.as_float_array(np.log(npq.from_float_array(q)))
        np.testing.assert_allclose(jq.log(q), want, rtol=1e-15)
        np.testing.assert_allclose(jq.log(q), [np.log(-w), np.pi, 0, 0], rtol=1e-15)
        # exp magnifies the rounding of ln|w| (|ln 1e-300| = 691) into its relative error.
        rtol = 2e-16 * (1 + abs(np.log(abs(w))))
        np.testing.assert_allclose(jq.exp(jq.log(q)), q, rtol=rtol, atol=3e-16 * abs(w))
    np.testing.assert_allclose(jq.log(2.0 * ONE), [np.log(2.0), 0, 0, 0], rtol=1e-15)
    for eps in [1e-12, 1e-6, 1e-3]:
        v = eps * np.array([0.6, 0.0, -0.8])
        np.testing.assert_allclose(
            jq.exp(np.concatenate([[0.0], v])),
            np.concatenate([[np.cos(eps)], np.sin(eps) * v / eps]),
            rtol=1e-15,
            atol=1e-20,
        )
        q = np.concatenate([[np.cos(eps)], np.sin(eps) * v / eps])
        np.testing.assert_allclose(jq.log(q)[1:], v, rtol=1e-13)

    @jax.jit
    def derivatives(w):
        return jax.jacfwd(jq.exp)(jnp.array([w, 0.0, 0.0, 0.0])), jax.jacrev(jq.log)(
            jnp.array([w, 0.0, 0.0, 0.0])
        )

    with jax.debug_nans(True):
        d_exp, d_log = derivatives(0.3)
    # At v = 0: d exp = e^w · I₄ (w-row e^w, vector block e^w I₃); d log vector block = I₃ / w.
    np.testing.assert_allclose(d_exp, np.exp(0.3) * np.eye(4), rtol=1e-15)
    np.testing.assert_allclose(d_log, np.diag([1 / 0.3, 1 / 0.3, 1 / 0.3, 1 / 0.3]), rtol=1e-15)


def test_identity_and_broadcasting():
    np.testing.assert_array_equal(jq.identity(), ONE)
    p = np.asarray(random_unit(jax.random.key(3), (3, 1, 2)))
    q = np.asarray(random_unit(jax.random.key(4), (2,)))
    out = jq.multiply(p, q)
    assert out.shape == (3, 1, 2, 4)
    np.testing.assert_allclose(out[2, 0, 1], jq.multiply(p[2, 0, 1], q[1]), rtol=1e-15)
    assert jq.multiply(p.astype(np.float32), q.astype(np.float32)).dtype == jnp.float32
    # Integers are promoted to the default float.
    assert jq.multiply([1, 2, 3, 4], [4, 3, 2, 1]).dtype == jnp.float64


@pytest.mark.parametrize(
    "call, name",
    [
        (lambda: jq.multiply(np.zeros(3), ONE), "p"),
        (lambda: jq.multiply(ONE, np.zeros((2, 5))), "q"),
        (lambda: jq.conjugate(np.zeros(3)), "q"),
        (lambda: jq.norm(np.zeros(())), "q"),
        (lambda: jq.dot(ONE, np.zeros(2)), "q"),
        (lambda: jq.from_vector(np.zeros(4)), "v"),
        (lambda: jq.exp(np.zeros(3)), "q"),
        (lambda: jq.log(np.zeros(3)), "q"),
    ],
)
def test_wrong_trailing_dimension_raises(call, name):
    with pytest.raises(ValueError, match=rf"`{name}` must have shape \(\.\.\., [34]\); got shape"):
        call()


def test_incompatible_batch_shapes_raise():
    with pytest.raises(
        ValueError, match=r"do not broadcast: `p` has shape \(3, 4\); `q` has shape \(2, 4\)"
    ):
        jq.multiply(np.zeros((3, 4)), np.zeros((2, 4)))


def test_exp_and_log_where_squares_overflow_or_underflow():
    """Against mpmath at 40 digits and complex exp: |v| so large that 4|v|² overflows, eʷ = ∞ with a
    zero vector component, and w < 0 with |v| so small that |v|² underflows (the angle is then π, the
    axis v's own direction). The old code gave NaN, NaN·0 = NaN components and π·v instead of π·v̂."""
    import mpmath

    mpmath.mp.dps = 40
    for size in [1e160, 1e200, -3e300]:
        got = np.asarray(jq.exp(np.array([0.0, 0.0, size, 0.0])))
        x = mpmath.mpf(size)
        want = [float(mpmath.cos(x)), 0.0, float(mpmath.sin(x) / x * x), 0.0]
        np.testing.assert_allclose(got, want, atol=1e-15)
    # Beyond |v| ~ 1e307 (float64) and ~4e37 (float32) sin|v|/|v| is subnormal, flushed to 0 by
    # XLA:CPU: the vector part was lost ((0, 1e38, 0, 0) in float32 gave (0.1468, 0, 0, 0)).
    # One component: |v| is exact, and so is the reference. Several: sin and cos of |v| ~ 1e308
    # hang on its last bit, so the result is checked for unit norm and a vector part along ±v.
    for dtype, v in [
        (np.float64, [0.0, 1.5e308, 0.0]),
        (np.float64, [1e308, 1e308, 0.0]),
        (np.float64, [3e307, -1e307, 2e306]),
        (np.float32, [1e38, 0.0, 0.0]),
        (np.float32, [-2e38, 1e38, 5e37]),
    ]:
        v = np.asarray(v, dtype)
        tol = 1e-6 if dtype == np.float32 else 1e-15
        got = np.asarray(jq.exp(np.concatenate([[0.0], v]).astype(dtype)), np.float64)
        assert abs(np.linalg.norm(got) - 1.0) < tol, (dtype, v, got)
        direction = v.astype(np.float64) / np.abs(v).max()  # (|v|² overflows)
        direction /= np.linalg.norm(direction)
        np.testing.assert_allclose(got[1:], np.dot(got[1:], direction) * direction, atol=tol)
        assert abs(abs(np.dot(got[1:], direction)) - np.sqrt(1 - got[0] ** 2)) < 10 * tol
        if np.count_nonzero(v) == 1:
            x = mpmath.mpf(float(v[np.flatnonzero(v)[0]]))
            want = [float(mpmath.cos(x))] + [float(mpmath.sin(x)) * np.sign(c) for c in v]
            np.testing.assert_allclose(got, want, atol=tol)
    np.testing.assert_array_equal(jq.exp(np.array([800.0, 0, 0, 0])), [np.inf, 0, 0, 0])
    got = np.asarray(jq.exp(np.array([800.0, 1.0, 0, 0])))
    np.testing.assert_array_equal(got[2:], [0.0, 0.0])
    np.testing.assert_array_equal(np.sign(got[:2]), np.sign([np.cos(1.0), np.sin(1.0)]))
    assert np.all(np.isinf(got[:2]))
    for dtype, tiny in [(np.float64, 1e-160), (np.float64, 1e-300), (np.float32, 1e-19)]:
        for sign in [1.0, -1.0]:
            v = np.array([0.0, 0.6, sign * 0.8]) * tiny
            got = np.asarray(jq.log(np.concatenate([[-2.0], v]).astype(dtype)))
            want = [np.log(2.0), 0.0, 0.6 * np.pi, sign * 0.8 * np.pi]
            np.testing.assert_allclose(got, want, rtol=1e-6 if dtype == np.float32 else 1e-15)
    # Squares so small that XLA flushes some of them to zero but not all: |v|² alone then gives
    # |v| short (a vector part of length 3.31 instead of π for the first, 3.62 for the second).
    cases = [
        (np.float64, [-1.0, 3e-154, 1e-154, 0.0]),
        (np.float64, [-1.0, 2e-154, 1.4e-154, 1.4e-154]),
        (np.float64, [-2.0, 1e-153, -3e-154, 0.0]),
        (np.float64, [-1e-70, 3e-154, 1e-154, 0.0]),
        (np.float32, [-1.0, 3e-19, 1e-19, 0.0]),
        (np.float32, [-1.0, 2e-19, -1.4e-19, 1.4e-19]),
    ]
    for dtype, q in cases:
        exact = [mpmath.mpf(c) for c in q]
        s = mpmath.sqrt(sum(c * c for c in exact[1:]))
        want = [float(mpmath.log(mpmath.sqrt(s * s + exact[0] ** 2)))]
        want += [float(mpmath.atan2(s, exact[0]) * c / s) for c in exact[1:]]
        got = np.asarray(jq.log(np.array(q, dtype)))
        rtol = 1e-6 if dtype == np.float32 else 1e-15
        np.testing.assert_allclose(got, want, rtol=rtol, atol=1e-30)  # ln|q| ≈ 1e-37, 1e-307
    # A tiny v with w > 0 stays v/w.
    np.testing.assert_allclose(jq.log(np.array([2.0, 1e-160, 0, 0]))[1], 0.5e-160, rtol=1e-15)
