"""Test helpers: sign-invariant comparison, per-dtype tolerances, samplers incl. singular points."""

from __future__ import annotations

import contextlib

import jax
import jax.numpy as jnp
import numpy as np

# Relative tolerances for derivative checks and value comparisons, per dtype.
TOL = {jnp.dtype("float64"): 1e-7, jnp.dtype("float32"): 1e-3}


def tol(dtype) -> float:
    return TOL[jnp.dtype(dtype)]


def canonical(q):
    """Sign-fix quaternions (w ≥ 0, ties broken by the first non-zero component) for comparison."""
    q = np.asarray(q, dtype=np.float64)
    idx = np.argmax(np.abs(q) > 1e-12 * np.max(np.abs(q), axis=-1, keepdims=True), axis=-1)
    lead = np.take_along_axis(q, idx[..., None], axis=-1)
    sign = np.where(q[..., :1] != 0, np.sign(q[..., :1]), np.sign(lead))
    return q * np.where(sign == 0, 1.0, sign)


def quat_distance(p, q):
    """max over the batch of min(|p − q|, |p + q|): zero iff equal up to sign."""
    p = np.asarray(p, dtype=np.float64)
    q = np.asarray(q, dtype=np.float64)
    d = np.minimum(np.linalg.norm(p - q, axis=-1), np.linalg.norm(p + q, axis=-1))
    return float(np.max(d)) if d.size else 0.0


def assert_quat_close(p, q, atol=1e-12):
    """Assert that p and q are equal up to sign, element-wise over the batch."""
    d = quat_distance(p, q)
    assert d <= atol, f"quaternions differ (up to sign) by {d:.3e} > {atol:.1e}"


def random_unit(key, shape=(), dtype=jnp.float64):
    """Haar-uniform unit quaternions of shape `(*shape, 4)`."""
    x = jax.random.normal(key, tuple(shape) + (4,), dtype=dtype)
    return x / jnp.linalg.norm(x, axis=-1, keepdims=True)


def near_identity(key, eps, shape=(), dtype=jnp.float64):
    """Unit quaternions at angle ≈ eps from the identity (eps = 0 gives exactly the identity)."""
    r = jax.random.normal(key, tuple(shape) + (3,), dtype=dtype)
    r = eps * r / jnp.linalg.norm(r, axis=-1, keepdims=True)
    half = 0.5 * jnp.linalg.norm(r, axis=-1, keepdims=True)
    safe = jnp.where(half > 0, half, 1.0)
    vec = jnp.where(half > 0, jnp.sin(half) / safe * 0.5, 0.5) * r
    return jnp.concatenate([jnp.cos(half), vec], axis=-1)


def near_pi(key, eps, shape=(), dtype=jnp.float64):
    """Unit quaternions at angle π − eps (w ≈ 0)."""
    axis = jax.random.normal(key, tuple(shape) + (3,), dtype=dtype)
    axis = axis / jnp.linalg.norm(axis, axis=-1, keepdims=True)
    half = 0.5 * (jnp.pi - eps)
    return jnp.concatenate(
        [jnp.full(axis.shape[:-1] + (1,), jnp.cos(half), dtype), jnp.sin(half) * axis], -1
    )


def tangent_perturbation(q, direction):
    """Project a 4-vector perturbation onto the tangent space of the unit sphere at q."""
    return direction - jnp.sum(direction * q, axis=-1, keepdims=True) * q


def central_jacobian(f, x, eps=None):
    """Central finite-difference Jacobian of f at x (float64 numpy), shape f(x).shape + x.shape."""
    x = np.asarray(x, dtype=np.float64)
    if eps is None:
        eps = 1e-6
    fx = np.asarray(f(x))
    jac = np.zeros(fx.shape + x.shape)
    for idx in np.ndindex(x.shape):
        dx = np.zeros_like(x)
        dx[idx] = eps
        jac[(...,) + idx] = (np.asarray(f(x + dx)) - np.asarray(f(x - dx))) / (2 * eps)
    return jac


# The DeformableBodies.jl example of seed 001 (its rotation documentation): five point masses, their
# centre of mass, and the positions after rotating by 1+2i+3j+4k about it, as printed there.
SEED_MASSES = np.array(
    [
        0.027623475555394572,
        0.08235034045511802,
        0.16330720003612642,
        0.8618919657812625,
        0.5806780634969708,
    ]
)
SEED_POSITIONS = np.array(
    [
        [0.622502144842952, 0.11921732534587282, 0.8843304426741481],
        [0.9932241501452683, 0.334779563612172, 0.8007546565223924],
        [0.386699947607279, 0.8099171674657109, 0.5908987643400341],
        [0.000659859384851913, 0.7755364055477827, 0.37741989797604925],
        [0.922564768890463, 0.04356399040074832, 0.18765714901619934],
    ]
)
SEED_CENTRE = np.array([0.40704043526795597, 0.4993749112573767, 0.3619966261272671])
SEED_ROTATED = np.array(
    [
        [0.5957564162308041, 1.1179577906424625, 0.14864795800777955],
        [0.31606113462014573, 1.2375345239874034, 0.46226994400353016],
        [0.629867962558881, 0.5349019262226586, 0.6755761877965223],
        [0.7260927511178531, 0.14668287713769346, 0.48634359841711555],
        [-0.1252661931427156, 0.8787684558838791, 0.08516928092044052],
    ]
)
SEED_ROTATED_CENTRE = np.array([0.40704043526795597, 0.49937491125737676, 0.361996626127267])


def mapping_count() -> int | None:
    """How many memory areas this process has mapped (None where /proc/self/maps is not available):
    `tests/conftest.py` keeps each worker under the kernel's limit."""
    try:
        with open("/proc/self/maps", "rb") as maps:
            return maps.read().count(b"\n")
    except OSError:
        return None


_LOWERING = "/jax/core/compile/jaxpr_to_mlir_module_duration"


@contextlib.contextmanager
def count_lowerings():
    """A list that collects one entry for each program JAX lowers for compilation inside the block,
    i.e. each miss of its in-memory compilation caches (whether or not the persistent cache then
    holds the compiled program)."""
    lowered = []

    def listener(name, duration, **kwargs):
        if name == _LOWERING:
            lowered.append(duration)

    jax.monitoring.register_event_duration_secs_listener(listener)
    try:
        yield lowered
    finally:
        jax.monitoring.unregister_event_duration_listener(listener)


def run_on_four_devices(script: str, timeout: float = 600) -> dict:
    """Run a Python `script` in a subprocess with four host (CPU) devices (the device count is fixed
    when JAX starts) and return the JSON object its last line of stdout prints."""
    import json
    import os
    import subprocess
    import sys

    env = dict(
        os.environ, XLA_FLAGS="--xla_force_host_platform_device_count=4", JAX_PLATFORMS="cpu"
    )
    proc = subprocess.run(
        [sys.executable, "-c", script], capture_output=True, text=True, env=env, timeout=timeout
    )
    assert proc.returncode == 0, proc.stderr[-3000:]
    return json.loads(proc.stdout.strip().splitlines()[-1])
