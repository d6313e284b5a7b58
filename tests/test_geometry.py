"""Geometry: geodesic angle, slerp, squad, canonicalisation, Haar sampling, the chordal mean and the
opt-in unit check — against SciPy, closed forms and statistics."""

from __future__ import annotations

import math

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from helpers import assert_quat_close, quat_distance, random_unit
from scipy import stats
from scipy.spatial.transform import Rotation, Slerp

import jaxquat as jq


@pytest.fixture(scope="module")
def pairs():
    k1, k2 = jax.random.split(jax.random.key(11))
    return np.asarray(random_unit(k1, (10_000,))), np.asarray(random_unit(k2, (10_000,)))


# ---------------------------------------------------------------------------------------------------
# angle_between


def test_angle_between_matches_scipy_and_is_sign_invariant(pairs):
    p, q = pairs
    expected = (
        Rotation.from_quat(p, scalar_first=True).inv() * Rotation.from_quat(q, scalar_first=True)
    ).magnitude()
    angle = np.asarray(jq.angle_between(p, q))
    np.testing.assert_allclose(angle, expected, rtol=0, atol=1e-12)
    assert np.all((angle >= 0) & (angle <= np.pi))
    np.testing.assert_allclose(jq.angle_between(-p, q), angle, rtol=0, atol=1e-12)
    np.testing.assert_allclose(jq.angle_between(p, -2.0 * q), angle, rtol=0, atol=1e-12)
    np.testing.assert_allclose(jq.angle_between(q, p), angle, rtol=0, atol=1e-12)


def test_angle_between_is_accurate_for_tiny_angles():
    p = np.asarray(random_unit(jax.random.key(12), (5,)))
    for angle in [1e-14, 1e-10, 1e-6]:
        q = jq.multiply(p, jq.from_axis_angle([1.0, -2.0, 0.5], angle))
        # q itself is rounded (~1e-16 per component): that, not the formula, bounds the agreement.
        np.testing.assert_allclose(jq.angle_between(p, q), angle, rtol=0, atol=5e-16)
        np.testing.assert_allclose(jq.angle_between(p, -q), angle, rtol=0, atol=5e-16)
        # 2·acos|⟨p, q⟩| cannot resolve angles below ~2e-8 rad.
        if angle < 1e-8:
            acos_angle = 2.0 * np.arccos(np.minimum(np.abs(np.sum(p * np.asarray(q), -1)), 1.0))
            assert np.max(np.abs(acos_angle - angle)) > 1e-9
    np.testing.assert_array_equal(jq.angle_between(p, p), 0.0)
    np.testing.assert_array_equal(jq.angle_between(p, -p), 0.0)


@pytest.mark.parametrize("dtype", [jnp.float32, jnp.float64])
def test_angle_between_a_quaternion_and_itself_is_zero_for_every_shape(dtype):
    """θ(q, ±q) = 0 exactly whatever the batch shape, eager and under `jax.jit`: a single float32
    quaternion gave 5e-8 rad (XLA normalised p and q by different fusions) where a batch gave 0."""
    q = (
        np.asarray(random_unit(jax.random.key(13), (6,)), dtype)
        * np.array([1, 3, 0.5, 2, 7, 1])[:, None]
    )
    cases = [(q[0], q[0]), (q[:1], q[:1]), (q[:2], q[:2]), (q[:, None], q[:, None]), (q[3], q[3:4])]
    cases += [(np.asarray([1, 2, 3, 4], dtype), np.asarray([1, 2, 3, 4], dtype))]
    for a, b in cases:
        for f in (jq.angle_between, jax.jit(jq.angle_between)):
            np.testing.assert_array_equal(
                f(a, b), np.zeros(np.broadcast_shapes(a.shape, b.shape)[:-1])
            )
            np.testing.assert_array_equal(
                f(a, -b), np.zeros(np.broadcast_shapes(a.shape, b.shape)[:-1])
            )
    # One rounding away it is still the geodesic angle: against 2·atan2(|vec(a* b)|, |⟨a, b⟩|) at 50
    # digits (1.51e-16 rad in float64, 8.10e-8 in float32), to half an ε (the normalisations round).
    import mpmath

    mpmath.mp.dps = 50
    a = np.asarray([1, 2, 3, 4], dtype)
    b = a.copy()
    b[1] = np.nextafter(b[1], dtype(3))
    (aw, *av), (bw, *bv) = [[mpmath.mpf(float(c)) for c in x] for x in (a, b)]
    cross = [
        av[1] * bv[2] - av[2] * bv[1],
        av[2] * bv[0] - av[0] * bv[2],
        av[0] * bv[1] - av[1] * bv[0],
    ]
    vec = [aw * y - bw * x - c for x, y, c in zip(av, bv, cross, strict=True)]
    dot = aw * bw + sum(x * y for x, y in zip(av, bv, strict=True))
    want = float(2 * mpmath.atan2(mpmath.sqrt(sum(c * c for c in vec)), abs(dot)))
    np.testing.assert_allclose(jq.angle_between(a, b), want, rtol=0, atol=0.5 * np.finfo(dtype).eps)


def test_angle_between_gradient_near_and_at_zero():
    """Along the geodesic q(t) = p ⊗ exp(t n̂), dθ/dt = 1 for t > 0 (the cone's slope), also at
    t = 1e-12 where finite differences cannot resolve it; at t = 0 the gradient is exactly 0."""
    p = np.asarray(random_unit(jax.random.key(13)))
    n = np.array([0.6, -0.8, 0.0])

    def along(t):
        return jq.angle_between(p, jq.multiply(p, jq.from_rotvec(t * n)))

    @jax.jit
    def slopes(ts):
        return jax.vmap(jax.grad(along))(ts), jax.vmap(lambda t: jax.jvp(along, (t,), (1.0,))[1])(
            ts
        )

    ts = jnp.array([1e-12, 1e-6, 0.3, 3.0])
    with jax.debug_nans(True):
        reverse, forward = slopes(ts)
        at_zero = jax.jit(jax.grad(jq.angle_between, argnums=(0, 1)))(p, p)
    # Both modes under jit: within round-off of the vector part, ~ε/θ relative (forward 1.7e-5 and
    # reverse 8.8e-6 at θ = 1e-12 in some compilations, where XLA's fused evaluation rounds the tiny
    # vector part differently for the norm and for its derivative; 5e-9 eagerly). The input q itself
    # carries that round-off: the angle at t = 1e-12 is 7e-5 relative off t.
    tolerance = 1e-7 + 4 * np.finfo(np.float64).eps / np.asarray(ts)
    assert np.all(np.abs(np.asarray(reverse) - 1.0) <= tolerance), reverse
    assert np.all(np.abs(np.asarray(forward) - 1.0) <= tolerance), forward
    for g in at_zero:
        np.testing.assert_array_equal(g, 0.0)


# ---------------------------------------------------------------------------------------------------
# slerp and squad


def test_slerp_matches_scipy_and_has_constant_speed(pairs):
    p, q = pairs[0][:500], pairs[1][:500]
    ts = np.linspace(0.0, 1.0, 7)
    ours = np.asarray(jq.slerp(p[:, None], q[:, None], ts[None, :]))
    for n in range(20):
        scipy_path = Slerp(
            [0.0, 1.0], Rotation.from_quat(np.stack([p[n], q[n]]), scalar_first=True)
        )(ts)
        assert quat_distance(ours[n], scipy_path.as_quat(scalar_first=True)) < 1e-12
    total = np.asarray(jq.angle_between(p, q))
    np.testing.assert_allclose(jq.angle_between(p[:, None], ours), total[:, None] * ts, atol=1e-12)
    np.testing.assert_array_equal(ours[:, 0], p)  # exactly p at t = 0
    assert_quat_close(ours[:, -1], q, atol=1e-12)
    # Shortest arc, hence sign-invariant in q.
    assert quat_distance(jq.slerp(p[:, None], -q[:, None], ts[None, :]), ours) < 1e-12


def test_squad_endpoints_and_reduction_to_slerp(pairs):
    p, q, a, b = pairs[0][:4], pairs[1][:4], pairs[0][4:8], pairs[1][4:8]
    t = np.array([0.0, 0.25, 0.7, 1.0])[:, None]
    out = np.asarray(jq.squad(p, a, b, q, t))
    assert_quat_close(out[0], p, atol=1e-14)
    assert_quat_close(out[-1], q, atol=1e-12)
    assert_quat_close(jq.squad(p, p, q, q, t), jq.slerp(p, q, t), atol=1e-12)


def test_squad_is_continuous_between_keys_far_apart():
    """The outer interpolation chose the short way at every t, so where the two inner curves passed
    π apart as rotations the curve jumped by a half-turn mid-segment: keys turned 120° about x, y, x
    gave a 3.14 rad jump at t ≈ 0.5, and so did 61 % of segments between Haar-random keys (none up to
    90° apart). Neighbouring samples must be close, and the curve must not depend on the signs."""
    x, y = np.eye(3)[0], np.eye(3)[1]
    keys = [np.array([1.0, 0.0, 0.0, 0.0])]
    for axis in (x, y, x):
        keys.append(np.asarray(jq.multiply(jq.from_rotvec(np.radians(120.0) * axis), keys[-1])))
    haar = np.asarray(random_unit(jax.random.key(7), (200, 4)))
    keys = np.concatenate([np.stack(keys)[None], haar])  # (201, 4 keys, 4)
    a = jq.squad_control_points(keys[:, 0], keys[:, 1], keys[:, 2])
    b = jq.squad_control_points(keys[:, 1], keys[:, 2], keys[:, 3])
    ts = np.linspace(0.0, 1.0, 401)[:, None]
    curve = np.asarray(jq.squad(keys[:, 1], a, b, keys[:, 2], ts))  # (401, 201, 4)
    steps = np.asarray(jq.angle_between(curve[1:], curve[:-1]))
    assert steps[:, 0].max() < 0.01, steps[:, 0].max()
    assert steps.max() < 0.1, steps.max()
    assert_quat_close(curve[0], keys[:, 1], atol=1e-14)
    assert_quat_close(curve[-1], keys[:, 2], atol=1e-12)
    signs = np.where(np.asarray(random_unit(jax.random.key(8), (4, 201)))[..., :1] < 0, -1.0, 1.0)
    flipped = jq.squad(signs[0] * keys[:, 1], signs[1] * a, signs[2] * b, signs[3] * keys[:, 2], ts)
    assert quat_distance(flipped, curve) < 1e-12


def test_squad_spline_has_continuous_angular_velocity():
    """With Shoemake's control points the piecewise squad curve is C¹ at the interior keys."""
    keys = np.asarray(random_unit(jax.random.key(14), (5,)))
    # A smooth-ish key sequence: small steps, mixed signs (the construction must not care).
    steps = np.array([[0, 0, 0], [0.3, 0.1, 0], [0.5, 0.6, 0.2], [0.4, 1.0, 0.7], [0.9, 1.2, 0.5]])
    keys = (
        np.asarray(jq.multiply(jq.from_rotvec(steps), keys[0]))
        * np.array([1, -1, 1, 1, -1])[:, None]
    )
    controls = np.stack(
        [
            np.asarray(jq.squad_control_points(keys[i - 1], keys[i], keys[i + 1]))
            for i in range(1, 4)
        ]
    )

    def omega(p, a, b, q, t):  # world-frame angular velocity 2·vec(q̇ q*) of a squad segment
        value, derivative = jax.jvp(lambda s: jq.squad(p, a, b, q, s), (t,), (1.0,))
        return 2.0 * jq.vector_part(jq.multiply(derivative, jq.conjugate(value)))

    @jax.jit
    def key_velocities(keys, controls):
        # interior key 2: the end of segment 1 and the start of segment 2
        left = omega(keys[1], controls[0], controls[1], keys[2], 1.0)
        right = omega(keys[2], controls[1], controls[2], keys[3], 0.0)
        return left, right

    left, right = key_velocities(keys, controls)
    np.testing.assert_allclose(left, right, atol=1e-10)
    # A plain slerp chain would have the constant world rate to_rotvec(q₊ q*) on each segment,
    # which jumps at the key; squad's rate at the key is different from both.
    slerp_left = np.asarray(jq.to_rotvec(jq.multiply(keys[2], jq.conjugate(keys[1]))))
    slerp_right = np.asarray(jq.to_rotvec(jq.multiply(keys[3], jq.conjugate(keys[2]))))
    assert np.max(np.abs(slerp_left - slerp_right)) > 0.1
    assert np.linalg.norm(left) > 0.1


# ---------------------------------------------------------------------------------------------------
# canonicalize, random


def test_canonicalize_matches_scipy(pairs):
    p = pairs[0][:1000] * np.where(np.arange(1000) % 2, 1.0, -1.0)[:, None]
    special = np.array(
        [
            [0.0, -0.6, 0.8, 0.0],
            [0.0, 0.0, -1.0, 0.0],
            [0.0, 0.0, 0.0, -1.0],
            [-1.0, 0, 0, 0],
            [0, 0.6, -0.8, 0],
        ]
    )
    q = np.concatenate([p, special])
    ours = np.asarray(jq.canonicalize(q))
    scipy_canonical = Rotation.from_quat(q, scalar_first=True).as_quat(
        canonical=True, scalar_first=True
    )
    np.testing.assert_allclose(ours, scipy_canonical, rtol=0, atol=1e-15)  # SciPy renormalises
    assert np.all(ours[:, 0] >= 0)
    np.testing.assert_allclose(jq.to_matrix(ours), jq.to_matrix(q), atol=1e-15)
    np.testing.assert_array_equal(jq.canonicalize(ours), ours)


def test_random_is_haar_uniform():
    q = np.asarray(jq.random(jax.random.key(15), (20_000,)))
    np.testing.assert_allclose(np.linalg.norm(q, axis=-1), 1.0, atol=1e-15)
    angle = 2.0 * np.arctan2(np.linalg.norm(q[:, 1:], axis=-1), np.abs(q[:, 0]))
    # The rotation angle has density (1 − cos θ)/π on [0, π]: CDF (θ − sin θ)/π.
    result = stats.kstest(angle, lambda t: (t - np.sin(t)) / np.pi)
    assert result.pvalue > 1e-3
    # ... and a uniform density in θ would be rejected: the test has power.
    assert (
        stats.kstest(
            np.random.default_rng(0).uniform(0, np.pi, 20_000), lambda t: (t - np.sin(t)) / np.pi
        ).pvalue
        < 1e-6
    )
    # Haar measure: E[R] = 0 (each entry has variance 1/3; 5 standard errors).
    mean_matrix = np.mean(np.asarray(jq.to_matrix(q)), axis=0)
    assert np.max(np.abs(mean_matrix)) < 5 * math.sqrt(1 / 3 / len(q))
    # Rotated axes are uniform on the sphere: E[R e_z] = 0 and E[(R e_z)(R e_z)ᵀ] = I/3.
    z = np.asarray(jq.rotate(np.array([0.0, 0.0, 1.0]), q))
    np.testing.assert_allclose(z.T @ z / len(z), np.eye(3) / 3, atol=0.02)
    q32 = jq.random(jax.random.key(15), (3,), jnp.float32)
    assert q32.dtype == jnp.float32
    with pytest.raises(ValueError, match="`dtype` must be a float dtype"):
        jq.random(jax.random.key(0), (), jnp.int32)


# ---------------------------------------------------------------------------------------------------
# mean


def test_mean_matches_scipy_with_and_without_weights(pairs):
    rng = np.random.default_rng(16)
    centre = pairs[0][0]
    spread = np.asarray(jq.from_rotvec(0.8 * rng.normal(size=(2000, 3))))
    q = np.asarray(jq.multiply(centre, spread)) * rng.choice([-1.0, 1.0], size=(2000, 1))
    weights = rng.uniform(0.0, 2.0, size=2000)
    r = Rotation.from_quat(q, scalar_first=True)
    assert_quat_close(jq.mean(q), r.mean().as_quat(scalar_first=True), atol=1e-12)
    assert_quat_close(jq.mean(q, weights), r.mean(weights).as_quat(scalar_first=True), atol=1e-12)
    # Widely spread (Haar-random) sets too.
    r_all = Rotation.from_quat(pairs[0], scalar_first=True)
    assert_quat_close(jq.mean(pairs[0]), r_all.mean().as_quat(scalar_first=True), atol=1e-12)
    # Sign-invariant, w ≥ 0, and a batch of groups with `axis`.
    assert jq.mean(q)[0] >= 0
    np.testing.assert_allclose(jq.mean(-q, weights), jq.mean(q, weights), atol=1e-14)
    groups = q[:1000].reshape(10, 100, 4)
    batched = np.asarray(jq.mean(groups, axis=1))
    for g in range(10):
        assert_quat_close(
            batched[g],
            Rotation.from_quat(groups[g], scalar_first=True).mean().as_quat(scalar_first=True),
            atol=1e-12,
        )
    assert_quat_close(jq.mean(groups.transpose(1, 0, 2), axis=0), batched, atol=1e-14)


def test_mean_closed_forms():
    q = np.asarray(random_unit(jax.random.key(17)))
    np.testing.assert_allclose(jq.mean(np.stack([q, -q, q])), q * np.sign(q[0]), atol=1e-14)
    # Two rotations about one axis: the mean is the rotation halfway between them.
    a = jq.from_axis_angle([0.0, 0.0, 1.0], 0.2)
    b = jq.from_axis_angle([0.0, 0.0, 1.0], 1.0)
    assert_quat_close(
        jq.mean(np.stack([a, b])), jq.from_axis_angle([0.0, 0.0, 1.0], 0.6), atol=1e-14
    )
    # Weights (w, 1−w) on a symmetric pair ±φ about an axis: the chordal mean solves tan 2ψ = (2w−1) tan 2φ·…
    # — check the simplest case: weight 0 returns the other rotation exactly.
    assert_quat_close(jq.mean(np.stack([a, b]), np.array([0.0, 1.0])), b, atol=1e-14)


def test_mean_bad_arguments():
    q = np.asarray(random_unit(jax.random.key(18), (4, 3)))
    with pytest.raises(ValueError, match=r"`weights` must broadcast to the batch shape \(4, 3\)"):
        jq.mean(q, np.ones(5))
    with pytest.raises(ValueError, match="`axis`"):
        jq.mean(q, axis=2)
    with pytest.raises(ValueError, match=r"`q` must have shape \(\.\.\., 4\)"):
        jq.mean(q[..., :3])
    # A negative weight, as SciPy's Rotation.mean: it was used, giving a meaningless rotation.
    weights = np.ones((4, 3))
    weights[2, 1] = -0.5
    with pytest.raises(
        ValueError, match=r"`weights` must be finite and non-negative.*-0\.5 at index \(2, 1\)"
    ):
        jq.mean(q, weights)
    with pytest.raises(ValueError, match="must be non-negative"):
        Rotation.from_quat(q.reshape(-1, 4), scalar_first=True).mean(weights.reshape(-1))
    jq.mean(q, np.abs(weights))  # zero and positive weights are fine
    # A NaN or infinite weight gave a NaN mean silently (SciPy raises LinAlgError for NaN).
    for bad in [np.nan, np.inf]:
        weights[2, 1] = bad
        with pytest.raises(
            ValueError, match=rf"finite and non-negative.*got {bad} at index \(2, 1\)"
        ):
            jq.mean(q, weights)
    # The index is the weights' own, not the broadcast one's.
    with pytest.raises(ValueError, match=r"got nan at index \(1,\)"):
        jq.mean(q, np.array([1.0, np.nan, 2.0]))
    with pytest.raises(np.linalg.LinAlgError):
        Rotation.from_quat(q.reshape(-1, 4), scalar_first=True).mean(np.full(12, np.nan))
    # Under jit the weights cannot be seen: NaN propagates, as for any non-finite input.
    assert np.all(np.isnan(jax.jit(jq.mean)(q, weights)))


def test_mean_of_zero_total_weight_is_an_error_or_nan():
    """Weights summing to zero leave nothing to average: eigh's last eigenvector of the zero matrix,
    (0, 0, 0, 1), a half-turn about z, came out silently (also for one zero-weight slice of a batched
    mean). A ValueError when the weights are concrete; under jit NaN in that slice only, with finite,
    correct gradients for the others."""
    pair = np.array([[1.0, 0.0, 0.0, 0.0], [0.0, 1.0, 0.0, 0.0]])
    with pytest.raises(ValueError, match=r"`weights` sum to zero over the averaged axes \(0,\)"):
        jq.mean(pair, np.zeros(2))
    q = np.stack([np.array([[1.0, 0.0, 0.0, 0.0], [0.6, 0.8, 0.0, 0.0]]), pair])
    weights = np.array([[1.0, 2.0], [0.0, 0.0]])
    with pytest.raises(ValueError, match=r"sum to zero .* \(batch index \(1,\) of the mean\)"):
        jq.mean(q, weights, axis=1)
    jitted = jax.jit(lambda q, w: jq.mean(q, w, axis=1))
    out = np.asarray(jitted(q, weights))
    assert np.all(np.isnan(out[1]))
    expected = Rotation.from_quat(q[0], scalar_first=True).mean(weights[0])
    assert_quat_close(out[0], expected.as_quat(scalar_first=True), atol=1e-14)
    # The gradient of the non-empty mean: the same as that mean computed on its own, 0 for the empty
    # slice (the NaN output must not leak into it).
    grad = jax.grad(lambda w: jitted(q, w)[0, 1])(weights)
    alone = jax.grad(lambda w: jq.mean(q[0], w)[1])(weights[0])
    np.testing.assert_allclose(grad[0], alone, rtol=1e-12)
    np.testing.assert_array_equal(grad[1], 0.0)
    np.testing.assert_allclose(
        jax.jacfwd(lambda w: jitted(q, w)[0, 1])(weights), grad, rtol=1e-12, atol=0
    )


@pytest.mark.parametrize("dtype", [np.float32, np.float64])
def test_subnormal_weights_are_named_as_such(dtype):
    """Weights all below the smallest normal number are read as 0 by XLA on the CPU; the error said
    they "sum to zero" and that there was nothing to average, which is not what the caller gave."""
    tiny = np.finfo(dtype).tiny
    pair = np.array([[1.0, 0.0, 0.0, 0.0], [0.6, 0.8, 0.0, 0.0]], dtype)
    with pytest.raises(ValueError, match=r"sum to zero .*: they are all below the smallest normal"):
        jq.mean(pair, np.array([tiny / 4, tiny / 2], dtype))
    with pytest.raises(ValueError, match="nothing to average"):  # truly zero: the old message
        jq.mean(pair, np.zeros(2, dtype))
    # One normal weight is enough: the subnormal one counts as 0, the mean is the other rotation.
    out = jq.mean(pair, np.array([tiny / 4, 1.0], dtype))
    assert_quat_close(out, pair[1], atol=4 * np.finfo(dtype).eps)


def test_subnormal_components_are_read_as_zero_as_documented():
    """The README and the docstrings of `angle_between`, `mean` and `from_two_vectors` state that
    XLA:CPU reads a subnormal component as 0 even beside a normal one (these functions once claimed
    any scale): float32 (2e-38, 5e-39, 0, 0) is the identity, not a turn of 2·atan(1/4)."""
    p = np.array([2e-38, 5e-39, 0.0, 0.0], np.float32)
    identity = np.array([1.0, 0.0, 0.0, 0.0], np.float32)
    assert float(jq.angle_between(p, identity)) == 0.0
    np.testing.assert_array_equal(jq.mean(p[None]), identity)
    np.testing.assert_array_equal(jq.from_two_vectors(p[:3], np.float32([1, 0, 0])), identity)
    np.testing.assert_array_equal(jq.rotate(np.float32([0, 1, 0]), p), [0, 1, 0])
    # Scaled up first, the same quaternion is the turn it names.
    scaled = jq.angle_between(p * np.float32(2.0**100), identity)
    np.testing.assert_allclose(scaled, 2 * np.arctan(0.25), rtol=1e-6)


# ---------------------------------------------------------------------------------------------------
# check_unit


def test_check_unit_passes_unit_and_rejects_others():
    q = jq.random(jax.random.key(19), (3,))
    np.testing.assert_array_equal(jq.check_unit(q), q)
    np.testing.assert_array_equal(jax.jit(jq.check_unit)(q), q)
    bad = q.at[1].multiply(1.01)
    with pytest.raises(RuntimeError, match="not unit"):
        jq.check_unit(bad)
    # Through XLA's callback machinery the error class varies (JaxRuntimeError / ValueError); the
    # message is the contract.
    with pytest.raises((RuntimeError, ValueError), match="not unit"):
        jax.block_until_ready(jax.jit(jq.check_unit)(bad))
    with pytest.raises((RuntimeError, ValueError), match="not unit"):
        jq.check_unit(q.at[0, 0].set(jnp.nan))
    np.testing.assert_array_equal(jq.check_unit(bad, atol=0.02), bad)
    q32 = q.astype(jnp.float32)
    np.testing.assert_array_equal(jq.check_unit(q32), q32)  # default atol √ε(float32)
    # Differentiable: the identity map.
    np.testing.assert_array_equal(jax.jacrev(lambda x: jq.check_unit(x))(q[0]), np.eye(4))


@pytest.mark.parametrize("atol", ["x", -1.0, math.nan, math.inf, True, [1e-3]])
def test_check_unit_rejects_a_bad_atol(atol):
    """A string atol was a bare TypeError from the message's format; a negative one failed every
    quaternion; NaN passed none."""
    with pytest.raises(ValueError, match="`atol` must be a finite non-negative number"):
        jq.check_unit(jnp.array([1.0, 0.0, 0.0, 0.0]), atol=atol)


@pytest.mark.parametrize("dtype, tol", [("float32", 1e-6), ("float64", 1e-14)])
def test_angle_between_does_not_depend_on_the_inputs_lengths(dtype, tol):
    """Scale-invariance in floating point: scaling one argument by 1e-12 … 1e16 (where ±q − p once
    swamped the smaller one in rounding), or one or both to lengths whose square the dtype cannot
    hold, leaves the angle at its float64 value of the unit inputs."""
    rng = np.random.default_rng(5)
    p = rng.normal(size=(200, 4))
    q = rng.normal(size=(200, 4))
    want = Rotation.from_quat(q[:, [1, 2, 3, 0]]) * Rotation.from_quat(p[:, [1, 2, 3, 0]]).inv()
    want = want.magnitude()
    # Lengths whose square over- or underflows too (|p|² was formed from p itself: θ = 0 for any q
    # above 1e19 in float32, NaN below 1e-19; in float64 above 1e154 and below 1e-154).
    extreme = [1e-30, 1e-20, 1e20, 1e30] if dtype == "float32" else [1e-200, 1e-160, 1e160, 1e200]
    for scale in [1e-12, 1e-3, 1.0, 1e3, 1e9, 1e16, *extreme]:
        for args in [(scale * p, q), (p, scale * q), (scale * p, scale * q)]:
            got = jq.angle_between(*(jnp.asarray(x, dtype) for x in args))
            assert np.max(np.abs(np.asarray(got, np.float64) - want)) <= tol * 10


def test_smooth_squared_angle_of_the_docstring_has_hessian_two_at_coincidence():
    """angle_between's docstring sends users who need curvature at p = q to |to_rotvec(p* q)|²: its
    Hessian in a rotation-vector perturbation is 2·I there (the squared angle |r|², exactly)."""
    target = jq.from_rotvec(jnp.array([0.4, -0.2, 0.9]))

    def squared(r):
        q = jq.multiply(target, jq.from_rotvec(r))
        return jnp.sum(jq.to_rotvec(jq.multiply(jq.conjugate(target), q)) ** 2)

    for r in [jnp.zeros(3), jnp.array([1e-9, 0.0, 0.0]), jnp.array([0.3, 0.1, -0.2])]:
        np.testing.assert_allclose(jax.hessian(squared)(r), 2.0 * np.eye(3), atol=1e-9)
        # the angle itself, to the round-off of composing with `target` (absolute ~1e-16)
        assert abs(float(jnp.sqrt(squared(r))) - float(jnp.linalg.norm(r))) <= 1e-15


def test_mean_of_huge_weights_matches_scipy():
    """The mean does not depend on the weights' scale, but float64 weights of 1e308 overflowed the
    moment Σ wᵢ qᵢ qᵢᵀ: NaN, or for three rotations (0, 0, 0, 1), silently (SciPy overflows too:
    the reference is SciPy's mean with the weights divided by 1e308)."""
    r = Rotation.from_quat(np.asarray(random_unit(jax.random.key(61), (10,))), scalar_first=True)
    q = r.as_quat(scalar_first=True)
    for weights in [np.full(10, 1e308), np.linspace(1e308, 0.0, 10)]:
        expected = r.mean(weights / 1e308).as_quat(scalar_first=True)
        assert_quat_close(jq.mean(q, weights), expected, atol=1e-14)
        assert_quat_close(jax.jit(jq.mean)(q, weights), expected, atol=1e-14)
    # float32: 400 weights of 1e37 sum past float32's largest number.
    tiled = np.tile(q, (40, 1)).astype(np.float32)
    expected = r.mean().as_quat(scalar_first=True)
    assert_quat_close(jq.mean(tiled, np.full(400, 1e37, np.float32)), expected, atol=1e-6)


def test_mean_of_non_unit_quaternions_matches_scipy():
    """SciPy normalises every input; a quaternion's length must not act as a weight."""
    rng = np.random.default_rng(8)
    q = rng.normal(size=(50, 4)) * rng.uniform(0.01, 100.0, size=(50, 1))
    weights = rng.uniform(0.1, 1.0, size=50)
    rotations = Rotation.from_quat(q[:, [1, 2, 3, 0]])
    for w in [None, weights]:
        want = rotations.mean(weights=w).as_quat()[[3, 0, 1, 2]]
        got = jq.mean(jnp.asarray(q), None if w is None else jnp.asarray(w))
        assert float(jq.angle_between(got, jnp.asarray(want))) < 1e-12
    # Lengths whose square over- or underflows (float32 1e±25, float64 1e±200): each input was
    # normalised through |q|², which gave [0, 0, 0, 1] or NaN.
    unit = q / np.linalg.norm(q, axis=-1, keepdims=True)
    want = rotations.mean().as_quat()[[3, 0, 1, 2]]
    for dtype, lengths, tol in [
        ("float32", (1e25, 1e-25), 1e-5),
        ("float64", (1e200, 1e-200), 1e-12),
    ]:
        for length in lengths:
            got = jq.mean(jnp.asarray(unit * length, dtype))
            assert float(jq.angle_between(got, jnp.asarray(want, dtype))) < tol, (dtype, length)
    identity_and_scaled = jnp.stack(
        [jq.identity(), 3.0 * jq.from_rotvec(jnp.array([0.0, 0.0, 1.0]))]
    )
    np.testing.assert_allclose(
        jq.to_rotvec(jq.mean(identity_and_scaled)), [0.0, 0.0, 0.5], atol=1e-12
    )


def test_angle_between_gradient_at_a_half_turn_is_the_symmetric_subgradient():
    """At θ = π (w(p* q) = 0) θ has a ridge: the one-sided derivatives w.r.t. q_w are ∓2/|q_v| (central
    differences on either side); the documented choice is their mean, 0 — as for sign(w) — not the
    one-sided −2 that `jnp.abs` gives at 0."""
    p = jnp.array([1.0, 0.0, 0.0, 0.0])
    q = jnp.array([0.0, 0.6, 0.8, 0.0])
    f = lambda x: jq.angle_between(p, x)  # noqa: E731
    np.testing.assert_array_equal(np.asarray(jax.grad(f)(q)), 0.0)
    np.testing.assert_array_equal(np.asarray(jax.jacfwd(f)(q)), 0.0)
    h = 1e-7
    e = jnp.array([1.0, 0.0, 0.0, 0.0])
    right = (f(q + 2 * h * e) - f(q + h * e)) / h
    left = (f(q - h * e) - f(q - 2 * h * e)) / h
    np.testing.assert_allclose([right, left], [-2.0, 2.0], rtol=1e-5)
    # Away from the ridge the gradient is unchanged: d θ / d q_w = −2 sign(w)/|q_v| · (…) by FD.
    q1 = jnp.array([0.1, 0.6, 0.8, 0.0])
    fd = (f(q1 + h * e) - f(q1 - h * e)) / (2 * h)
    np.testing.assert_allclose(jax.grad(f)(q1)[0], fd, rtol=1e-6)


def test_mean_axis_accepts_numpy_integers_and_rejects_bools():
    q = jq.random(jax.random.key(3), (2, 3))
    np.testing.assert_array_equal(
        np.asarray(jq.mean(q, axis=np.int64(0))), np.asarray(jq.mean(q, axis=0))
    )
    np.testing.assert_array_equal(
        np.asarray(jq.mean(q, axis=(np.int32(-1),))), np.asarray(jq.mean(q, axis=1))
    )
    for axis in (True, (0, False), np.bool_(True)):
        with pytest.raises(ValueError, match="`axis` must be None, an int or a tuple of ints"):
            jq.mean(q, axis=axis)


def test_mean_axis_repeated_is_refused():
    """A repeated axis (also as a negative alias) was quietly de-duplicated, where NumPy raises."""
    q = jq.random(jax.random.key(4), (3, 2))
    for axis in ((0, 0), (0, -2), (1, -1, 0)):
        with pytest.raises(ValueError, match=r"`axis` .* repeats an axis"):
            jq.mean(q, axis=axis)
