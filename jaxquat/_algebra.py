"""Quaternion algebra on `(..., 4)` arrays ordered (w, x, y, z), Hamilton product.

All functions broadcast leading axes like NumPy and keep the input's float dtype.
"""

from __future__ import annotations

import jax.numpy as jnp
from jaxtyping import Array, ArrayLike

from ._numerics import (
    atan2_over,
    broadcast_batch,
    check_float_dtype,
    check_shape,
    check_trailing,
    cos_half,
    eager_jit,
    power_of_two_times,
    prescale,
    scaled_norm,
    sinc_half,
    sum_squares,
    unit_vector,
)

_LN2 = 0.6931471805599453


def identity(shape: int | tuple[int, ...] = (), dtype=None) -> Array:
    """The identity rotation 1 + 0i + 0j + 0k, broadcast to `shape + (4,)`.

    **Arguments:**

    - `shape`: batch shape of the result: a non-negative int or a tuple of them.
    - `dtype`: floating dtype; defaults to JAX's default float (float64 under `jax_enable_x64`).

    **Returns:** an array of shape `(*shape, 4)`.

    **Raises:** `ValueError` for a negative / non-integer `shape` or a non-floating `dtype`.
    """
    shape = check_shape(shape, "shape")
    dtype = check_float_dtype(dtype, "dtype")
    one = jnp.zeros((4,), dtype).at[0].set(1)
    return jnp.broadcast_to(one, shape + (4,))


def _split(q: Array) -> tuple[Array, Array, Array, Array]:
    return q[..., 0], q[..., 1], q[..., 2], q[..., 3]


@eager_jit()
def multiply(p: ArrayLike, q: ArrayLike) -> Array:
    """Hamilton product p ⊗ q (i² = j² = k² = ijk = −1).

    As rotations, `multiply(q2, q1)` applies `q1` first, then `q2`.

    **Arguments:**

    - `p`, `q`: quaternions of shape `(..., 4)`; leading axes broadcast.

    **Returns:** the product, shape `(..., 4)`.

    Example: `multiply([0, 1, 0, 0], [0, 0, 1, 0])` is k = `[0, 0, 0, 1]`.
    """
    p = check_trailing(p, 4, "p")
    q = check_trailing(q, 4, "q")
    p, q = broadcast_batch((p, 1, "p"), (q, 1, "q"))
    pw, px, py, pz = _split(p)
    qw, qx, qy, qz = _split(q)
    return jnp.stack(
        [
            pw * qw - px * qx - py * qy - pz * qz,
            pw * qx + px * qw + py * qz - pz * qy,
            pw * qy - px * qz + py * qw + pz * qx,
            pw * qz + px * qy - py * qx + pz * qw,
        ],
        axis=-1,
    )


@eager_jit()
def conjugate(q: ArrayLike) -> Array:
    """The conjugate q* = w − xi − yj − zk."""
    q = check_trailing(q, 4, "q")
    # Not `q * [1, -1, -1, -1]`: that implicit rank promotion raises for batched q.
    return jnp.concatenate([q[..., :1], -q[..., 1:]], axis=-1)


@eager_jit()
def norm(q: ArrayLike) -> Array:
    """The Euclidean norm |q| = √(w² + x² + y² + z²), shape `(...)`. Gradient 0 at q = 0; NaN in, NaN out."""
    q = check_trailing(q, 4, "q")
    return scaled_norm(q)  # |q| of any finite q the dtype holds, no overflow


def no_rotation(q: Array) -> Array:
    """Where q names no rotation, shape `(...)`: q = 0 (including all-subnormal q, which XLA:CPU
    flushes to zero) or an infinite component. `inverse`, `normalize`, `to_matrix`, `rotate` and the
    conversions to axis-angle, rotation vector and Euler angles are all-NaN there instead of
    inventing an answer (q/|q| of (∞, 0, 0, 0) came out as (NaN, 0, 0, 0), and its matrix kept a
    diagonal of ones)."""
    return jnp.all(q == 0, axis=-1) | jnp.any(jnp.isinf(q), axis=-1)


def canonical_sign(q: Array) -> Array:
    """The representative of ±q with w ≥ 0, ties at w = 0 broken like SciPy's canonical form (the
    first non-zero of x, y, z positive), so that an exact half-turn has one sign however it was
    computed. Gradient: ±identity, by the locally constant sign."""
    w, x, y, z = q[..., 0], q[..., 1], q[..., 2], q[..., 3]
    flip = (w < 0) | ((w == 0) & ((x < 0) | ((x == 0) & ((y < 0) | ((y == 0) & (z < 0))))))
    return jnp.where(flip[..., None], -q, q)


@eager_jit()
def inverse(q: ArrayLike) -> Array:
    """The inverse q⁻¹ = q*/|q|² (for unit quaternions, the conjugate). NaN for q = 0 and for an
    infinite component."""
    q = check_trailing(q, 4, "q")
    q, e = prescale(q)
    out = power_of_two_times(conjugate(q) / sum_squares(q, keepdims=True), -e[..., None])
    return jnp.where(no_rotation(q)[..., None], jnp.nan, out)


@eager_jit()
def normalize(q: ArrayLike) -> Array:
    """q/|q|, the unit quaternion of the same rotation, for any finite q the dtype holds (|q|² is not
    formed from q itself when it would overflow or underflow). NaN for q = 0 (nothing is invented)
    and for a q with an infinite component; q = 0 includes a q whose components are all subnormal,
    which XLA:CPU flushes to zero."""
    q = check_trailing(q, 4, "q")
    return jnp.where(no_rotation(q)[..., None], jnp.nan, unit_vector(q))


def unit_quaternion(q: Array) -> Array:
    """q/|q| without validation or rescaling, for internal loops whose q is already near unit."""
    return q / jnp.sqrt(sum_squares(q, keepdims=True))


@eager_jit()
def dot(p: ArrayLike, q: ArrayLike) -> Array:
    """The 4-vector dot product w₁w₂ + x₁x₂ + y₁y₂ + z₁z₂, shape `(...)`."""
    p = check_trailing(p, 4, "p")
    q = check_trailing(q, 4, "q")
    p, q = broadcast_batch((p, 1, "p"), (q, 1, "q"))
    return jnp.sum(p * q, axis=-1)


@eager_jit()
def from_vector(v: ArrayLike) -> Array:
    """The pure quaternion ṽ = (0, v) of a 3-vector v (the seed's equation vectorToQuat)."""
    v = check_trailing(v, 3, "v")
    return jnp.concatenate([jnp.zeros_like(v[..., :1]), v], axis=-1)


@eager_jit()
def vector_part(q: ArrayLike) -> Array:
    """The vector (imaginary) part (x, y, z) of q, shape `(..., 3)`."""
    q = check_trailing(q, 4, "q")
    return q[..., 1:]


@eager_jit()
def exp(q: ArrayLike) -> Array:
    """The quaternion exponential exp(w + v) = eʷ (cos|v| + sin|v| v/|v|).

    The rotation of a rotation vector r is `exp((0, r/2))` (see `from_rotvec`). Series-switched near
    v = 0: value eʷ (1, 0), Jacobian w.r.t. v there eʷ·[0; I₃].
    """
    q = check_trailing(q, 4, "q")
    v = q[..., 1:]
    # cos|v| = cos(θ/2) and sin|v|/|v| = 2 sin(θ/2)/θ with θ = 2|v|.
    theta_sq = 4.0 * sum_squares(v)
    scale = jnp.exp(q[..., 0])
    w = scale * cos_half(theta_sq)
    xyz = (scale * 2.0 * sinc_half(theta_sq))[..., None] * v
    # 4|v|² overflows for |v| above ~6.7e153 (float64; ~9.2e18 in float32): there |v| itself is
    # taken, prescaled, in the direct formula (sin|v|/|v| is then at most 1/|v|, far from the series).
    huge = jnp.isinf(theta_sq) & jnp.all(jnp.isfinite(v), axis=-1)
    size = scaled_norm(jnp.where(huge[..., None], v, jnp.ones_like(v)))
    w = jnp.where(huge, scale * jnp.cos(size), w)
    # (sin|v| times the direction: sin|v|/|v| itself is subnormal above |v| ~ 1e307, ~4e37 in
    # float32, and XLA:CPU flushes it to 0, losing the vector part.)
    direction = unit_vector(jnp.where(huge[..., None], v, jnp.ones_like(v)))
    xyz = jnp.where(huge[..., None], (scale * jnp.sin(size))[..., None] * direction, xyz)
    # eʷ = ∞ times a zero component is a zero component (as for complex exp(800 + 0j) = ∞ + 0j).
    xyz = jnp.where(jnp.isinf(scale)[..., None] & (v == 0), jnp.zeros_like(xyz), xyz)
    return jnp.concatenate([w[..., None], xyz], axis=-1)


@eager_jit()
def log(q: ArrayLike) -> Array:
    """The quaternion logarithm log(q) = (ln|q|, atan2(|v|, w) v/|v|), principal branch.

    For a unit quaternion the result is the pure quaternion (0, r/2) with r the rotation vector
    (|r| ≤ 2π; use `to_rotvec` for the shortest, |r| ≤ π). Series-switched near v = 0 for w > 0: value
    (ln w, 0), Jacobian of the vector part w.r.t. v there I₃/w. `exp(log(q)) = q` to round-off for
    every nonzero q (XLA:CPU reads subnormal components as 0: a q whose only nonzero components are
    subnormal is 0, log −∞).
    A negative real q = (w < 0, 0, 0, 0) has no axis of its own: its logarithm takes the x axis,
    (ln|w|, π, 0, 0), as numpy-quaternion does (the value jumps there: every (ln|w|, π·u) with |u| = 1
    is a limit; the Jacobian of the vector part is taken as 0). `log(0)` is −∞ in w.
    Near that axis (w < 0, |v| ≪ |w|) the Jacobian of the vector part is about π/|v| across v and
    accurate relative to that size only: its entry along v (−1/|w|) comes out with an error of about
    ε·π/|v| (float32, q = (−1, 1e-6, 0, 0): −0.91 forward, −1.0 reverse; float64 at |v| = 1e-12:
    −1.0004 and −1.0005). For rotations use `to_rotvec` (or `canonicalize` first), which take w ≥ 0.
    """
    q = check_trailing(q, 4, "q")
    q, e = prescale(q)  # ln|q| = ln|q 2⁻ᵉ| + e ln 2; the vector part is scale-invariant
    w = q[..., 0]
    v = q[..., 1:]
    s_sq = sum_squares(v)
    log_norm = 0.5 * jnp.log(s_sq + w * w) + e.astype(q.dtype) * _LN2
    xyz = atan2_over(s_sq, w)[..., None] * v
    # For w < 0 and a tiny vector part the angle atan2(|v|, w) is π to round-off, and the result
    # π·v/|v| needs |v| exactly; |v|² cannot give it there. It underflows to 0 (|v|/|w| below ~1e-154
    # in float64, ~1e-19 in float32), or — XLA:CPU flushes subnormal squares to zero — loses only the
    # smaller components: (−1, 3e-154, 1e-154, 0) gave a vector part of length 3.31 instead of π.
    # Below |v|² = tiny/ε, where a flushed square could still count, |v| and v/|v| are taken from v
    # scaled on its own (`scaled_norm`, `unit_vector`), and v = 0 takes the x axis.
    finfo = jnp.finfo(q.dtype)
    small = (w < 0) & (s_sq < finfo.tiny / finfo.eps)
    has_axis = jnp.any(v != 0, axis=-1, keepdims=True)
    x_axis = jnp.zeros_like(v).at[..., 0].set(1)
    masked = jnp.where(small[..., None] & has_axis, v, x_axis)  # v = 0: the x axis
    direction = unit_vector(masked)
    angle = jnp.arctan2(scaled_norm(masked) * has_axis[..., 0], w)
    xyz = jnp.where(small[..., None], angle[..., None] * direction, xyz)
    return jnp.concatenate([log_norm[..., None], xyz], axis=-1)
