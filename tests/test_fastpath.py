"""The loop structure of `integrate`'s fast paths (`jaxquat._fastpath`).

`one_kernel` is the identity that XLA:CPU lowers to one loop with several outputs; the sampled-ω run
takes groups of steps per kernel, a series exponential checked as it goes, and renormalisations between
groups. Everything is checked against mathematics or an independent loop, never against the fast path
itself: bit identity for `one_kernel`, SciPy's composition of the step rotations for the run, and AD
through a plain Python loop of exact steps for its derivatives.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from helpers import random_unit
from scipy.spatial.transform import Rotation

import jaxquat as jq
from jaxquat._fastpath import SERIES_MAX_THETA_SQ, UNROLL, one_kernel


def bits(x):
    x = np.asarray(x)
    return x.view(np.uint64 if x.dtype == np.float64 else np.uint32)


@pytest.mark.parametrize("dtype", [jnp.float32, jnp.float64])
def test_one_kernel_returns_its_arguments_bit_for_bit(dtype):
    """Signed zeros, infinities, NaN, subnormals and the extremes come back unchanged, eagerly and
    under jit (where XLA:CPU lowers it to a sum over a padded axis, which must not turn −0 into +0)."""
    info = jnp.finfo(dtype)
    special = jnp.array(
        [-0.0, 0.0, np.inf, -np.inf, np.nan, float(info.tiny) / 4, -float(info.max), 1.0], dtype
    )
    others = (jnp.arange(8, dtype=dtype) - 3.5) * 1e3, -special
    for function in (one_kernel, jax.jit(one_kernel)):
        out = function(special, *others)
        assert len(out) == 3
        for got, given in zip(out, (special, *others), strict=True):
            assert got.dtype == given.dtype and got.shape == given.shape
            np.testing.assert_array_equal(bits(got), bits(given))
    scalar = jax.jit(one_kernel)(jnp.array(-0.0, dtype))
    np.testing.assert_array_equal(bits(scalar[0]), bits(jnp.array(-0.0, dtype)))


def test_one_kernel_is_linear_with_identity_derivatives_and_batches():
    """jvp and vjp pass tangents and cotangents through unchanged (also symbolic zeros, for an output
    that does not depend on the input), it transposes to itself, and vmap over any axis, with
    unbatched arguments mixed in, equals the unbatched call."""
    x = jnp.linspace(-1.0, 2.0, 6)
    y = jnp.cos(x)

    def f(a, b):
        u, v = one_kernel(jnp.sin(a) * b, a * a)
        return u + 2.0 * v

    def reference(a, b):
        return jnp.sin(a) * b + 2.0 * a * a

    for argnums in (0, 1):
        np.testing.assert_allclose(
            jax.jacfwd(f, argnums)(x, y), jax.jacfwd(reference, argnums)(x, y), rtol=1e-15
        )
        np.testing.assert_allclose(
            jax.jacrev(f, argnums)(x, y), jax.jacrev(reference, argnums)(x, y), rtol=1e-15
        )
    hessian = jax.hessian(lambda a: jnp.sum(f(a, y)))(x)
    np.testing.assert_allclose(hessian, jax.hessian(lambda a: jnp.sum(reference(a, y)))(x))
    # Only the first argument carries a tangent: the second output's is a symbolic zero.
    _, (dz, dc) = jax.jvp(lambda a: one_kernel(a, jnp.ones(3)), (jnp.ones(3),), (jnp.arange(3.0),))
    np.testing.assert_array_equal(dz, [0.0, 1.0, 2.0])
    np.testing.assert_array_equal(dc, jnp.zeros(3))
    transpose = jax.linear_transpose(lambda a, b: one_kernel(a, b), x, y)
    back = transpose((2.0 * x, 3.0 * y))
    np.testing.assert_array_equal(back[0], 2.0 * x)
    np.testing.assert_array_equal(back[1], 3.0 * y)

    batch = jnp.arange(24.0).reshape(4, 6)
    mapped = jax.vmap(lambda a, b: one_kernel(a, b), in_axes=(1, None))(batch, x[:4])
    np.testing.assert_array_equal(mapped[0], batch.T)
    np.testing.assert_array_equal(mapped[1], jnp.broadcast_to(x[:4], (6, 4)))


def python_loop(q0, samples, dt, num_steps, renormalize_every, frame="world"):
    """The Lie–Euler run written out: q_k = exp(ω_k Δt) ⊗ q_(k−1) (world), renormalised after every
    `renormalize_every`-th step (an independent loop of `from_rotvec` and `multiply`)."""
    q = q0
    for k in range(num_steps):
        r = jq.from_rotvec(samples[k] * dt)
        q = jq.multiply(r, q) if frame == "world" else jq.multiply(q, r)
        if renormalize_every is not None and (k + 1) % renormalize_every == 0:
            q = q / jnp.linalg.norm(q, axis=-1, keepdims=True)
    return q


@pytest.mark.parametrize(
    ("num_steps", "renormalize_every"),
    [(1, None), (UNROLL, 3), (UNROLL + 1, None), (23, 5), (23, 1), (3 * UNROLL, UNROLL), (20, 12)],
)
def test_groups_of_steps_and_renormalisation_boundaries(num_steps, renormalize_every, getkey):
    """Runs shorter than a group, a group plus one step, renormalisation every step, every 3, 5 and
    12 steps (not multiples of the group) and at group ends: the final state, its gradient w.r.t.
    the samples and q₀ (reverse mode: the adjoint, whose groups run backwards) and its jvp (forward
    mode) equal the Python loop's, for a non-unit q₀."""
    q0 = random_unit(getkey(), (5,)) * jnp.linspace(0.5, 1.5, 5)[:, None]
    samples = 3.0 * jax.random.normal(getkey(), (num_steps, 5, 3))
    dt = 0.03
    target = random_unit(getkey(), (5,))

    def fast(w, q):
        final = jq.integrate(
            q, jq.sampled(w, dt), dt, num_steps, renormalize_every=renormalize_every, save="final"
        )
        return jnp.sum(jq.multiply(jq.conjugate(target), final)[..., 1:] ** 2), final

    def loop(w, q):
        final = python_loop(q, w, dt, num_steps, renormalize_every)
        return jnp.sum(jq.multiply(jq.conjugate(target), final)[..., 1:] ** 2), final

    (value, final), grads = jax.jit(jax.value_and_grad(fast, (0, 1), has_aux=True))(samples, q0)
    (value_ref, final_ref), grads_ref = jax.value_and_grad(loop, (0, 1), has_aux=True)(samples, q0)
    np.testing.assert_allclose(final, final_ref, rtol=0, atol=1e-14)
    np.testing.assert_allclose(value, value_ref, rtol=1e-13)
    for g, g_ref in zip(grads, grads_ref, strict=True):
        np.testing.assert_allclose(g, g_ref, rtol=0, atol=1e-12 * float(jnp.max(jnp.abs(g_ref))))
    direction = jax.random.normal(getkey(), samples.shape)
    tangent = jax.jit(lambda w: jax.jvp(lambda v: fast(v, q0)[1], (w,), (direction,))[1])(samples)
    tangent_ref = jax.jvp(lambda v: loop(v, q0)[1], (samples,), (direction,))[1]
    np.testing.assert_allclose(tangent, tangent_ref, rtol=0, atol=1e-12)


@pytest.mark.parametrize("frame", ["world", "body"])
def test_series_and_its_fallback_either_side_of_the_threshold(frame):
    """The run takes the series while every step has θ² ≤ `SERIES_MAX_THETA_SQ` and falls back to
    sin/cos as soon as one step of one body exceeds it: just below and just above the threshold (the
    largest step in the last body), the result is SciPy's composition of the step rotations, and the
    gradient equals AD through the Python loop."""
    num_steps, bodies, dt = 17, 4, 0.1
    rng = np.random.default_rng(3)
    directions = rng.normal(size=(num_steps, bodies, 3))
    directions /= np.linalg.norm(directions, axis=-1, keepdims=True)
    q0 = jnp.asarray(Rotation.random(bodies, random_state=4).as_quat(scalar_first=True))
    target = jnp.asarray(Rotation.random(bodies, random_state=5).as_quat(scalar_first=True))
    for factor in (1.0 - 1e-9, 1.0 + 1e-9):
        angles = rng.uniform(0.05, 0.3, size=(num_steps, bodies))
        angles[11, -1] = np.sqrt(SERIES_MAX_THETA_SQ) * factor  # θ of the largest step
        samples = jnp.asarray(directions * angles[..., None] / dt)
        final = jax.jit(
            lambda w: jq.integrate(q0, jq.sampled(w, dt), dt, num_steps, frame=frame, save="final")
        )(samples)
        expected = Rotation.from_quat(np.asarray(q0), scalar_first=True)
        for k in range(num_steps):
            step = Rotation.from_rotvec(np.asarray(samples[k]) * dt)
            expected = step * expected if frame == "world" else expected * step
        np.testing.assert_allclose(
            final, expected.as_quat(scalar_first=True, canonical=False), rtol=0, atol=1e-14
        )

        def loss(w, run):
            return jnp.sum(jq.multiply(jq.conjugate(target), run(w))[..., 1:] ** 2)

        def fast(w):
            return jq.integrate(q0, jq.sampled(w, dt), dt, num_steps, frame=frame, save="final")

        grad = jax.jit(jax.grad(lambda w: loss(w, fast)))(samples)
        grad_ref = jax.grad(
            lambda w: loss(w, lambda v: python_loop(q0, v, dt, num_steps, None, frame))
        )(samples)
        np.testing.assert_allclose(grad, grad_ref, rtol=0, atol=1e-13)


def angle_error(got, expected):
    """Largest rotation angle (rad) between two batches of quaternions (normalised), in float64."""
    got, expected = (np.asarray(q, np.float64) for q in (got, expected))
    got, expected = (q / np.linalg.norm(q, axis=-1, keepdims=True) for q in (got, expected))
    cosine = np.abs(np.sum(got * expected, axis=-1))
    return float(np.max(2.0 * np.arccos(np.clip(cosine, 0.0, 1.0))))


def assert_float32_gradient_matches_float64(loss, *args):
    """`jax.grad` of `loss(*args, dtype)` w.r.t. every argument: float32's (from the float32 args)
    within 1e-4 of the largest float64 component of float64's (from the same values in float64)."""
    where = tuple(range(len(args)))
    g32 = jax.jit(jax.grad(lambda *a: loss(*a, jnp.float32), where))(*args)
    g64 = jax.jit(jax.grad(lambda *a: loss(*a, jnp.float64), where))(
        *(a.astype(jnp.float64) for a in args)
    )
    for a, b in zip(g32, g64, strict=True):
        assert a.dtype == jnp.float32
        np.testing.assert_allclose(a, b, rtol=0, atol=1e-4 * float(jnp.max(jnp.abs(b))))


@pytest.mark.parametrize("given", ["sampled", "constant"])
@pytest.mark.parametrize(
    ("frame", "renormalize_every", "step_angle"),
    [("world", None, 2e-5), ("body", 1000, 2e-5), ("world", 1000, 0.8)],
)
def test_float32_default_compensated_final_state_is_fast_and_as_accurate(
    given, frame, renormalize_every, step_angle
):
    """float32 states default to the compensated (Kahan) long-run mode, whose final state now runs
    on the fast paths (kernels of grouped steps; for a constant ω the powers of the step, by their
    increments) instead of the general scan (14–50× slower). A constant ω, as an array or as
    samples, has the closed form exp(T Δt ω) ⊗ q₀ (SciPy, in float64): the fast compensated run
    stays within float32 resolution of it where the uncompensated one drifts, and agrees with the
    general compensated scan (ω through a callable). At 0.8 rad a step the sampled run takes sin/cos
    instead of the series."""
    num_steps, bodies, dt = 6000, 16, 0.01
    rng = np.random.default_rng(11)
    axes = rng.normal(size=(bodies, 3))
    axes /= np.linalg.norm(axes, axis=-1, keepdims=True)
    omega = jnp.asarray(
        axes * rng.uniform(0.5, 1.0, size=(bodies, 1)) * (step_angle / dt), jnp.float32
    )
    samples = jnp.broadcast_to(omega, (num_steps, bodies, 3))
    start = Rotation.random(bodies, random_state=12)
    q0 = jnp.asarray(start.as_quat(scalar_first=True), jnp.float32)
    h = jnp.float32(dt)
    # The closed form for the float32 ω and step as given.
    step = Rotation.from_rotvec(np.asarray(omega, np.float64) * float(h) * num_steps)
    exact = (step * start if frame == "world" else start * step).as_quat(scalar_first=True)
    options = dict(frame=frame, renormalize_every=renormalize_every, save="final")
    rate = jq.sampled(samples, h) if given == "sampled" else omega

    def run(compensated=None):
        return jq.integrate(q0, rate, h, num_steps, compensated=compensated, **options)

    assert "jaxquat_one_kernel" in str(jax.make_jaxpr(run)())  # the fast path's kernels
    fast = jax.jit(run)()
    assert fast.dtype == jnp.float32
    plain = jax.jit(lambda: run(False))()
    general = jax.jit(lambda: jq.integrate(q0, lambda t, q: omega, h, num_steps, **options))()
    # Resolution: a float32 unit quaternion resolves ~1.2e-7 rad; the rounding of each step's angle
    # (ω Δt and the exponential, about two ulps) adds up to T · θ · 2⁻²³.
    resolution = 4e-7 + num_steps * step_angle * 1.2e-7
    assert angle_error(fast, exact) <= resolution
    assert angle_error(fast, general) <= resolution
    if step_angle < 0.1:  # small steps: without compensation the rounding of 1 + δ accumulates
        assert angle_error(plain, exact) > 5 * angle_error(fast, exact)


@pytest.mark.parametrize(("frame", "renormalize_every"), [("world", None), ("body", 1000)])
def test_float32_default_compensated_trajectory_of_a_constant_omega(frame, renormalize_every):
    """`save="all"` with a constant ω in float32's default compensated mode takes the blocked fast
    path (two short scans of power tables, compensated: (a − 1, b) advanced by Kahan-summed
    increments, block rows rescaled to unit norm when renormalising) instead of a scan over every
    step. Every saved state is within float32 resolution of the closed form exp(k Δt ω) ⊗ q₀ (SciPy,
    float64) and of the general compensated scan, the norm stays within 4e-7 of 1 when
    renormalising, and the gradient w.r.t. ω and q₀ matches float64's."""
    num_steps, bodies, dt, step_angle = 6000, 8, 0.01, 2e-4
    rng = np.random.default_rng(21)
    axes = rng.normal(size=(bodies, 3))
    axes /= np.linalg.norm(axes, axis=-1, keepdims=True)
    omega = jnp.asarray(
        axes * rng.uniform(0.5, 1.0, size=(bodies, 1)) * (step_angle / dt), jnp.float32
    )
    start = Rotation.random(bodies, random_state=22)
    q0 = jnp.asarray(start.as_quat(scalar_first=True), jnp.float32)
    h = jnp.float32(dt)
    options = dict(frame=frame, renormalize_every=renormalize_every, save="all")

    def run(w=omega, q=q0):
        return jq.integrate(q, w, h, num_steps, **options)

    assert f"length={num_steps}" not in str(jax.make_jaxpr(run)())  # no scan over the steps
    fast = jax.jit(run)()
    assert fast.dtype == jnp.float32 and fast.shape == (num_steps + 1, bodies, 4)
    general = jax.jit(lambda: jq.integrate(q0, lambda t, q: omega, h, num_steps, **options))()
    ks = np.arange(0, num_steps + 1, 500)
    rotvecs = np.asarray(omega, np.float64) * float(h)
    resolution = 4e-7 + num_steps * step_angle * 1.2e-7
    for k in ks:
        step = Rotation.from_rotvec(rotvecs * k)
        exact = (step * start if frame == "world" else start * step).as_quat(scalar_first=True)
        assert angle_error(fast[k], exact) <= resolution
        assert angle_error(fast[k], general[k]) <= resolution
    if renormalize_every is not None:
        norms = np.linalg.norm(np.asarray(fast[renormalize_every:], np.float64), axis=-1)
        assert np.max(np.abs(norms - 1.0)) <= 4e-7
    target = jnp.asarray(Rotation.random(bodies, random_state=23).as_quat(scalar_first=True))

    def loss(w, q, dtype):
        path = jq.integrate(
            q.astype(dtype), w.astype(dtype), h.astype(dtype), num_steps, **options
        )[::600]
        return jnp.sum((path * target.astype(dtype)[None]) ** 2)

    assert_float32_gradient_matches_float64(loss, omega, q0)


@pytest.mark.parametrize(
    ("frame", "renormalize_every", "stride", "step_angle"),
    [
        ("world", None, 1, 2e-4),
        ("body", 1000, 1, 2e-4),
        ("world", 1000, 2, 2e-4),  # samples at Δt/2, step k holds sample 2k: the off-grid lookup
        ("body", 1000, 1, 0.8),  # too large for the series: sin/cos
    ],
)
def test_float32_default_compensated_trajectory_of_sampled_omega(
    frame, renormalize_every, stride, step_angle
):
    """`save="all"` with sampled ω in float32's default compensated mode runs on the fast path (one
    kernel a step carrying q and its Kahan compensation) instead of the general scan. The reference
    is SciPy's float64 composition of the same step rotations exp(Δt ω_k) (the Lie–Euler step with
    a held sample is exact), checked every 500 steps: the fast run stays within float32 resolution
    of it and of the general compensated scan (ω through a callable), the uncompensated run drifts
    5× further at small steps, |q| stays within 4e-7 of 1 when renormalising, and the float32
    gradient w.r.t. the samples and q₀ matches float64's."""
    num_steps, bodies, dt = 6000, 8, 0.01
    rng = np.random.default_rng(31)
    directions = rng.normal(size=(num_steps * stride, bodies, 3))
    directions /= np.linalg.norm(directions, axis=-1, keepdims=True)
    # A slowly turning rate, so that the steps differ but do not cancel.
    drift = np.cumsum(0.05 * directions, axis=0) + rng.normal(size=(1, bodies, 3))
    drift /= np.linalg.norm(drift, axis=-1, keepdims=True)
    samples = jnp.asarray(drift * (step_angle / dt), jnp.float32)
    start = Rotation.random(bodies, random_state=32)
    q0 = jnp.asarray(start.as_quat(scalar_first=True), jnp.float32)
    h = jnp.float32(dt)
    options = dict(frame=frame, renormalize_every=renormalize_every, save="all")

    def run(s=samples, q=q0, compensated=None):
        return jq.integrate(
            q, jq.sampled(s, h / stride), h, num_steps, compensated=compensated, **options
        )

    assert "jaxquat_one_kernel" in str(jax.make_jaxpr(run)())  # the fast path's kernels
    fast = jax.jit(run)()
    assert fast.dtype == jnp.float32 and fast.shape == (num_steps + 1, bodies, 4)
    plain = jax.jit(lambda: run(compensated=False))()

    def held(t, q):
        return samples[jnp.round(t / h).astype(jnp.int32) * stride]

    general = jax.jit(lambda: jq.integrate(q0, held, h, num_steps, **options))()
    rotvecs = np.asarray(samples, np.float64) * float(h)
    exact, orientation = {}, start
    for k in range(num_steps + 1):
        if k % 500 == 0:
            exact[k] = orientation.as_quat(scalar_first=True)
        if k < num_steps:
            turn = Rotation.from_rotvec(rotvecs[k * stride])
            orientation = turn * orientation if frame == "world" else orientation * turn
    resolution = 4e-7 + num_steps * step_angle * 1.2e-7
    worst = max(angle_error(fast[k], expected) for k, expected in exact.items())
    assert worst <= resolution
    assert max(angle_error(fast[k], general[k]) for k in exact) <= resolution
    if step_angle < 0.1:
        assert max(angle_error(plain[k], expected) for k, expected in exact.items()) > 5 * worst
    if renormalize_every is not None:
        norms = np.linalg.norm(np.asarray(fast[renormalize_every:], np.float64), axis=-1)
        # Each renormalisation resets |q|; in between it drifts by the steps' rounding (≈ ε θ).
        assert np.max(np.abs(norms - 1.0)) <= 4e-7 + renormalize_every * step_angle * 1.2e-7
    target = jnp.asarray(Rotation.random(bodies, random_state=33).as_quat(scalar_first=True))

    def loss(s, q, dtype):
        path = jq.integrate(
            q.astype(dtype),
            jq.sampled(s.astype(dtype), (h / stride).astype(dtype)),
            h.astype(dtype),
            num_steps,
            **options,
        )[::600]
        return jnp.sum((path * target.astype(dtype)[None]) ** 2)

    assert_float32_gradient_matches_float64(loss, samples, q0)


@pytest.mark.parametrize("dtype", [jnp.float32, jnp.float64])
@pytest.mark.parametrize("unused", [np.nan, np.inf, 1e30])
def test_trajectory_gradient_ignores_a_sample_the_run_does_not_use(dtype, unused):
    """More samples than steps, the first unused one non-finite or huge: `save="all"` with sampled ω
    must not read it, not even in the loop's last, discarded iteration, where reverse mode would
    multiply its NaN derivative by a zero cotangent and spread NaN through every step. Gradients
    w.r.t. the samples and q₀ agree with the general scan's (ω through a callable) and with central
    finite differences (float64)."""
    num_steps, dt = 4, 0.1
    rng = np.random.default_rng(41)
    given = rng.normal(size=(num_steps + 2, 2, 3))
    given[num_steps] = unused
    samples = jnp.asarray(given, dtype)
    q0 = jnp.asarray(Rotation.random(2, random_state=42).as_quat(scalar_first=True), dtype)
    weights = jnp.asarray(rng.normal(size=(num_steps + 1, 2, 4)), dtype)
    rate = jq.sampled(samples, dt)

    def loss(s, q, general=False):
        omega = jq.sampled(s, dt)
        if general:
            omega = lambda t, q, omega=omega: omega(t, q)  # noqa: E731
        return jnp.sum(jq.integrate(q, omega, dt, num_steps, save="all") * weights)

    assert "jaxquat_one_kernel" in str(jax.make_jaxpr(loss)(rate.omegas, q0))
    fast = jax.grad(loss, (0, 1))(samples, q0)
    general = jax.grad(lambda s, q: loss(s, q, True), (0, 1))(samples, q0)
    tolerance = 2e-5 if dtype == jnp.float32 else 1e-13
    for got, expected in zip(fast, general, strict=True):
        assert np.all(np.isfinite(np.asarray(got)))
        np.testing.assert_allclose(got, expected, rtol=0, atol=tolerance)
    assert not np.any(np.asarray(fast[0][num_steps:]))  # unused samples: zero cotangent
    if dtype == jnp.float64:
        eps = 1e-6
        bump = np.zeros(given.shape)
        bump[1, 0, 2] = eps
        difference = (loss(samples + bump, q0) - loss(samples - bump, q0)) / (2 * eps)
        assert abs(float(fast[0][1, 0, 2]) - float(difference)) <= 1e-8
