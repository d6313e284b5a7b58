"""Rotations: rotating vectors, and conversions between unit quaternions and other representations.

Active rotations with the right-hand rule: v' = q v q⁻¹. Quaternions are (w, x, y, z).
"""

from __future__ import annotations

import jax.numpy as jnp
from jaxtyping import Array, ArrayLike

from ._numerics import (
    as_float_array,
    atan2_over,
    broadcast_batch,
    check_trailing,
    cos_half,
    cross,
    safe_norm,
    sinc_half,
    sum_squares,
)


def rotate(v: ArrayLike, q: ArrayLike, center: ArrayLike | None = None) -> Array:
    """Rotate vectors `v` by the quaternion `q` about `center`: v' = q (v − c) q⁻¹ + c.

    `q` need not be unit: q⁻¹ = q*/|q|² is used, so only the direction of q matters (the seed's
    `rotate(v, q, center)`; with `center=None` the origin).

    **Arguments:**

    - `v`: vectors, shape `(..., 3)`. A point set `(n, 3)` rotated by one `q` of shape `(4,)` broadcasts.
    - `q`: quaternions, shape `(..., 4)`; leading axes broadcast with those of `v`.
    - `center`: optional centre of rotation, shape `(..., 3)`.

    **Returns:** the rotated vectors, shape `(..., 3)`.

    Example: `rotate([3, 0, 0], [1, 2, 3, 4])` is `[-2, 2, 1]`.
    """
    v = check_trailing(v, 3, "v")
    q = check_trailing(q, 4, "q")
    if center is not None:
        center = check_trailing(center, 3, "center")
        v, q, center = broadcast_batch((v, 1), (q, 1), (center, 1))
        v = v - center
    else:
        v, q = broadcast_batch((v, 1), (q, 1))
    w = q[..., :1]
    u = q[..., 1:]
    scale = 2.0 / sum_squares(q, keepdims=True)
    uv = cross(u, v)
    out = v + scale * (w * uv + cross(u, uv))
    if center is not None:
        out = out + center
    return out


def from_axis_angle(axis: ArrayLike, angle: ArrayLike) -> Array:
    """The unit quaternion (cos(θ/2), sin(θ/2) n̂) of a rotation by `angle` θ about `axis` (right-hand).

    `axis` need not be unit (it is normalised; a zero axis gives the identity). `angle` has shape
    `(...)` and broadcasts with the batch shape of `axis`.

    Example: `from_axis_angle([0, 0, 2], jnp.pi / 2)` is `[0.70711, 0, 0, 0.70711]`.
    """
    axis = check_trailing(axis, 3, "axis")
    angle = as_float_array(angle, "angle")
    axis_norm = safe_norm(axis, keepdims=True)
    unit = axis / jnp.where(axis_norm > 0, axis_norm, jnp.ones_like(axis_norm))
    unit, angle = broadcast_batch((unit, 1), (angle, 0))
    half = 0.5 * angle
    return jnp.concatenate([jnp.cos(half)[..., None], jnp.sin(half)[..., None] * unit], axis=-1)


def to_axis_angle(q: ArrayLike) -> tuple[Array, Array]:
    """The axis (unit, shape `(..., 3)`) and angle in [0, π] (shape `(...)`) of the rotation q.

    `q` need not be unit. At the identity the axis is undefined and `(1, 0, 0)` is returned.
    """
    q = check_trailing(q, 4, "q")
    q = jnp.where(q[..., :1] < 0, -q, q)
    v = q[..., 1:]
    s = safe_norm(v)
    angle = 2.0 * jnp.arctan2(s, q[..., 0])
    default = jnp.zeros_like(v).at[..., 0].set(1.0)
    safe_s = jnp.where(s > 0, s, jnp.ones_like(s))[..., None]
    axis = jnp.where((s > 0)[..., None], v / safe_s, default)
    return axis, angle


def from_rotvec(r: ArrayLike) -> Array:
    """The unit quaternion exp(r/2) = (cos(|r|/2), sin(|r|/2) r/|r|) of a rotation vector r.

    Series-switched at r = 0: value (1, 0, 0, 0), Jacobian ½·[0; I₃] (SciPy's and jax.scipy's are NaN).
    """
    r = check_trailing(r, 3, "r")
    theta_sq = sum_squares(r)
    return jnp.concatenate([cos_half(theta_sq)[..., None], sinc_half(theta_sq)[..., None] * r], axis=-1)


def to_rotvec(q: ArrayLike) -> Array:
    """The rotation vector r (|r| ≤ π) of the rotation q; `q` need not be unit.

    r = 2·atan2(|v|, |w|)·sgn(w) v/|v|. Series-switched at the identity: value 0, Jacobian [0 | 2·I₃].
    """
    q = check_trailing(q, 4, "q")
    q = jnp.where(q[..., :1] < 0, -q, q)
    v = q[..., 1:]
    return (2.0 * atan2_over(sum_squares(v), q[..., 0]))[..., None] * v


def to_matrix(q: ArrayLike) -> Array:
    """The 3×3 rotation matrix R with R v = q v q⁻¹; `q` need not be unit (uses 2/|q|²).

    Example: `to_matrix([1, 2, 3, 4])` is the seed's table
    `[[-2/3, 2/15, 11/15], [2/3, -1/3, 2/3], [1/3, 14/15, 2/15]]`.
    """
    q = check_trailing(q, 4, "q")
    w, x, y, z = q[..., 0], q[..., 1], q[..., 2], q[..., 3]
    s = 2.0 / sum_squares(q)
    xx, yy, zz = s * x * x, s * y * y, s * z * z
    xy, xz, yz = s * x * y, s * x * z, s * y * z
    wx, wy, wz = s * w * x, s * w * y, s * w * z
    rows = [
        [1.0 - (yy + zz), xy - wz, xz + wy],
        [xy + wz, 1.0 - (xx + zz), yz - wx],
        [xz - wy, yz + wx, 1.0 - (xx + yy)],
    ]
    return jnp.stack([jnp.stack(row, axis=-1) for row in rows], axis=-2)


def from_xyzw(q: ArrayLike) -> Array:
    """Reorder a scalar-last quaternion (x, y, z, w) (SciPy's default, ROS) to jaxquat's (w, x, y, z)."""
    q = check_trailing(q, 4, "q")
    return jnp.roll(q, 1, axis=-1)


def to_xyzw(q: ArrayLike) -> Array:
    """Reorder (w, x, y, z) to scalar-last (x, y, z, w)."""
    q = check_trailing(q, 4, "q")
    return jnp.roll(q, -1, axis=-1)
