"""Tests for `simulate_ensemble` and `load_ensemble`: closed forms, chunking, streaming, sharding."""

import json
import os
import subprocess
import sys
import textwrap

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest
from helpers import assert_quat_close, random_unit, run_on_four_devices
from scipy.spatial.transform import Rotation

import jaxquat
from jaxquat import load_ensemble, simulate_ensemble
from jaxquat._cli import main
from jaxquat._ensemble import _default_chunk, _run_chunk


def _ensemble(getkey, n, dtype=jnp.float64, scale=1.0):
    q0 = random_unit(getkey(), (n,), dtype)
    omega = scale * jax.random.normal(getkey(), (n, 3), dtype)
    return q0, omega


def _angle(p, q):
    return np.asarray(jaxquat.angle_between(p, q))


@pytest.mark.parametrize("frame", ["world", "body"])
def test_constant_omega_matches_closed_form(getkey, frame):
    q0, omega = _ensemble(getkey, 257)
    dt, steps = 0.01, 120
    result = simulate_ensemble(
        q0, omega, dt, steps, frame=frame, save_every=40, statistics=True, chunk_size=80
    )

    def exact(t):
        turn = jaxquat.from_rotvec(omega * t)
        return jaxquat.multiply(turn, q0) if frame == "world" else jaxquat.multiply(q0, turn)

    assert_quat_close(result.final, exact(dt * steps), atol=1e-12)
    np.testing.assert_allclose(result.times, [0.0, 0.4, 0.8, 1.2], rtol=0, atol=1e-15)
    assert result.saved.shape == (4, 257, 4)
    for saved, t in zip(result.saved, result.times, strict=True):
        assert_quat_close(saved, exact(t), atol=1e-12)
    # Per-body statistics: path length |ω|T, net and farthest angles from the start.
    speed = np.linalg.norm(np.asarray(omega), axis=-1)
    np.testing.assert_allclose(result.total_angle, speed * dt * steps, rtol=1e-11)
    np.testing.assert_allclose(result.angle_from_start, _angle(q0, exact(dt * steps)), atol=1e-12)
    turn = np.mod(speed[:, None] * dt * np.arange(1, steps + 1), 2 * np.pi)
    farthest = np.max(np.minimum(turn, 2 * np.pi - turn), axis=1)
    np.testing.assert_allclose(result.max_angle_from_start, farthest, atol=1e-11)
    np.testing.assert_array_equal(result.final_omega, omega)


@pytest.mark.parametrize("dtype", [jnp.float64, jnp.float32])
@pytest.mark.parametrize("frame", ["world", "body"])
def test_constant_omega_step_made_once_is_the_per_step_one(getkey, dtype, frame):
    """A constant ω's rotation is made once per chunk, not at every step: the same states as the
    same ω given as a function (evaluated every step) — bit for bit in float64 here — and as
    `integrate` (float32: the Kahan-compensated steps of its general scan, ω given as a function;
    a constant ω array there takes the compensated powers of the step, whose rounding differs),
    and the same statistics, which take the step angle as 2 atan2(|vec r|, |w(r)|) of
    r = q_k* ⊗ q_(k+1), checked against |ω|Δt."""
    q0, omega = _ensemble(getkey, 300, dtype, scale=3.0)
    dt, steps = 0.01, 1200  # past one renormalisation (every 1,000 global steps)
    kwargs = dict(frame=frame, save_every=300, chunk_size=600, statistics=True)
    made_once = simulate_ensemble(q0, omega, dt, steps, **kwargs)
    every_step = simulate_ensemble(q0, lambda t, q: omega, dt, steps, **kwargs)
    rate = (lambda t, q: omega) if dtype == jnp.float32 else omega
    reference = jaxquat.integrate(
        q0, rate, dt, steps, frame=frame, save="final", compensated=dtype == jnp.float32
    )
    atol = 1e-15 if dtype == jnp.float64 else 5e-7
    np.testing.assert_allclose(made_once.saved, every_step.saved, rtol=0, atol=atol)
    np.testing.assert_allclose(made_once.final, reference, rtol=0, atol=max(atol, 2e-14))
    speed = np.linalg.norm(np.asarray(omega, np.float64), axis=-1)
    rtol = 1e-11 if dtype == jnp.float64 else 5e-5  # float32: 1.6e-5 measured
    np.testing.assert_allclose(made_once.total_angle, speed * dt * steps, rtol=rtol)
    np.testing.assert_allclose(made_once.total_angle, every_step.total_angle, rtol=rtol)


def test_statistics_near_a_half_turn_and_their_derivatives():
    """The farthest angle is kept as (|vec r|², |w(r)|) of r = q_start* ⊗ q and turned into an angle
    once, by atan2: exact near π too, where an angle from sin²(θ/2) alone would lose half its digits.
    Bodies turning by 0.1 rad a step reach 3.1 rad (step 31), one reaches π − 1e-9 exactly at its
    last step; one is at rest. The statistics are differentiable, without NaN at rest (the angles'
    |vec r| = 0 there), and match central differences."""
    dt, steps = 0.1, 40
    speeds = np.array([1.0, (np.pi - 1e-9) / (dt * steps), 0.0])
    axes = np.array([[0.0, 0.0, 1.0], [0.6, 0.0, 0.8], [1.0, 0.0, 0.0]])
    q0 = random_unit(jax.random.key(3), (3,))
    result = simulate_ensemble(q0, speeds[:, None] * axes, dt, steps, statistics=True)
    turn = np.mod(speeds[:, None] * dt * np.arange(1, steps + 1), 2 * np.pi)
    farthest = np.max(np.minimum(turn, 2 * np.pi - turn), axis=1)
    np.testing.assert_allclose(result.max_angle_from_start, farthest, rtol=0, atol=2e-13)
    np.testing.assert_allclose(result.total_angle, speeds * dt * steps, rtol=1e-12, atol=1e-300)

    def statistics(omega):
        run = simulate_ensemble(q0, omega, dt, 12, statistics=True)
        return jnp.sum(run.total_angle) + jnp.sum(run.max_angle_from_start)

    omega = jnp.asarray(0.5 * axes)
    omega = omega.at[2].set(0.0)
    gradient = jax.grad(statistics)(omega)
    assert np.all(np.isfinite(gradient))
    # d/dω of (total + farthest) = 2·12·dt·ω/|ω| for a body at constant ω (both are 12·dt·|ω|).
    expected = (
        2
        * 12
        * dt
        * np.asarray(omega)
        / np.maximum(np.linalg.norm(np.asarray(omega), axis=-1, keepdims=True), 1e-300)
    )
    np.testing.assert_allclose(gradient[:2], expected[:2], rtol=1e-9, atol=1e-14)
    np.testing.assert_allclose(gradient[2], 0.0, atol=0)  # at rest: the minimum-norm subgradient
    h = 1e-6
    for i in range(2):
        for j in range(3):
            step = jnp.zeros_like(omega).at[i, j].set(h)
            difference = (statistics(omega + step) - statistics(omega - step)) / (2 * h)
            np.testing.assert_allclose(gradient[i, j], difference, rtol=1e-6, atol=1e-8)


@pytest.mark.parametrize(
    ("dtype", "first", "second"), [(jnp.float64, 1e-8, 1e-12), (jnp.float32, 3e-4, 1e-6)]
)
def test_farthest_angle_tells_apart_two_visits_near_a_half_turn(dtype, first, second):
    """A body turns to π − first, back to the start, then to π − second (closer to π). Chosen by
    sin²(θ/2) alone the two visits round to the same value and the first was kept: a review saw
    max_angle_from_start = π − 1e-8 with angle_from_start = π − 1e-12. Compared by tan²(θ/2) the
    farthest is the last visit, as the body's own angle from the start says."""
    turns = np.array([np.pi - first, -(np.pi - first), np.pi - second])

    def omega(t, q):
        k = jnp.clip(jnp.round(t).astype(jnp.int32), 0, 2)
        rate = jnp.asarray([0.0, 0.0, 1.0], q.dtype) * jnp.asarray(turns, q.dtype)[k]
        return jnp.broadcast_to(rate, q.shape[:-1] + (3,))

    q0 = jnp.asarray([[1.0, 0.0, 0.0, 0.0]], dtype)
    result = simulate_ensemble(q0, omega, 1.0, 3, statistics=True)
    final = float(result.angle_from_start[0])
    assert np.pi - final < 10 * second
    assert float(result.max_angle_from_start[0]) == final


def test_rigid_bodies_match_simulate_rigid_body(getkey):
    q0, omega = _ensemble(getkey, 64)
    inertia = jnp.array([1.0, 2.0, 3.5])
    result = simulate_ensemble(q0, omega, 0.02, 60, inertia=inertia, save_every=20, chunk_size=20)
    qs, omegas = jaxquat.simulate_rigid_body(q0, omega, inertia, 0.02, 60, save_every=20)
    np.testing.assert_array_equal(result.saved, qs)
    np.testing.assert_array_equal(result.saved_omega, omegas)
    # World-frame rates and per-body inertia matrices (angular momentum is conserved in the world).
    matrices = jnp.broadcast_to(jnp.diag(inertia), (64, 3, 3))
    world = simulate_ensemble(q0, omega, 0.02, 60, inertia=matrices, frame="world", chunk_size=25)
    q_ref, w_ref = jaxquat.simulate_rigid_body(
        q0, omega, inertia, 0.02, 60, frame="world", save="final"
    )
    np.testing.assert_allclose(world.final, q_ref, atol=1e-13)
    np.testing.assert_allclose(world.final_omega, w_ref, atol=1e-12)

    def momentum(q, w):
        body = jaxquat.rotate(w, jaxquat.conjugate(q))
        return jaxquat.rotate(inertia[None] * body, q)

    np.testing.assert_allclose(
        momentum(world.final, world.final_omega), momentum(q0, omega), atol=1e-5
    )


@pytest.mark.parametrize("method", ["magnus4", "magnus8", "cf4"])
def test_time_dependent_omega_chunked_equals_unchunked_and_integrate(getkey, method):
    q0, _ = _ensemble(getkey, 33)
    rates = jax.random.normal(getkey(), (33, 3))

    def omega(t, q):
        return rates * jnp.cos(1.3 * t)

    kwargs = dict(method=method, t0=0.25, save_every=8, statistics=True)
    whole = simulate_ensemble(q0, omega, 0.05, 48, chunk_size=48, **kwargs)
    pieces = simulate_ensemble(q0, omega, 0.05, 48, chunk_size=16, **kwargs)
    assert pieces.num_chunks == 3 and whole.num_chunks == 1
    for field in ("final", "saved", "total_angle", "max_angle_from_start", "angle_from_start"):
        np.testing.assert_array_equal(getattr(whole, field), getattr(pieces, field), err_msg=field)
    reference = jaxquat.integrate(q0, omega, 0.05, 48, method=method, t0=0.25, save_every=8)
    np.testing.assert_allclose(whole.saved, reference, atol=1e-13)


@pytest.mark.parametrize("bodies", [1, 1000, 10**5, 10**6, 10**7])
@pytest.mark.parametrize("save_every", [None, 1, 2, 3, 16])
def test_default_chunk_bounds_the_work_and_the_saved_states(bodies, save_every):
    """About 2²⁶ body-steps per chunk, and at most 2²⁴ saved states (256 MB in float32) held per
    chunk whatever `save_every` is: at 10⁶ bodies and save_every=1 the chunks were 1 GB each."""
    steps = 10_000
    chunk = _default_chunk(steps, bodies, save_every)
    assert 1 <= chunk <= steps + (save_every or 0)
    if save_every:
        assert chunk % save_every == 0
        # One chunk's saved states; the rounding to a multiple of save_every adds at most half of one.
        assert bodies * chunk // save_every <= 2**24 * 1.5 or chunk == save_every
    assert bodies * chunk <= 2**26 * 1.5 or chunk <= (save_every or 1)
    if bodies <= 2**26 // steps and save_every in (None, 1):
        assert chunk == steps  # one chunk when the whole run is small
    if save_every is None and bodies > 2**26 // steps:
        assert bodies * chunk >= 2**25  # not shortened when nothing is saved


@pytest.mark.parametrize("method", ["magnus4", "magnus6", "magnus8"])
def test_magnus_refuses_a_q_dependent_omega_as_integrate(method):
    # The Magnus methods freeze q at the Gauss points: a q-dependent ω silently ran at first order.
    q0 = jnp.tile(jnp.array([1.0, 0.0, 0.0, 0.0]), (2, 1))

    def omega(t, q):
        return jnp.stack(
            [jnp.sin(t) + q[..., 1], jnp.cos(3 * t) + 0 * q[..., 0], 0.5 + 0 * q[..., 0]], -1
        )

    with pytest.raises(ValueError) as expected:
        jaxquat.integrate(q0, omega, 0.05, 30, method=method, save="final")
    with pytest.raises(ValueError, match="depends on q") as got:
        simulate_ensemble(q0, omega, 0.05, 30, method=method)
    assert str(got.value) == str(expected.value)
    # A q-independent ω (using only q's shape) is accepted.
    spin = lambda t, q: jnp.broadcast_to(jnp.cos(t), q.shape[:-1] + (3,))  # noqa: E731
    result = simulate_ensemble(q0, spin, 0.05, 4, method=method)
    np.testing.assert_allclose(
        result.final, jaxquat.integrate(q0, spin, 0.05, 4, method=method, save="final"), atol=1e-14
    )


class _Spin(eqx.Module):
    """A trainable angular velocity ω(t) = sin(t)·w, shared by all bodies."""

    w: jax.Array

    def __call__(self, t, q):
        return jnp.broadcast_to(jnp.sin(t) * self.w, q.shape[:-1] + (3,))


class _Drag(eqx.Module):
    """A trainable torque τ = −c·ω."""

    c: jax.Array

    def __call__(self, t, q, omega):
        return -self.c * omega


def test_callables_carrying_arrays_match_integrate_and_do_not_recompile(getkey):
    # `jaxquat.sampled` and equinox.Module callables (arrays inside) once failed with JAX's
    # "Non-hashable static arguments"; their arrays are now arguments of the compiled chunk.
    q0 = random_unit(getkey(), (2, 3))
    samples = jax.random.normal(getkey(), (12, 2, 3, 3))  # per-body samples, laid out over bodies
    for method in ("euler", "cf4"):
        omega = jaxquat.sampled(samples, 0.1, t0=0.05)
        result = simulate_ensemble(q0, omega, 0.1, 10, method=method, t0=0.05, chunk_size=4)
        reference = jaxquat.integrate(q0, omega, 0.1, 10, method=method, t0=0.05, save="final")
        assert result.final.shape == (2, 3, 4)
        np.testing.assert_allclose(result.final, reference, atol=1e-13, err_msg=method)
    np.testing.assert_array_equal(result.final_omega, samples[10])  # ω at t0 + 10·dt
    spin = _Spin(jnp.array([0.3, -0.2, 1.0]))
    result = simulate_ensemble(q0, spin, 0.1, 10, method="cf4", save_every=5)
    reference = jaxquat.integrate(q0, spin, 0.1, 10, method="cf4", save_every=5)
    np.testing.assert_allclose(result.saved, reference, atol=1e-13)
    # New parameter values reuse the compiled chunk.
    compiled = _run_chunk._cache_size()
    again = simulate_ensemble(
        q0, _Spin(jnp.array([1.0, 0.5, -0.3])), 0.1, 10, method="cf4", save_every=5
    )
    assert _run_chunk._cache_size() == compiled
    reference = jaxquat.integrate(
        q0, _Spin(jnp.array([1.0, 0.5, -0.3])), 0.1, 10, method="cf4", save_every=5
    )
    np.testing.assert_allclose(again.saved, reference, atol=1e-13)
    # A torque given as a Module, against `simulate_rigid_body`.
    omega0 = jax.random.normal(getkey(), (2, 3, 3))
    inertia = jnp.array([1.0, 2.0, 3.5])
    for frame in ("body", "world"):
        drag = _Drag(jnp.asarray(0.4))
        result = simulate_ensemble(q0, omega0, 0.05, 20, inertia=inertia, torque=drag, frame=frame)
        q_ref, w_ref = jaxquat.simulate_rigid_body(
            q0, omega0, inertia, 0.05, 20, torque=drag, frame=frame, save="final"
        )
        np.testing.assert_allclose(result.final, q_ref, atol=1e-13, err_msg=frame)
        np.testing.assert_allclose(result.final_omega, w_ref, atol=1e-13, err_msg=frame)


_GAIN = {"value": 1.0}


def _global_spin(t, q):  # reads a module-level gain when traced
    return jnp.broadcast_to(jnp.array([_GAIN["value"], 0.0, 0.0]), q.shape[:-1] + (3,))


class _DataclassSpin:  # compares by value but does not hash (as a dataclass with eq=True)
    __hash__ = None

    def __init__(self, rate):
        self.rate = rate

    def __eq__(self, other):
        return isinstance(other, _DataclassSpin) and self.rate == other.rate

    def __call__(self, t, q):
        return jnp.broadcast_to(jnp.array([0.0, self.rate, 0.0]), q.shape[:-1] + (3,))


class _NumpyAxisSpin(eqx.Module):  # a NumPy field the call uses with NumPy (not traceable)
    axis: np.ndarray

    def __call__(self, t, q):
        return jnp.broadcast_to(jnp.asarray(np.asarray(self.axis) * 1.0), q.shape[:-1] + (3,))


class _DataclassDrag:  # the torque −c ω, unhashable too
    __hash__ = None

    def __init__(self, c):
        self.c = c

    def __eq__(self, other):
        return isinstance(other, _DataclassDrag) and self.c == other.c

    def __call__(self, t, q, omega):
        return -self.c * omega


def test_callables_other_than_modules_are_compiled_at_each_call():
    """A function that reads a global, a callable that does not hash (it once failed with "must be
    hashable apart from its arrays") and a Module calling NumPy on its NumPy field (once a tracer
    conversion error) all run, their chunks compiled for each call, with each call's values: the
    trajectory and the final ω agree (a cached run once replayed the first call's gain while the
    final ω, evaluated after the run, read the new one). Closed forms of a constant ω about x, y, z
    for 1 s over two chunks, and of a sphere under the torque −c ω, ω(t) = ω₀ exp(−c t / I)."""
    q0 = jaxquat.identity((2,))

    def run(omega, **kw):
        return simulate_ensemble(q0, omega, 0.01, 100, chunk_size=60, **kw)

    def final(omega, **kw):
        return run(omega, **kw).final

    def turn(axis, angle):
        return np.broadcast_to(
            np.concatenate([[np.cos(angle / 2)], np.sin(angle / 2) * np.eye(3)[axis]]), (2, 4)
        )

    for gain in (1.0, 2.0):
        _GAIN["value"] = gain
        result = run(_global_spin)
        np.testing.assert_allclose(result.final, turn(0, gain), atol=1e-13)
        np.testing.assert_array_equal(result.final_omega, np.broadcast_to([gain, 0.0, 0.0], (2, 3)))
    for rate in (0.4, -1.2):
        np.testing.assert_allclose(final(_DataclassSpin(rate)), turn(1, rate), atol=1e-13)
    for angle in (0.8, -2.5):
        spin = _NumpyAxisSpin(np.array([0.0, 0.0, angle]))
        np.testing.assert_allclose(final(spin), turn(2, angle), atol=1e-13)
    omega0 = jnp.array([[0.2, -0.4, 1.1]])
    for c in (0.5, 2.0):
        result = simulate_ensemble(
            q0[:1],
            omega0,
            0.01,
            100,
            inertia=jnp.full(3, 2.0),
            torque=_DataclassDrag(c),
            chunk_size=60,
        )
        np.testing.assert_allclose(result.final_omega, omega0 * np.exp(-c / 2), rtol=1e-9)


class _ListSpin(eqx.Module):  # parameters kept in a list: ω(t) = w₀ + sin(t) w₁
    ws: list

    def __call__(self, t, q):
        return jnp.broadcast_to(self.ws[0] + jnp.sin(t) * self.ws[1], q.shape[:-1] + (3,))


class _ScalarSpin(eqx.Module):  # a NumPy scalar field (indexing a NumPy array gives one)
    rate: float

    def __call__(self, t, q):
        return jnp.broadcast_to(jnp.array([0.0, 0.0, float(self.rate)]), q.shape[:-1] + (3,))


def test_modules_with_containers_and_numpy_scalars_and_runs_under_jit():
    """A Module whose arrays sit in a list reuses the compiled chunk with new values; one with a NumPy
    scalar field that it converts with `float` runs (traced, it failed); and the whole ensemble runs
    inside `jax.jit` (its dt check once called NumPy on a tracer). Closed forms about the z axis:
    ω = a + b sin t turns by a T + b (1 − cos T) (cf4's error at Δt = 0.01 is ~1e-10)."""
    q0 = jaxquat.identity((2,))
    z = jnp.array([0.0, 0.0, 1.0])

    def about_z(angle):
        return np.broadcast_to([np.cos(angle / 2), 0.0, 0.0, np.sin(angle / 2)], (2, 4))

    def listed(a, b):
        spin = _ListSpin([a * z, b * z])
        return simulate_ensemble(q0, spin, 0.01, 100, method="cf4", chunk_size=60).final

    np.testing.assert_allclose(listed(0.5, 1.0), about_z(0.5 + (1 - np.cos(1.0))), atol=1e-9)
    compiled = _run_chunk._cache_size()
    np.testing.assert_allclose(listed(-1.0, 2.0), about_z(-1.0 + 2 * (1 - np.cos(1.0))), atol=1e-9)
    assert _run_chunk._cache_size() == compiled
    for rate in np.array([0.3, -1.1]):  # np.float64 scalars
        result = simulate_ensemble(q0, _ScalarSpin(rate), 0.01, 100, chunk_size=60)
        np.testing.assert_allclose(result.final, about_z(rate), atol=1e-13)
    jitted = jax.jit(lambda w: simulate_ensemble(q0, w, 0.01, 100, statistics=True))
    result = jitted(jnp.broadcast_to(0.7 * z, (2, 3)))
    np.testing.assert_allclose(result.final, about_z(0.7), atol=1e-13)
    np.testing.assert_allclose(result.total_angle, np.full(2, 0.7), atol=1e-12)


def test_sampled_grid_within_round_off_is_the_grid_as_in_integrate(getkey):
    """A float32 Δt of 0.7 (0.699999988) against samples every float64 0.7: as `integrate`, the
    ensemble holds sample k on step k (by time alone, its Euler steps started 2e-8·k samples short of
    each boundary and read sample k − 1). Reference: SciPy's composition of the steps' rotations."""
    steps = 6
    omegas = jax.random.normal(getkey(), (steps, 3))
    dt32 = np.float32(0.7)
    rotation = Rotation.identity()
    for k in range(steps):
        rotation = Rotation.from_rotvec(np.asarray(omegas[k]) * float(dt32)) * rotation
    expected = jaxquat.from_xyzw(jnp.asarray(rotation.as_quat()))
    result = simulate_ensemble(jaxquat.identity((1,)), jaxquat.sampled(omegas, 0.7), dt32, steps)
    assert _angle(result.final[0], expected) <= 1e-6
    integrated = jaxquat.integrate(jaxquat.identity(), jaxquat.sampled(omegas, 0.7), dt32, steps)
    assert _angle(integrated[-1], expected) <= 1e-6


def test_float32_in_float32_out_and_chunking_is_exact(getkey):
    q0, omega = _ensemble(getkey, 100, jnp.float32)
    whole = simulate_ensemble(q0, omega, 1e-2, 300, chunk_size=300)
    pieces = simulate_ensemble(q0, omega, 1e-2, 300, chunk_size=70)
    assert whole.final.dtype == jnp.float32 and whole.angle_from_start.dtype == jnp.float32
    np.testing.assert_array_equal(whole.final, pieces.final)
    exact = jaxquat.multiply(
        jaxquat.from_rotvec(omega.astype(jnp.float64) * 3.0), q0.astype(jnp.float64)
    )
    assert np.max(_angle(whole.final.astype(jnp.float64), exact)) < 2e-5


def test_batch_shapes_broadcast_and_padding(getkey):
    q0 = random_unit(getkey(), (3, 1))
    omega = jax.random.normal(getkey(), (5, 3))
    result = simulate_ensemble(q0, omega, 0.1, 7, save_every=7, chunk_size=3)
    assert result.final.shape == (3, 5, 4) and result.saved.shape == (2, 3, 5, 4)
    exact = jaxquat.multiply(jaxquat.from_rotvec(omega * 0.7), q0)
    assert_quat_close(result.final, exact, atol=1e-13)
    one = simulate_ensemble(jaxquat.identity(), jnp.array([0.0, 0.0, np.pi]), 0.01, 100)
    assert_quat_close(one.final, jnp.array([0.0, 0.0, 0.0, 1.0]), atol=1e-13)


def test_stream_to_file_reads_back_the_in_memory_states(getkey, tmp_path):
    q0, omega = _ensemble(getkey, 50)
    inertia = jnp.array([2.0, 1.0, 3.0])
    kwargs = dict(inertia=inertia, save_every=5, statistics=True, chunk_size=15)
    memory = simulate_ensemble(q0, omega, 0.01, 40, **kwargs)
    streamed = simulate_ensemble(q0, omega, 0.01, 40, path=tmp_path / "run", **kwargs)
    assert streamed.saved is None and streamed.path == str(tmp_path / "run")
    data = load_ensemble(tmp_path / "run")
    assert data["complete"] and data["steps_done"] == 40
    np.testing.assert_array_equal(data["steps"], np.arange(0, 41, 5))
    np.testing.assert_allclose(data["times"], memory.times, rtol=0, atol=1e-15)
    np.testing.assert_array_equal(data["states"], memory.saved)
    np.testing.assert_array_equal(data["omegas"], memory.saved_omega)
    for key in ("final", "final_omega", "total_angle", "max_angle_from_start"):
        np.testing.assert_array_equal(data[key], getattr(streamed, key), err_msg=key)
    assert data["metadata"]["method"] == "cf4" and data["metadata"]["frame"] == "body"
    # Writing again into the same directory replaces the previous run.
    simulate_ensemble(q0[:10], omega[:10], 0.01, 10, path=tmp_path / "run", save_every=10)
    again = load_ensemble(tmp_path / "run")
    assert again["states"].shape == (2, 10, 4)
    assert sorted(os.listdir(tmp_path / "run")) == sorted(
        [
            "index.json",
            "states_000000.npy",
            "states_000001.npy",
            "final.npy",
            "final_omega.npy",
            "angle_from_start.npy",
        ]
    )


def test_interrupt_between_chunks_leaves_the_completed_chunks(getkey, tmp_path):
    q0, omega = _ensemble(getkey, 40)
    full = simulate_ensemble(q0, omega, 0.01, 100, save_every=5, chunk_size=20)
    calls = []

    def progress(done, total):
        calls.append((done, total))
        if done >= 40:
            raise KeyboardInterrupt

    with pytest.raises(KeyboardInterrupt):
        simulate_ensemble(
            q0,
            omega,
            0.01,
            100,
            save_every=5,
            chunk_size=20,
            path=tmp_path / "run",
            progress=progress,
        )
    assert calls == [(20, 100), (40, 100)]
    data = load_ensemble(tmp_path / "run")
    assert not data["complete"] and data["steps_done"] == 40
    np.testing.assert_array_equal(data["steps"], np.arange(0, 41, 5))
    np.testing.assert_array_equal(data["states"], full.saved[:9])
    with open(tmp_path / "run" / "index.json") as f:
        assert json.load(f)["final"] == {}
    assert not [name for name in os.listdir(tmp_path / "run") if name.endswith(".tmp")]


def test_interrupt_inside_a_write_leaves_no_temporary_file(getkey, tmp_path, monkeypatch):
    # Ctrl-C while a record's .npy is half written: the earlier records stay readable and no
    # `.tmp` file is left behind.
    q0, omega = _ensemble(getkey, 12)
    full = simulate_ensemble(q0, omega, 0.01, 40, save_every=5, chunk_size=10)
    real_save = np.save
    saves = []

    def save(file, array, *args, **kwargs):
        saves.append(array.shape)
        if len(saves) == 3:  # the third record, interrupted with part of its file written
            file.write(b"\x93NUMPY partial")
            raise KeyboardInterrupt
        return real_save(file, array, *args, **kwargs)

    monkeypatch.setattr(np, "save", save)
    with pytest.raises(KeyboardInterrupt):
        simulate_ensemble(q0, omega, 0.01, 40, save_every=5, chunk_size=10, path=tmp_path / "run")
    monkeypatch.undo()
    assert len(saves) == 3
    assert not [name for name in os.listdir(tmp_path / "run") if name.endswith(".tmp")]
    data = load_ensemble(tmp_path / "run")
    # Records: the initial state, steps 5-10, then steps 15-20 (interrupted).
    assert not data["complete"] and data["steps_done"] == 10
    np.testing.assert_array_equal(data["steps"], [0, 5, 10])
    np.testing.assert_array_equal(data["states"], full.saved[: len(data["steps"])])


def test_progress_is_off_by_default_and_a_bar_on_request(getkey, capsys):
    q0, omega = _ensemble(getkey, 8)
    simulate_ensemble(q0, omega, 0.01, 20, chunk_size=5)
    assert capsys.readouterr().err == ""
    simulate_ensemble(q0, omega, 0.01, 20, chunk_size=5, progress=True)
    assert "ensemble" in capsys.readouterr().err


@pytest.mark.parametrize(
    "kwargs, name",
    [
        (dict(q0=np.ones((3, 3))), "q0"),
        (dict(omega=np.ones((3, 2))), "omega"),
        (dict(method="heun"), "method"),
        (dict(frame="inertial"), "frame"),
        (dict(num_steps=-1), "num_steps"),
        (dict(num_steps=2.5), "num_steps"),
        (dict(save_every=0), "save_every"),
        (dict(chunk_size=0), "chunk_size"),
        (dict(dt=np.ones(3)), "dt"),
        (dict(torque=lambda t, q, w: w), "torque"),
        (dict(inertia=np.array([1.0, -2.0, 3.0])), "inertia"),
        (dict(inertia=np.ones((2, 2))), "inertia"),
        (dict(inertia=np.ones(3), method="magnus4"), "method"),
        (dict(omega=np.ones((4, 3)), q0=np.ones((3, 4))), "broadcast"),
        (dict(progress="yes"), "progress"),
        (dict(q0=np.ones((0, 4)), omega=np.ones((0, 3))), r"no bodies \(batch shape \(0,\)\)"),
        (dict(q0=np.ones((2, 0, 4))), r"no bodies \(batch shape \(2, 0\)\)"),
        (dict(devices=[]), "devices"),
        (dict(devices=["cpu"]), "devices.*jax.Device"),
        (dict(devices=5), "devices.*jax.Device"),
        (dict(path=5), "path.*str or os.PathLike"),
        (dict(omega=lambda t, q: q), r"`omega\(t, q\)` must return shape \(\.\.\., 3\)"),
        (
            dict(q0=np.ones((3, 4)) / 2, omega=lambda t, q: jnp.ones((2, 3))),
            r"omega\(t, q\).*element-wise",
        ),
    ],
)
def test_bad_arguments_raise_value_errors_naming_them(kwargs, name):
    arguments = dict(q0=np.array([1.0, 0, 0, 0]), omega=np.zeros(3), dt=0.1, num_steps=3)
    arguments.update(kwargs)
    q0, omega, dt, steps = (arguments.pop(k) for k in ("q0", "omega", "dt", "num_steps"))
    with pytest.raises(ValueError, match=name):
        simulate_ensemble(q0, omega, dt, steps, **arguments)


def test_bad_paths(tmp_path):
    (tmp_path / "file").write_text("x")
    (tmp_path / "other").mkdir()
    (tmp_path / "other" / "notes.txt").write_text("keep me")
    args = (np.array([1.0, 0, 0, 0]), np.zeros(3), 0.1, 2)
    with pytest.raises(ValueError, match="not a directory"):
        simulate_ensemble(*args, path=tmp_path / "file", save_every=1)
    # Paths that cannot be made: under a file, a dangling symbolic link (were raw OSErrors).
    (tmp_path / "dangling").symlink_to(tmp_path / "nowhere")
    for where, why in [("file/run", "NotADirectoryError"), ("dangling", "FileExistsError")]:
        with pytest.raises(ValueError, match=f"`path` .*{where}' cannot be created.*{why}"):
            simulate_ensemble(*args, path=tmp_path / where, save_every=1)
    with pytest.raises(ValueError, match="not a jaxquat ensemble"):
        simulate_ensemble(*args, path=tmp_path / "other", save_every=1)
    assert (tmp_path / "other" / "notes.txt").read_text() == "keep me"
    # A run killed while writing its first index leaves only index.json.tmp: a run can start there.
    (tmp_path / "killed").mkdir()
    (tmp_path / "killed" / "index.json.tmp").write_text('{"form')
    simulate_ensemble(*args, path=tmp_path / "killed", save_every=1)
    assert load_ensemble(tmp_path / "killed")["complete"]
    assert not (tmp_path / "killed" / "index.json.tmp").exists()
    with pytest.raises(ValueError, match="index.json"):
        load_ensemble(tmp_path / "other")
    with pytest.raises(ValueError, match="does not exist"):
        load_ensemble(tmp_path / "missing")
    with pytest.raises(ValueError, match="not a directory"):
        load_ensemble(tmp_path / "file")


@pytest.mark.parametrize(
    "index",
    [
        [1],
        {"format": "jaxquat-ensemble", "final": []},
        {"format": "jaxquat-ensemble", "records": [1]},
        {"format": "jaxquat-ensemble", "records": {"files": "x.npy"}},
        {"format": "jaxquat-ensemble", "records": [{"files": ["states_000000.npy"]}]},
    ],
)
def test_a_malformed_index_in_path_is_a_value_error(tmp_path, capsys, index):
    # The writer removes the files a previous run's index names: a JSON-valid but malformed index was
    # an AttributeError (the CLI: "internal error", exit 1), now a ValueError naming the file.
    run = tmp_path / "run"
    run.mkdir()
    (run / "index.json").write_text(json.dumps(index))
    (run / "states_000000.npy").write_bytes(b"keep")
    args = (np.array([1.0, 0, 0, 0]), np.zeros(3), 0.1, 2)
    with pytest.raises(ValueError, match=r"`path` '.*run'.*index\.json"):
        simulate_ensemble(*args, path=run, save_every=1)
    assert (run / "states_000000.npy").read_bytes() == b"keep"
    status = main(
        ["simulate", "--bodies", "3", "--steps", "5", "--output", str(run), "--no-progress"]
    )
    err = capsys.readouterr().err
    assert status == 2 and err.count("\n") == 1 and "index.json" in err, err
    assert "internal error" not in err


def test_load_ensemble_rejects_malformed_files(tmp_path):
    # Every way a written ensemble can be damaged gives one ValueError naming the path, never a
    # JSONDecodeError, KeyError or a silently reshaped result.
    import json

    run = tmp_path / "run"
    simulate_ensemble(
        np.tile([1.0, 0, 0, 0], (5, 1)),
        np.ones((5, 3)),
        0.1,
        6,
        save_every=2,
        chunk_size=2,
        path=run,
    )
    assert load_ensemble(run)["states"].shape == (4, 5, 4)
    index = json.loads((run / "index.json").read_text())
    data = run / index["records"][1]["files"]["states"]
    good = data.read_bytes()
    np.save(data, np.zeros((3, 5, 4), np.float32))  # a data file of the wrong length
    with pytest.raises(ValueError, match=r"record 1\) holds float32\[3, 5, 4\]"):
        load_ensemble(run)
    data.write_bytes(good[:40])  # truncated
    with pytest.raises(ValueError, match="malformed jaxquat ensemble"):
        load_ensemble(run)
    data.write_bytes(good + b"JUNK" * 10)  # data appended (np.load reads the array and ignores it)
    with pytest.raises(ValueError, match=r"has 40 bytes after its float\d+\[.*\] data"):
        load_ensemble(run)
    data.write_bytes(good)
    load_ensemble(run)
    version = dict(index, version=True)  # true == 1 in Python: not the format version 1
    (run / "index.json").write_text(json.dumps(version))
    with pytest.raises(ValueError, match="format version True is not one this jaxquat reads"):
        load_ensemble(run)
    del index["records"][0]["steps"]  # an edited index
    (run / "index.json").write_text(json.dumps(index))
    with pytest.raises(ValueError, match="malformed jaxquat ensemble.*KeyError"):
        load_ensemble(run)
    (run / "index.json").write_text('{"format": ')  # truncated JSON
    with pytest.raises(ValueError, match="JSONDecodeError"):
        load_ensemble(run)
    (run / "index.json").write_text("[1, 2]")
    with pytest.raises(ValueError, match="not a jaxquat ensemble index"):
        load_ensemble(run)


_SHARDED = textwrap.dedent(
    """
    import jax, jax.numpy as jnp, numpy as np
    jax.config.update("jax_enable_x64", True)
    jax.config.update("jax_numpy_rank_promotion", "raise")
    import jaxquat
    assert jax.device_count() == 4, jax.devices()
    key_q, key_w = jax.random.split(jax.random.key(0))
    out = {}
    for n, inertia in ((1000, jnp.array([1.0, 2.0, 3.0])), (1001, None)):
        q0 = jaxquat.random(key_q, (n,), jnp.float64)
        omega = jax.random.normal(key_w, (n, 3), jnp.float64)
        def run(**kw):
            return jaxquat.simulate_ensemble(q0, omega, 0.01, 60, inertia=inertia, save_every=20,
                                             chunk_size=40, statistics=True, **kw)
        sharded = run()
        single = run(devices=jax.devices()[:1])
        out[n] = dict(
            devices=len(sharded.sharding.device_set),
            spec=str(sharded.sharding.spec),
            mesh=dict(sharded.sharding.mesh.shape),
            shards=sorted({s.data.shape[0] for s in sharded.final.addressable_shards}),
            single_devices=len(single.sharding.device_set),
            final=float(np.max(np.abs(np.asarray(sharded.final) - np.asarray(single.final)))),
            saved=float(np.max(np.abs(np.asarray(sharded.saved) - np.asarray(single.saved)))),
            total=float(np.max(np.abs(np.asarray(sharded.total_angle) - np.asarray(single.total_angle)))),
            shape=list(sharded.final.shape),
        )
    # Multi-axis batches: each device keeps the bodies it computed where the flattened blocks are
    # products of per-axis blocks ((2, 4) and (2, 6) on a 2 x 2 mesh), else replicated ((3, 4)).
    for batch in ((2, 4), (2, 6), (1, 8), (3, 4)):
        q0 = jaxquat.random(key_q, batch, jnp.float64)
        omega = jax.random.normal(key_w, batch + (3,), jnp.float64)
        def run(**kw):
            return jaxquat.simulate_ensemble(q0, omega, 0.01, 60, save_every=20, chunk_size=40,
                                             statistics=True, **kw)
        sharded, single = run(), run(devices=jax.devices()[:1])
        fields = ("final", "saved", "total_angle", "final_omega", "angle_from_start")
        out[str(batch)] = dict(
            difference=max(float(np.max(np.abs(np.asarray(getattr(sharded, f))
                                               - np.asarray(getattr(single, f))))) for f in fields),
            per_device=[max(s.data.nbytes for s in getattr(sharded, f).addressable_shards)
                        / getattr(sharded, f).nbytes for f in fields],
            specs=[str(getattr(sharded, f).sharding.spec) for f in fields],
        )
    import json; print(json.dumps(out))
    """
)


def test_bodies_are_sharded_over_four_devices_and_match_one_device():
    out = run_on_four_devices(_SHARDED, timeout=300)
    even = out["1000"]
    assert even["devices"] == 4 and even["mesh"] == {"bodies": 4} and "bodies" in even["spec"]
    assert even["shards"] == [250]  # each device holds a quarter of the bodies
    assert even["single_devices"] == 1
    # 1000 rigid bodies; 1001 kinematic bodies padded to 1004 on the devices, padding dropped.
    for n in ("1000", "1001"):
        assert out[n]["final"] <= 1e-12 and out[n]["saved"] <= 1e-12 and out[n]["total"] <= 1e-12
    assert out["1001"]["shape"] == [1001, 4]
    # Multi-axis batches were replicated (4x the memory) unless the first axis was a multiple of 4.
    for batch in ("(2, 4)", "(2, 6)", "(1, 8)", "(3, 4)"):
        assert out[batch]["difference"] == 0.0, (batch, out[batch])
        expected = 1.0 if batch == "(3, 4)" else 0.25  # (3, 4): 3-body blocks straddle the rows
        assert out[batch]["per_device"] == [expected] * 5, (batch, out[batch])
    assert out["(2, 4)"]["specs"][0] == "P('bodies', 'bodies_1')", out["(2, 4)"]


_COMMITTED = textwrap.dedent(
    """
    import json, jax, jax.numpy as jnp, numpy as np
    jax.config.update("jax_enable_x64", True)
    jax.config.update("jax_numpy_rank_promotion", "raise")
    import jaxquat
    assert jax.device_count() == 4, jax.devices()
    devices = jax.devices()
    q0 = jaxquat.random(jax.random.key(0), (6,))
    omega = jax.random.normal(jax.random.key(1), (6, 3))
    samples = jnp.broadcast_to(omega, (12, 6, 3))
    want = np.asarray(jaxquat.integrate(q0, omega, 0.1, 10, save="final"))
    on_one = lambda x, d=devices[1]: jax.device_put(x, d)
    cases = dict(
        one_device=lambda: jaxquat.simulate_ensemble(on_one(q0), on_one(omega), on_one(0.1), 10),
        other_layout=lambda: jaxquat.simulate_ensemble(
            jax.device_put(q0[:4], jaxquat.body_sharding()), omega[:4], 0.1, 10,
            devices=devices[:2]),
        sampled=lambda: jaxquat.simulate_ensemble(
            q0, jaxquat.sampled(on_one(samples), 0.1), 0.1, 10, t0=on_one(0.0)),
        inertia=lambda: jaxquat.simulate_ensemble(
            q0, omega, 0.1, 10, inertia=on_one(jnp.ones((6, 3))), frame="world"),
    )
    out = {}
    for name, run in cases.items():
        try:
            final = np.asarray(run().final)
            out[name] = float(np.max(np.abs(final - want[: len(final)])))
        except Exception as e:
            out[name] = f"{type(e).__name__}: {e}"[:300]
    print(json.dumps(out))
    """
)


def test_arrays_committed_to_other_devices_are_taken():
    """Arrays put on one device (`jax.device_put(x, device)`), or laid out over other devices than
    the ensemble's, are copied onto its devices: the chunks' sharding constraints refused them
    ("Received incompatible devices for jitted computation")."""
    out = run_on_four_devices(_COMMITTED, timeout=300)
    for name, error in out.items():  # (unit moments, world frame: the kinematic ensemble)
        assert isinstance(error, float) and error <= 1e-12, (name, error)


_SHARDED_CALLABLES = textwrap.dedent(
    """
    import json, equinox as eqx, jax, jax.numpy as jnp, numpy as np
    jax.config.update("jax_enable_x64", True)
    jax.config.update("jax_numpy_rank_promotion", "raise")
    import jaxquat
    assert jax.device_count() == 4, jax.devices()
    class Spin(eqx.Module):
        w: jax.Array
        def __call__(self, t, q):
            return jnp.broadcast_to(jnp.sin(t) * self.w, q.shape[:-1] + (3,))
    class Drag(eqx.Module):
        c: jax.Array
        def __call__(self, t, q, omega):
            return -self.c * omega
    q0 = jaxquat.random(jax.random.key(0), (2, 3))  # 6 bodies, padded to 8 on 4 devices
    samples = jax.random.normal(jax.random.key(1), (12, 2, 3, 3))
    omega0 = jax.random.normal(jax.random.key(2), (2, 3, 3))
    inertia = jnp.array([1.0, 2.0, 3.5])
    class NumpyAxis(eqx.Module):
        axis: np.ndarray
        def __call__(self, t, q):  # NumPy on the field: a constant of the program, not traced
            return jnp.broadcast_to(jnp.sin(t) * np.asarray(self.axis), q.shape[:-1] + (3,))
    axis = jax.device_put(jnp.array([0.3, -0.2, 1.0]), jax.devices()[0])  # committed to one device
    def closure(t, q):
        return jnp.broadcast_to(jnp.sin(t) * axis, q.shape[:-1] + (3,))
    cases = dict(
        closure=(closure, dict(method="midpoint")),
        numpy_module=(NumpyAxis(np.array([0.3, -0.2, 1.0])), dict(method="midpoint")),
        plain_torque=(omega0, dict(inertia=inertia, torque=lambda t, q, w: -0.4 * w)),
        sampled=(jaxquat.sampled(samples, 0.1), dict(method="cf4")),
        module=(Spin(jnp.array([0.3, -0.2, 1.0])), dict(method="midpoint")),
        torque=(omega0, dict(inertia=inertia, torque=Drag(jnp.asarray(0.4)))),
    )
    out = {}
    for name, (omega, kw) in cases.items():
        sharded = jaxquat.simulate_ensemble(q0, omega, 0.1, 10, chunk_size=4, **kw)
        single = jaxquat.simulate_ensemble(q0, omega, 0.1, 10, devices=jax.devices()[:1], **kw)
        if "inertia" in kw:
            reference, _ = jaxquat.simulate_rigid_body(q0, omega, inertia, 0.1, 10, torque=kw["torque"], save="final")
        else:
            reference = jaxquat.integrate(q0, omega, 0.1, 10, save="final", **kw)
        out[name] = dict(
            devices=len(sharded.final.sharding.device_set) if sharded.final.sharding.device_set else 0,
            single=float(np.max(np.abs(np.asarray(sharded.final) - np.asarray(single.final)))),
            reference=float(np.max(np.abs(np.asarray(sharded.final) - np.asarray(reference)))),
            shape=list(sharded.final.shape),
        )
    print(json.dumps(out))
    """
)


def test_callables_carrying_arrays_run_on_four_devices():
    out = run_on_four_devices(_SHARDED_CALLABLES, timeout=300)
    for name, case in out.items():
        assert case["shape"] == [2, 3, 4], name
        assert case["single"] <= 1e-13 and case["reference"] <= 1e-13, (name, case)


_MEMORY = textwrap.dedent(
    """
    import resource, sys, jax, jax.numpy as jnp
    import jaxquat
    n, path = 50_000, sys.argv[1]
    q0 = jaxquat.random(jax.random.key(0), (n,), jnp.float32)
    omega = jax.random.normal(jax.random.key(1), (n, 3), jnp.float32)
    def run(steps):
        return jaxquat.simulate_ensemble(q0, omega, 1e-3, steps, save_every=1, chunk_size=10, path=path)
    run(10)  # compile
    before = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    result = run(200)
    after = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    print(before, after, result.num_chunks)
    """
)


def test_streaming_memory_is_bounded_by_the_chunk(tmp_path):
    """Proxy for the 10⁶-body run: 200 saved steps (160 MB) streamed in chunks of 10 (8 MB)."""
    proc = subprocess.run(
        [sys.executable, "-c", _MEMORY, str(tmp_path / "run")],
        capture_output=True,
        text=True,
        timeout=300,
        env=dict(os.environ, JAX_PLATFORMS="cpu"),
    )
    assert proc.returncode == 0, proc.stderr[-2000:]
    before, after, chunks = (int(x) for x in proc.stdout.split())
    assert chunks == 20
    assert (after - before) * 1024 < 60e6, (before, after)
    data = load_ensemble(tmp_path / "run")
    assert data["states"].shape == (201, 50_000, 4) and data["complete"]


_KEPT_MEMORY = textwrap.dedent(
    """
    import resource, jax, jax.numpy as jnp, numpy as np
    import jaxquat
    n = 50_000
    q0 = jaxquat.random(jax.random.key(0), (n,), jnp.float32)
    omega = jax.random.normal(jax.random.key(1), (n, 3), jnp.float32)
    def run(steps):
        return jaxquat.simulate_ensemble(q0, omega, 1e-3, steps, save_every=1, chunk_size=20)
    run(40)  # compile
    before = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    result = run(400)
    jax.block_until_ready(result.saved)
    after = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    ok = bool(jnp.all(result.saved[-1] == result.final)) and bool(jnp.all(result.saved[0] == q0))
    print(before, after, result.num_chunks, result.saved.nbytes, ok)
    """
)


def test_in_memory_saved_states_are_held_once():
    """The chunks' saved states are written into one array as they come: joining them at the end
    held them twice (401 saved steps of 50,000 bodies, 321 MB, peaked at 2× that)."""
    proc = subprocess.run(
        [sys.executable, "-c", _KEPT_MEMORY],
        capture_output=True,
        text=True,
        timeout=300,
        env=dict(os.environ, JAX_PLATFORMS="cpu"),
    )
    assert proc.returncode == 0, proc.stderr[-2000:]
    before, after, chunks, nbytes, ok = proc.stdout.split()
    assert int(chunks) == 20 and int(nbytes) == 401 * 50_000 * 16 and ok == "True"
    assert (int(after) - int(before)) * 1024 < 1.3 * int(nbytes), (before, after, nbytes)


@pytest.mark.parametrize("dynamic", [False, True])
def test_bfloat16_run_round_trips(tmp_path, dynamic):
    """np.save stores bfloat16 as 2-byte void records (|V2): the reader refused every bfloat16 run
    although it lists bfloat16 as a dtype the index may name."""
    q0 = jnp.asarray([[1.0, 0, 0, 0], [0.0, 1.0, 0, 0]], jnp.bfloat16)
    omega = jnp.asarray([[0.5, -1.0, 2.0], [1.0, 0.0, 0.0]], jnp.bfloat16)
    extra = {"inertia": jnp.asarray([1.0, 2.0, 3.0], jnp.bfloat16)} if dynamic else {}
    result = simulate_ensemble(q0, omega, 0.01, 10, save_every=5, path=tmp_path / "run", **extra)
    run = load_ensemble(tmp_path / "run")
    assert run["states"].dtype == jnp.bfloat16 and run["states"].shape == (3, 2, 4)
    assert run["finite"]
    np.testing.assert_array_equal(run["final"], np.asarray(result.final))
    np.testing.assert_array_equal(run["states"][-1], np.asarray(result.final))
    if dynamic:
        assert run["omegas"].dtype == jnp.bfloat16


def test_a_header_claiming_a_huge_shape_is_refused_before_allocating(tmp_path):
    """The .npy header is checked against the index before numpy allocates (a raw MemoryError of
    2.9 TiB before); a file of the right shape but another dtype is named too."""
    run = tmp_path / "run"
    simulate_ensemble(np.tile([1.0, 0, 0, 0], (1, 1)), np.ones((1, 3)), 0.1, 4, path=run)
    final = run / "final.npy"
    good = final.read_bytes()
    bad = good.replace(b"(1, 4)", b"(99999999999, 4)")
    assert bad != good
    final.write_bytes(bad)
    with pytest.raises(ValueError, match=r"final\.npy \(final\) holds float64\[99999999999, 4\]"):
        load_ensemble(run)
    np.save(final, np.zeros((1, 4), np.float32))
    with pytest.raises(ValueError, match=r"final\.npy \(final\) holds float32\[1, 4\], the index"):
        load_ensemble(run)


def test_rigid_ensemble_checks_inertia_and_keeps_the_orientation_dtype():
    """The same inertia checks as `simulate_rigid_body` (a non-symmetric matrix ran silently), and
    float32 bodies with a float64 NumPy inertia stay float32, as in `simulate_rigid_body`."""
    q0, omega = np.tile([1.0, 0, 0, 0], (2, 1)), np.ones((2, 3))
    with pytest.raises(ValueError, match="`inertia` must be a symmetric matrix"):
        simulate_ensemble(q0, omega, 0.01, 5, inertia=[[2.0, 0.9, 0], [0, 2.0, 0], [0, 0, 3.0]])
    with pytest.raises(ValueError, match="`inertia` must be positive definite"):
        simulate_ensemble(q0, omega, 0.01, 5, inertia=[1.0, -2.0, 3.0])
    q32, w32 = jnp.asarray(q0, jnp.float32), jnp.asarray(omega, jnp.float32)
    moments = np.array([1.0, 2.0, 3.0])
    result = simulate_ensemble(q32, w32, 0.01, 5, inertia=moments)
    assert result.final.dtype == jnp.float32 and result.final_omega.dtype == jnp.float32
    q_ref, w_ref = jaxquat.simulate_rigid_body(q32, w32, moments, 0.01, 5, save="final")
    assert q_ref.dtype == jnp.float32
    np.testing.assert_allclose(np.asarray(result.final), np.asarray(q_ref), atol=1e-6)


def test_derivatives_in_dt_and_t0_with_saved_states(tmp_path):
    """`save_every` made the saved times with float(dt) and float(t0): a ConcretizationTypeError
    under jax.grad, where the states without saving differentiated fine. Now the derivatives match
    central differences; writing a traced run to `path` is a ValueError naming `path`."""
    q0 = jaxquat.random(jax.random.key(1), (2,))
    omega = jnp.array([[0.3, 0.1, -0.2], [1.0, 2.0, 0.5]])

    def saved(dt, t0):
        result = jaxquat.simulate_ensemble(q0, lambda t, q: omega * t, dt, 10, save_every=5, t0=t0)
        return jnp.sum(result.saved) + jnp.sum(result.times)

    h = 1e-6
    for argnum in (0, 1):
        gradient = jax.grad(saved, argnums=argnum)(0.05, 1.0)
        shift = (h, 0.0) if argnum == 0 else (0.0, h)
        central = (
            saved(0.05 + shift[0], 1.0 + shift[1]) - saved(0.05 - shift[0], 1.0 - shift[1])
        ) / (2 * h)
        np.testing.assert_allclose(gradient, central, rtol=1e-7)
    with pytest.raises(ValueError, match="`path`: a run under a JAX transformation .`dt` traced"):
        jax.grad(
            lambda dt: jnp.sum(
                jaxquat.simulate_ensemble(
                    q0, omega, dt, 10, save_every=5, path=tmp_path / "r"
                ).saved
            )
        )(0.05)


def test_writing_under_a_transformation_is_refused_before_the_previous_run_is_touched(tmp_path):
    """Under jax.jit (even with constant inputs), jax.grad or jax.vmap the states are traced and
    cannot be written. Only a traced `dt` or `t0` was refused; a traced `q0` or `omega`, or any
    call under jit, replaced the run already in `path` and then failed in NumPy
    (TracerArrayConversionError), leaving an incomplete run. An `omega` closing over a traced value
    is seen only when its states are: a ValueError naming `path` then too."""
    q0 = jaxquat.random(jax.random.key(0), (8,))
    omega = jnp.ones((8, 3))
    path = tmp_path / "run"

    def run(q, w, **kwargs):
        return jaxquat.simulate_ensemble(q, w, 0.1, 5, save_every=1, path=path, **kwargs)

    run(q0, omega)
    before = jaxquat.load_ensemble(path)["states"]
    assert before.shape == (6, 8, 4)
    calls = {
        "inside jax.jit": lambda: jax.jit(lambda: run(q0, omega).final)(),
        "`q0` traced": lambda: jax.jit(lambda q: run(q, omega).final)(q0),
        "`omega` traced": lambda: jax.grad(lambda w: jnp.sum(run(q0, w).final))(omega),
        "`q0`, `omega` traced": lambda: jax.vmap(lambda q, w: run(q, w).final)(
            q0[None], omega[None]
        ),
    }
    for what, call in calls.items():
        with pytest.raises(ValueError, match=f"`path`: a run under a JAX transformation .{what}"):
            call()
        loaded = jaxquat.load_ensemble(path)
        assert loaded["complete"]
        np.testing.assert_array_equal(loaded["states"], before)
    with pytest.raises(ValueError, match="`path`: the run's states are traced"):
        jax.grad(lambda s: jnp.sum(run(q0, lambda t, q: s * omega[0]).final))(1.0)
    with pytest.raises(ValueError, match="`path`: the run's states are traced"):
        jax.grad(
            lambda s: jnp.sum(
                jaxquat.simulate_ensemble(q0, lambda t, q: s * omega[0], 0.1, 5, path=path).final
            )
        )(1.0)


def test_under_a_transformation_inside_an_explicit_mesh_is_a_clear_error():
    """The ensemble sets a mesh of its own inside a caller's `jax.set_mesh` of explicit axes, which
    JAX refuses while tracing: under jax.jit or jax.grad that was JAX's "`set_mesh` can only be used
    outside of `jax.jit`". Now a ValueError that says what to do; with automatic axes, as it says,
    the transformed run equals the eager one."""
    q0 = jaxquat.random(jax.random.key(0), (8,))
    omega = jax.random.normal(jax.random.key(1), (8, 3))

    def final(q, w, dt=0.05):
        return jaxquat.simulate_ensemble(q, w, dt, 12, save_every=4).final

    eager = final(q0, omega)
    gradient = jax.grad(lambda w: jnp.sum(jnp.sin(final(q0, w))))(omega)
    explicit = jax.make_mesh((1,), ("b",), axis_types=(jax.sharding.AxisType.Explicit,))
    with jax.set_mesh(explicit):
        np.testing.assert_array_equal(final(q0, omega), eager)  # eagerly it runs
        for call in (
            lambda: jax.jit(final)(q0, omega),
            lambda: jax.jit(lambda dt: final(q0, omega, dt))(0.05),
            lambda: jax.grad(lambda w: jnp.sum(final(q0, w)))(omega),
        ):
            with pytest.raises(ValueError, match="cannot run inside `jax.set_mesh` with a mesh of"):
                call()
    automatic = jax.make_mesh((1,), ("b",), axis_types=(jax.sharding.AxisType.Auto,))
    with jax.set_mesh(automatic):
        np.testing.assert_allclose(jax.jit(final)(q0, omega), eager, rtol=0, atol=1e-15)
        np.testing.assert_allclose(
            jax.grad(lambda w: jnp.sum(jnp.sin(final(q0, w))))(omega), gradient, rtol=1e-14
        )


def test_float32_total_angle_is_a_compensated_sum():
    """The total angle of a long float32 run is Σ |ω|Δt to float32's round-off of the step angles,
    not of the running sum: 20,000 steps of ~0.035 rad summed plainly in float32 came out 2.6e-4
    relative low (2.8e-3 after 200,000 steps; 1.35e-2 after 10⁶ steps in the CLI, a review); the
    Kahan-compensated sum is 1.8e-7 off."""
    rng = np.random.default_rng(0)
    omega = jnp.asarray(2.0 * rng.normal(size=(64, 3)), jnp.float32)
    q0 = jaxquat.random(jax.random.key(0), (64,), jnp.float32)
    dt, steps = 0.01, 20_000
    result = simulate_ensemble(q0, omega, dt, steps, statistics=True)
    assert result.total_angle.dtype == jnp.float32
    speed = np.linalg.norm(np.asarray(omega, np.float64), axis=-1)
    expected = speed * float(np.float32(dt)) * steps
    np.testing.assert_allclose(result.total_angle, expected, rtol=2e-6)


def test_three_bodies_with_their_own_principal_moments():
    """A `(3, 3)` inertia is one matrix, also for three bodies (a review found three bodies' moments
    read as a shared matrix). The documented form, diagonal matrices `jax.vmap(jnp.diag)(m)`, gives
    each body its own moments (checked against `simulate_rigid_body` body by body), and a table of
    moments that is not symmetric is refused with that hint."""
    q0 = jaxquat.random(jax.random.key(5), (3,))
    omega = jnp.array([[1.1, 0.2, 0.8], [0.3, 1.0, 0.5], [0.7, 0.1, 1.3]])
    moments = jnp.array([[1.0, 2.0, 3.0], [2.0, 2.0, 1.0], [1.5, 1.0, 2.0]])
    inertia = jax.vmap(jnp.diag)(moments)
    result = simulate_ensemble(q0, omega, 0.01, 50, inertia=inertia, frame="world")
    for i in range(3):
        q, w = jaxquat.simulate_rigid_body(
            q0[i], omega[i], moments[i], 0.01, 50, frame="world", save="final"
        )
        np.testing.assert_allclose(result.final[i], q, rtol=0, atol=1e-14)
        np.testing.assert_allclose(result.final_omega[i], w, rtol=0, atol=1e-14)
    with pytest.raises(ValueError, match=r"diagonal matrices, `jax.vmap\(jnp.diag\)\(moments\)`"):
        simulate_ensemble(q0, omega, 0.01, 5, inertia=moments)


def test_a_short_write_names_the_file_and_the_likely_cause(tmp_path, capsys, monkeypatch):
    """NumPy reports a short write (a full disk) as "40000 requested and 26592 written": an OSError
    with no file and no error number, which the command line printed as it was (a probe on a full
    tmpfs). It now names the file and says the disk may be full; no temporary file is left."""
    import errno

    from jaxquat import _ensemble

    target = str(tmp_path / "states_000000.npy")

    def short(f):
        f.write(b"partial")
        raise OSError("40000 requested and 26592 written")

    with pytest.raises(OSError) as raised:
        _ensemble._replace_atomically(target, "wb", short)
    assert raised.value.errno == errno.ENOSPC and raised.value.filename == target
    assert "40000 requested and 26592 written (is the disk full?)" in raised.value.strerror
    assert sorted(p.name for p in tmp_path.iterdir()) == []

    def save(file, array, **kwargs):  # every data file of a run meets the full disk
        raise OSError("40000 requested and 26592 written")

    monkeypatch.setattr(_ensemble.np, "save", save)
    run = tmp_path / "run"
    argv = ["simulate", "--bodies", "3", "--steps", "4", "--save-every", "2", "--output", str(run)]
    status = main([*argv, "--no-progress"])
    err = capsys.readouterr().err
    assert status == 2 and err.count("\n") == 1, err
    assert err.startswith(f"jaxquat: error: {run}") and "(is the disk full?)" in err, err


def test_a_run_that_cannot_fit_on_the_disk_is_refused_before_anything_is_written(
    tmp_path, capsys, monkeypatch
):
    """`simulate --bodies 100000000 --steps 1000 --save-every 1 --output big` (1.6 TB) started
    writing on a disk with 64 GB free and wrote 11 GB before it was stopped (helper-76). Now the
    bytes of the data files are compared with the free space first (counting what a previous run in
    `path` frees), and a run that cannot fit is a ValueError that leaves the previous run whole; the
    command line prints it as one line and exits 2."""
    import shutil

    from jaxquat import _ensemble

    q0 = jnp.tile(jnp.array([1.0, 0.0, 0.0, 0.0]), (10, 1))
    run = tmp_path / "run"
    first = simulate_ensemble(q0, jnp.ones(3), 0.1, 6, save_every=2, path=run)
    previous = {p.name: p.read_bytes() for p in run.iterdir()}
    data = sum(len(b) for name, b in previous.items() if name.endswith(".npy"))
    # 4 saved states, then the final q, ω and angle: 10 bodies, float64, plus 5 files' headers
    assert data == (4 * 4 + 8) * 10 * 8 + 5 * 128
    usage = shutil.disk_usage(tmp_path)

    def disk_usage_with(free):
        return lambda path: usage._replace(free=free)

    inertia = jnp.array([1.0, 2.0, 3.0])
    monkeypatch.setattr(_ensemble.shutil, "disk_usage", disk_usage_with(0))
    with pytest.raises(
        ValueError, match=r"run': the saved states need 2\.88e-06 GB and .* has 2\.56e-06 GB free"
    ):
        simulate_ensemble(q0, jnp.ones(3), 0.1, 6, save_every=2, inertia=inertia, path=run)
    assert {p.name: p.read_bytes() for p in run.iterdir()} == previous
    with pytest.raises(ValueError, match=r"has 0 GB free; save less often"):
        simulate_ensemble(q0, jnp.ones(3), 0.1, 6, save_every=2, path=tmp_path / "new")
    assert not (tmp_path / "new").exists()
    # The space the previous run frees counts: the same run fits in its place with nothing free.
    again = simulate_ensemble(q0, jnp.ones(3), 0.1, 6, save_every=2, path=run)
    np.testing.assert_array_equal(np.asarray(again.saved), np.asarray(first.saved))
    monkeypatch.setattr(_ensemble.shutil, "disk_usage", disk_usage_with(10**10))
    argv = ["simulate", "--bodies", "1000000", "--steps", "1000", "--save-every", "1"]
    status = main([*argv, "--dtype", "float32", "--no-progress", "--output", str(tmp_path / "big")])
    err = capsys.readouterr().err
    assert status == 2 and err.count("\n") == 1, err
    assert "the saved states need 16.1 GB and the file system holding it has 10 GB free" in err, err
    assert not (tmp_path / "big").exists()


def test_saved_times_that_overflow_are_refused_before_the_run(tmp_path, capsys):
    """t0 + k·dt beyond float64 at a saved step: `simulate` exited 0 and wrote an ensemble that
    `load_ensemble` then refused (helper-49). Now a ValueError naming dt and the step, before
    anything is written; the command line prints it as one line and exits 2."""
    q0 = jnp.array([[1.0, 0.0, 0.0, 0.0]])
    with pytest.raises(ValueError, match=r"`dt` = 1e\+307.*saved step k = 20 overflows float64"):
        simulate_ensemble(q0, jnp.zeros(3), 1e307, 100, save_every=10, path=tmp_path / "run")
    assert not (tmp_path / "run").exists()
    with pytest.raises(ValueError, match=r"`t0` = -1\.7e\+308.*saved step k = 1 overflows"):
        simulate_ensemble(q0, jnp.zeros(3), -1e308, 2, t0=-1.7e308, save_every=1)
    # Times that stay finite are kept, in float64.
    run = simulate_ensemble(q0, jnp.zeros(3), 1e306, 100, save_every=10)
    np.testing.assert_array_equal(run.times, 1e306 * np.arange(0, 101, 10))
    argv = ["simulate", "--dt", "1e307", "--dtype", "float64", "--steps", "100", "--bodies", "4"]
    argv += ["--omega-scale", "0", "--save-every", "10", "--no-progress"]
    status = main([*argv, "--output", str(tmp_path / "cli")])
    out, err = capsys.readouterr()
    assert status == 2 and err.count("\n") == 1 and "overflows float64" in err, err
    assert not (tmp_path / "cli").exists()
