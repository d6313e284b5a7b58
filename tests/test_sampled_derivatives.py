"""Derivatives of `integrate` with sampled ω, euler, save="final" (`_fastpath._sampled_final`).

Forward mode runs a tangent scan and reverse mode an adjoint scan that steps back through the run with
the inverse rotations (nothing stored per step). Both are checked against AD through an independent
plain scan of exact steps (`from_rotvec` ⊗ q, renormalising like `integrate`), and against AD through
the general checkpointed scan for a long run.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from helpers import random_unit
from jax import lax

import jaxquat as jq

STEPS, DT = 30, 0.07


def naive(q, samples, h, frame, renormalize_every, indices=None):
    """q_k = exp(ω_(i_k) h) ⊗ q_(k−1) (world) or q_(k−1) ⊗ exp(ω_(i_k) h) (body), renormalised after
    every `renormalize_every`-th step, as a plain `lax.scan` differentiated by JAX's own rules.

    (A Python loop of the same steps gave the same derivatives, to 1e-15, but its second derivatives
    took 10–13 s each to evaluate against 3–4.5 s for the scan: the suite's slowest tests.)"""
    indices = jnp.arange(STEPS) if indices is None else jnp.asarray(indices)

    def step(q, k_and_i):
        k, i = k_and_i
        r = jq.from_rotvec(samples[i] * h)
        q = jq.multiply(r, q) if frame == "world" else jq.multiply(q, r)
        if renormalize_every is not None:
            due = (k + 1) % renormalize_every == 0
            q = jnp.where(due, q / jnp.linalg.norm(q, axis=-1, keepdims=True), q)
        return q, None

    return lax.scan(step, q, (jnp.arange(indices.shape[0]), indices))[0]


def problem(key, case):
    """q₀ with norms 1.7, 1, 0.6 and samples either all small (series branch) or large with a body at
    rest and one step of nearly π (exact branch)."""
    k1, k2 = jax.random.split(key)
    q0 = random_unit(k1, (3,)) * jnp.array([[1.7], [1.0], [0.6]])
    samples = (0.5 if case == "series" else 8.0) * jax.random.normal(k2, (STEPS, 3, 3))
    if case == "exact":
        samples = samples.at[:, 1].set(0.0)
        samples = samples.at[3, 2].set(jnp.array([np.pi - 1e-3, 0.0, 0.0]) / DT)
    return q0, samples


@pytest.mark.parametrize(
    ("frame", "renormalize_every", "case"),
    [
        ("world", None, "series"),
        ("body", 7, "series"),
        ("world", 7, "exact"),
        ("body", 30, "exact"),
        ("body", None, "exact"),
    ],
)
def test_first_derivatives_match_a_naive_loop(frame, renormalize_every, case, getkey):
    """Values, and jacfwd and jacrev w.r.t. q₀ (non-unit), the samples and Δt, equal AD through the
    naive loop, in both frames, with renormalisation never, every 7 steps (4 times plus a tail) and
    at the last step, for small steps (series) and large ones (exact sin/cos, a body at rest, a step
    of π − 1e-3)."""
    q0, samples = problem(getkey(), case)

    def fast(q, w, h):
        return jq.integrate(
            q,
            jq.sampled(w, DT),
            h,
            STEPS,
            save="final",
            frame=frame,
            renormalize_every=renormalize_every,
        )

    def reference(q, w, h):
        return naive(q, w, h, frame, renormalize_every)

    args = (q0, samples, jnp.asarray(DT))
    np.testing.assert_allclose(fast(*args), reference(*args), atol=1e-14)
    expected = jax.jacrev(reference, argnums=(0, 1, 2))(*args)
    for transform in (jax.jacfwd, jax.jacrev):
        got = jax.jit(transform(fast, argnums=(0, 1, 2)))(*args)
        for g, e in zip(got, expected, strict=True):
            np.testing.assert_allclose(g, e, atol=1e-13 * max(float(jnp.max(jnp.abs(e))), 1.0))


def test_second_derivatives_match_a_naive_loop(getkey):
    """Second directional derivatives uᵀ H v of a fitting loss w.r.t. the samples, by all four
    compositions of forward and reverse mode, equal the naive loop's (the custom linear map's own
    derivative rules, not a fallback)."""
    q0, samples = problem(getkey(), "exact")
    target = random_unit(getkey(), (3,))
    u, v = jax.random.normal(getkey(), (2,) + samples.shape)

    def loss(final):
        def value(w):
            q = final(q0, w, DT)
            return jnp.sum(jq.multiply(jq.conjugate(target), q)[..., 1:] ** 2)

        return value

    def fast(q, w, h):
        return jq.integrate(
            q, jq.sampled(w, DT), h, STEPS, save="final", frame="body", renormalize_every=7
        )

    f = loss(fast)
    reference = loss(lambda q, w, h: naive(q, w, h, "body", 7))
    expected = jnp.vdot(u, jax.jvp(jax.grad(reference), (samples,), (v,))[1])
    assert abs(float(expected)) > 1e-3

    def along(g):  # w ↦ ⟨u, g(w)⟩
        return lambda w: jnp.vdot(u, g(w))

    def forward(w):  # w ↦ the directional derivative along v
        return jax.jvp(f, (w,), (v,))[1]

    results = {
        "forward over reverse": jax.jvp(along(jax.grad(f)), (samples,), (v,))[1],
        "reverse over reverse": jnp.vdot(v, jax.grad(along(jax.grad(f)))(samples)),
        "reverse over forward": jnp.vdot(u, jax.grad(forward)(samples)),
        "forward over forward": jax.jvp(forward, (samples,), (u,))[1],
    }
    for name, value in results.items():
        np.testing.assert_allclose(value, expected, rtol=1e-12, err_msg=name)


def test_reverse_over_reverse_of_a_loss_linear_in_the_final_state(getkey):
    """A loss linear in q_T (one component, a fixed dot product) has a constant cotangent, which once
    left the transposed linear map with an untied slot: reverse over reverse failed with an
    AssertionError inside JAX. uᵀ H v w.r.t. the samples and d²/dΔt², by reverse over reverse, equal
    the naive loop's."""
    q0, samples = problem(getkey(), "series")
    weights = jax.random.normal(getkey(), q0.shape)
    u, v = jax.random.normal(getkey(), (2,) + samples.shape)

    def fast(w, h):
        return jq.integrate(q0, jq.sampled(w, DT), h, STEPS, save="final", renormalize_every=7)

    losses = {
        "one component": lambda final: lambda w, h: final(w, h)[0, 1],
        "dot product": lambda final: lambda w, h: jnp.sum(weights * final(w, h)),
    }
    h = jnp.asarray(DT)
    for name, loss in losses.items():
        f = loss(fast)
        reference = loss(lambda w, h: naive(q0, w, h, "world", 7))
        expected = jnp.vdot(
            u, jax.jvp(lambda w, r=reference: jax.grad(r)(w, h), (samples,), (v,))[1]
        )
        assert abs(float(expected)) > 1e-3
        along = jax.grad(lambda w, f=f: jnp.vdot(u, jax.grad(f)(w, h)))(samples)
        np.testing.assert_allclose(jnp.vdot(v, along), expected, rtol=1e-12, err_msg=name)
        second = jax.grad(jax.grad(f, argnums=1), argnums=1)(samples, h)
        want = jax.grad(jax.grad(reference, argnums=1), argnums=1)(samples, h)
        np.testing.assert_allclose(second, want, rtol=1e-12, err_msg=name)


def test_mixed_second_derivatives_match_a_naive_loop(getkey):
    """Mixed second derivatives, reverse mode w.r.t. the samples over forward mode w.r.t. q₀ or Δt
    (and forward over reverse for q₀), equal the naive loop's. Reverse over forward once failed with
    an AssertionError inside JAX: the linear map's q₀ and Δt slots were tied to their own primal only
    and had no tangent w.r.t. the samples. (Each composition compiles for ~10 s: only these.)"""
    q0, samples = problem(getkey(), "exact")
    target = random_unit(getkey(), (3,))
    u = jax.random.normal(getkey(), samples.shape)
    directions = {"q0": jax.random.normal(getkey(), q0.shape), "h": jnp.asarray(0.7)}
    h = jnp.asarray(DT)

    def loss(final):
        def value(q, w, h):
            return jnp.sum(jq.multiply(jq.conjugate(target), final(q, w, h))[..., 1:] ** 2)

        return value

    def fast(q, w, h):
        return jq.integrate(q, jq.sampled(w, DT), h, STEPS, save="final", renormalize_every=7)

    f = loss(fast)
    reference = loss(lambda q, w, h: naive(q, w, h, "world", 7))

    def forward(g, a):  # w ↦ ∂g/∂a along the direction of a (a = "q0" or "h")
        def derivative(w):
            if a == "q0":
                return jax.jvp(lambda q: g(q, w, h), (q0,), (directions[a],))[1]
            return jax.jvp(lambda s: g(q0, w, s), (h,), (directions[a],))[1]

        return derivative

    expected = {}
    for a in ("q0", "h"):
        expected[a] = jnp.vdot(u, jax.grad(forward(reference, a))(samples))
        assert abs(float(expected[a])) > 1e-4, a
        value = jax.jit(lambda w, a=a: jnp.vdot(u, jax.grad(forward(f, a))(w)))(samples)
        np.testing.assert_allclose(
            value, expected[a], rtol=1e-11, err_msg=f"reverse over forward, {a}"
        )
    along = jax.jit(
        lambda q: jax.jvp(
            lambda x: jnp.vdot(u, jax.grad(f, argnums=1)(x, samples, h)), (q,), (directions["q0"],)
        )[1]
    )(q0)
    np.testing.assert_allclose(along, expected["q0"], rtol=1e-11, err_msg="forward over reverse")


@pytest.mark.parametrize("frame", ["world", "body"])
@pytest.mark.parametrize("renormalize_every", [None, 100])
def test_gradient_at_a_zero_or_badly_scaled_initial_state(frame, renormalize_every, getkey):
    """q₀ = 0 (a padded body) without renormalisation: the adjoint's λ₀ = p₀ ⊗ q₀/|q₀|² was 0/0 (NaN)
    although q_T = Q ⊗ q₀ has the finite gradient Q̄ ⊗ λ_T; now equal to the naive loop's and to
    forward mode. float32 q₀ of length 1e±20 (|q₀|² overflows or underflows): finite and equal to
    the float64 gradient."""
    q0 = random_unit(getkey(), (3,)).at[1].set(0.0) * jnp.array([[1.0], [1.0], [0.6]])
    samples = 0.8 * jax.random.normal(getkey(), (STEPS, 3, 3))
    weights = jax.random.normal(getkey(), (3, 4))
    every = renormalize_every

    def loss(final):
        return lambda q, w: jnp.sum(weights * final(q, w)) + jnp.sum(final(q, w) ** 2)

    def fast(q, w, **options):
        return jq.integrate(
            q,
            jq.sampled(w, DT),
            DT,
            STEPS,
            save="final",
            frame=frame,
            renormalize_every=every,
            **options,
        )

    want = jax.grad(loss(lambda q, w: naive(q, w, DT, frame, None)), argnums=(0, 1))(q0, samples)
    got = jax.grad(loss(fast), argnums=(0, 1))(q0, samples)
    assert float(jnp.max(jnp.abs(want[0][1]))) > 0.1  # the zero body's gradient is not zero
    for g, w in zip(got, want, strict=True):
        np.testing.assert_allclose(g, w, rtol=1e-12, atol=1e-13)
    np.testing.assert_allclose(jax.jacfwd(loss(fast))(q0, samples), want[0], rtol=1e-12, atol=1e-13)

    # float32 at lengths 1e20 and 1e-20 (the fast path: compensated=False); a loss linear in q_T
    for length in (1e20, 1e-20):
        start = (q0 * length).at[1].set(q0[0] * length)

        def linear(q, w, options=None):
            return jnp.sum(weights.astype(q.dtype) * fast(q, w, **(options or {})))

        single = jax.grad(linear)(
            start.astype(jnp.float32), samples.astype(jnp.float32), {"compensated": False}
        )
        double = jax.grad(linear)(start, samples)
        assert bool(jnp.all(jnp.isfinite(single))), length
        np.testing.assert_allclose(single, double, rtol=2e-5, atol=1e-5, err_msg=str(length))


@pytest.mark.parametrize("save", ["final", "all"])
def test_empty_batch_and_non_finite_samples(save):
    """No bodies: an empty result of the right shape (as with a constant or callable ω), not an error
    from the run-wide series test. A NaN or inf sample makes the affected body's result NaN, as the
    general scan's (the series test then falls to exact sin/cos)."""
    out = jq.integrate(jnp.ones((0, 4)), jq.sampled(jnp.ones((5, 0, 3)), DT), DT, 5, save=save)
    assert out.shape == ((0, 4) if save == "final" else (6, 0, 4))
    q0 = jq.normalize(jnp.array([[1.0, 0.2, 0.0, 0.0], [0.3, 0.0, 1.0, 0.0]]))
    for bad in [np.nan, np.inf]:
        samples = jnp.full((5, 2, 3), 0.1).at[2, 1, 0].set(bad)
        out = jq.integrate(q0, jq.sampled(samples, DT), DT, 5, save=save)
        final = out if save == "final" else out[-1]
        assert np.all(np.isfinite(final[0])) and np.all(np.isnan(final[1]))


def test_held_samples_off_the_grid(getkey):
    """Samples on a coarser grid than the steps (each held for two steps, from a shifted start): the
    gradient w.r.t. a sample sums over the steps that use it, and equals the naive loop's; vmap over
    bodies of the per-body gradient agrees."""
    q0, samples = problem(getkey(), "exact")
    samples = samples / 4.0
    sample_dt, t0 = 2 * DT, 0.5 * DT
    # The module's zero-order hold: step k at t0 + k·dt uses sample ⌊(t0 + k·dt)/sample_dt⌋.
    indices = [int(np.floor((t0 + k * DT) / sample_dt + 1e-9)) for k in range(STEPS)]
    assert indices[:4] == [0, 0, 1, 1]
    target = random_unit(getkey(), (3,))

    def fast(w, q=q0, t=target):
        final = jq.integrate(q, jq.sampled(w, sample_dt), DT, STEPS, t0=t0, save="final")
        return jnp.sum(jq.multiply(jq.conjugate(t), final)[..., 1:] ** 2)

    def reference(w):
        final = naive(q0, w, DT, "world", 1000, indices)
        return jnp.sum(jq.multiply(jq.conjugate(target), final)[..., 1:] ** 2)

    np.testing.assert_allclose(fast(samples), reference(samples), rtol=1e-13)
    expected = jax.grad(reference)(samples)
    np.testing.assert_allclose(jax.jit(jax.grad(fast))(samples), expected, atol=1e-12)
    np.testing.assert_allclose(jax.jit(jax.jacfwd(fast))(samples), expected, atol=1e-12)
    per_body = jax.vmap(jax.grad(fast), in_axes=(1, 0, 0), out_axes=1)(samples, q0, target)
    np.testing.assert_allclose(per_body, expected, atol=1e-12)


def test_long_run_gradient_matches_the_general_scan(getkey):
    """5,000 steps of about a radian each: the adjoint reconstructs the states by stepping back, so its
    round-off grows with T; the gradient still equals AD through the general checkpointed scan (the
    same samples given as a callable ω) to 1e-11 relative."""
    steps, dt = 5000, 0.1
    q0 = random_unit(getkey(), (3,))
    samples = 10.0 * jax.random.normal(getkey(), (steps, 3, 3))
    target = random_unit(getkey(), (3,))

    def loss(w, source):
        final = jq.integrate(q0, source(w), dt, steps, save="final")
        return jnp.sum(jq.multiply(jq.conjugate(target), final)[..., 1:] ** 2)

    def as_callable(w):
        s = jq.sampled(w, dt)
        return lambda t, q: s(t)

    fast = jax.jit(jax.grad(lambda w: loss(w, lambda w: jq.sampled(w, dt))))(samples)
    general = jax.jit(jax.grad(lambda w: loss(w, as_callable)))(samples)
    scale = float(jnp.max(jnp.abs(general)))
    np.testing.assert_allclose(fast, general, atol=1e-11 * scale)


def test_reverse_mode_stores_nothing_per_step():
    """Reverse mode's scratch memory is a small fraction of its output (T × N × 3), not the T × N × 4
    states that AD through a loop keeps (the compiled executable's own accounting)."""
    steps, bodies = 2000, 500
    q0 = jq.identity((bodies,))

    def loss(w):
        return jnp.sum(jq.integrate(q0, jq.sampled(w, 0.01), 0.01, steps, save="final")[..., 0])

    omegas = jax.ShapeDtypeStruct((steps, bodies, 3), jnp.float64)
    stats = jax.jit(jax.grad(loss)).lower(omegas).compile().memory_analysis()
    if stats is None:
        pytest.skip("this backend reports no memory statistics")
    output = steps * bodies * 3 * 8
    assert stats.temp_size_in_bytes < 0.05 * output


@pytest.mark.parametrize("compensated", [False, None])
def test_float32_gradient_matches_float64(compensated, getkey):
    """In float32 the gradient stays within float32 round-off of the float64 one over 200 steps, in
    the plain mode and in the default compensated (Kahan) mode: both take the fast path, whose
    derivative rule (the adjoint of the exact steps) serves both."""
    steps, dt = 200, 0.01
    q0 = random_unit(getkey(), (5,))
    samples = 3.0 * jax.random.normal(getkey(), (steps, 5, 3))
    target = random_unit(getkey(), (5,))

    def loss(w, dtype):
        final = jq.integrate(
            q0.astype(dtype),
            jq.sampled(w.astype(dtype), dt),
            dt,
            steps,
            save="final",
            compensated=compensated if dtype == jnp.float32 else False,
        )
        return jnp.sum(jq.multiply(jq.conjugate(target.astype(dtype)), final)[..., 1:] ** 2)

    g64 = jax.grad(loss)(samples, jnp.float64)
    g32 = jax.grad(lambda w: loss(w, jnp.float32))(samples.astype(jnp.float32))
    assert g32.dtype == jnp.float32
    np.testing.assert_allclose(g32, g64, atol=2e-5 * float(jnp.max(jnp.abs(g64))))


@pytest.mark.parametrize(
    ("samples_shape", "q0_shape"),
    [((3, 3), (3,)), ((5, 3), (3,)), ((3, 3), (5,)), ((4, 2, 3), (5, 1))],
)
@pytest.mark.parametrize("save", ["final", "all"])
def test_samples_broadcast_over_bodies_from_the_right(samples_shape, q0_shape, save, getkey):
    """Samples with fewer batch axes than q₀ broadcast like ω does (batch axes aligned from the right,
    the time axis never paired with a body axis; a review found the fast path did pair them, silently
    when the sample count equalled the number of bodies): values and gradients equal the general
    path's (the same samples as a callable)."""
    steps, dt = 3, 0.2
    samples = 2.0 * jax.random.normal(getkey(), samples_shape)
    q0 = random_unit(getkey(), q0_shape)

    def run(w, general):
        source = jq.sampled(w, dt)
        omega = (lambda t, q: source(t)) if general else source
        return jq.integrate(q0, omega, dt, steps, save=save)

    np.testing.assert_allclose(run(samples, False), run(samples, True), atol=1e-14)
    grads = [jax.grad(lambda w, g=g: jnp.sum(run(w, g) ** 3))(samples) for g in (False, True)]
    np.testing.assert_allclose(grads[0], grads[1], atol=1e-13)
