"""Rotations: rotating vectors, and conversions between unit quaternions and other representations.

Active rotations with the right-hand rule: v' = q v q⁻¹. Quaternions are (w, x, y, z).
"""

from __future__ import annotations

import jax.numpy as jnp
from jaxtyping import Array, ArrayLike

from ._algebra import canonical_sign, no_rotation
from ._numerics import (
    as_float_array,
    atan2_over,
    broadcast_batch,
    check_matrix,
    check_trailing,
    cos_half,
    cross,
    eager_jit,
    prescale,
    safe_atan2,
    safe_norm,
    scaled_norm,
    sinc_half,
    sum_squares,
    top_eigenvector,
    unit_vector,
)


@eager_jit()
def rotate(
    v: ArrayLike,
    q: ArrayLike | None = None,
    center: ArrayLike | None = None,
    *,
    axis: ArrayLike | None = None,
    angle: ArrayLike | None = None,
) -> Array:
    """Rotate vectors `v` by the quaternion `q` about `center`: v' = q (v − c) q⁻¹ + c.

    `q` need not be unit: q⁻¹ = q*/|q|² is used, so only the direction of q matters (the seed's
    `rotate(v, q, center)`; with `center=None` the origin). Any finite nonzero q the dtype holds works
    (nonzero: not all components zero or subnormal, since XLA:CPU flushes subnormal numbers to zero):
    one whose |q|² would overflow or underflow is first scaled by an exact power of two.
    As in DeformableBodies.jl, the rotation may be given as `axis=` and `angle=` instead of `q`
    (`rotate(v, axis=n, angle=θ, center=c)` is `rotate(v, from_axis_angle(n, θ), c)`).

    **Arguments:**

    - `v`: vectors, shape `(..., 3)`. A point set `(n, 3)` rotated by one `q` of shape `(4,)` broadcasts.
    - `q`: quaternions, shape `(..., 4)`; leading axes broadcast with those of `v`.
    - `center`: optional centre of rotation, shape `(..., 3)`.
    - `axis`, `angle` (keywords, instead of `q`): a rotation axis `(..., 3)` (need not be unit) and
      angle in radians `(...)`, right-handed, as for `from_axis_angle`.

    **Returns:** the rotated vectors, shape `(..., 3)`.

    **Errors:** a `ValueError` naming the argument for a bad shape, and for a call giving neither
    `q` nor both `axis` and `angle`, or both.

    Example: `rotate([3, 0, 0], [1, 2, 3, 4])` is `[-2, 2, 1]`;
    `rotate([1, 0, 0], axis=[0, 0, 1], angle=jnp.pi / 2, center=[0, 1, 0])` is `[1, 2, 0]`.
    """
    given = [f"`{name}`" for name, x in (("axis", axis), ("angle", angle)) if x is not None]
    if q is None:
        if len(given) < 2:
            raise ValueError(
                "`rotate` needs the rotation: a quaternion `q`, or both `axis` and `angle`; got "
                f"{'only ' + given[0] if given else 'neither'}."
            )
        q = from_axis_angle(axis, angle)
    elif given:
        raise ValueError(
            "`rotate` takes the rotation as `q` or as `axis` and `angle`, not both; got `q` and "
            f"{' and '.join(given)}."
        )
    v = check_trailing(v, 3, "v")
    q = check_trailing(q, 4, "q")
    if center is not None:
        center = check_trailing(center, 3, "center")
        v, q, center = broadcast_batch((v, 1, "v"), (q, 1, "q"), (center, 1, "center"))
        v = v - center
    else:
        v, q = broadcast_batch((v, 1, "v"), (q, 1, "q"))
    # q at scale 1 whatever |v|: the formula's cross(u, cross(u, v)) is |q|²·|v| before its 2/|q|²
    # (float32 rotate([1e30, 0, 0], [1e5, 0, 0, 1e5]) overflowed; helper-53).
    out = rotate_unchecked(v, prescale(q, limit=0)[0])
    if center is not None:
        out = out + center
    return out


def rotate_unchecked(v: Array, q: Array) -> Array:
    """q v q⁻¹ for broadcast `(..., 3)` and `(..., 4)` arrays, without validation or rescaling (for
    internal loops whose q is near unit; `rotate` brings any finite q into range first)."""
    w = q[..., :1]
    u = q[..., 1:]
    scale = 2.0 / sum_squares(q, keepdims=True)
    uv = cross(u, v)
    return v + scale * (w * uv + cross(u, uv))


@eager_jit()
def from_axis_angle(axis: ArrayLike, angle: ArrayLike) -> Array:
    """The unit quaternion (cos(θ/2), sin(θ/2) n̂) of a rotation by `angle` θ about `axis` (right-hand).

    `axis` need not be unit (it is normalised; a zero axis gives the identity for any finite angle, and
    so does an all-subnormal one, which XLA:CPU flushes to zero).
    `angle` has shape `(...)` and broadcasts with the batch shape of `axis`. NaN in either, or an
    infinite component of the axis (which has no direction), gives NaN in every component.

    Example: `from_axis_angle([0, 0, 2], jnp.pi / 2)` is `[0.70711, 0, 0, 0.70711]`.
    """
    axis = check_trailing(axis, 3, "axis")
    angle = as_float_array(angle, "angle")
    axis, angle = broadcast_batch((axis, 1, "axis"), (angle, 0, "angle"))
    # `unit_vector` divides by the largest |component| first, so |axis|² can neither overflow nor
    # underflow (a float32 axis of length 1e20 or 1e-20 has a direction too). A zero axis is replaced
    # by a safe one (its angle is dropped below); a NaN or infinite axis is not all zero and gives
    # NaN.
    has_axis = ~jnp.all(axis == 0, axis=-1, keepdims=True)
    unit = unit_vector(jnp.where(has_axis, axis, jnp.ones_like(axis)))
    # No axis, no rotation: the angle about a zero axis is dropped (else (cos θ/2, 0, 0, 0), not unit).
    # `0 * angle` rather than a literal 0 keeps a NaN angle NaN (its derivative is still 0).
    half = jnp.where(has_axis[..., 0], 0.5 * angle, 0.0 * angle)
    half = jnp.where(
        jnp.any(~jnp.isfinite(axis), axis=-1), jnp.nan, half
    )  # a NaN or infinite axis: NaN, w included ((inf, 0, 0) gave a finite w and a NaN x)
    return jnp.concatenate([jnp.cos(half)[..., None], jnp.sin(half)[..., None] * unit], axis=-1)


@eager_jit()
def to_axis_angle(q: ArrayLike) -> tuple[Array, Array]:
    """The axis (unit, shape `(..., 3)`) and angle in [0, π] (shape `(...)`) of the rotation q.

    `q` need not be unit (any finite nonzero magnitude). At the identity the axis is undefined and
    `(1, 0, 0)` is returned. A NaN anywhere in `q`, q = 0 or an infinite component gives NaN axis and
    angle.

    **Gradient:** smooth for angles in (0, π). The angle is a cone 2|v|/|w| at the identity, where
    its gradient is 0 (the safe norm's choice, no NaN) and the axis's is 0 too. At a half-turn
    (w = 0) q and −q meet, and the derivative is that of the w ≥ 0 side: ∂angle/∂w = −2/|v| (where
    `angle_between` takes 0 instead); for a smooth angle near π use `to_rotvec` away from w = 0 or
    a sign-invariant loss.
    """
    q = prescale(check_trailing(q, 4, "q"))[0]
    undefined = no_rotation(q)
    q = jnp.where(q[..., :1] < 0, -q, q)
    v = q[..., 1:]
    # |v| prescaled on its own: beside w ≈ 1, |v|² of a rotation by less than ~2e-19 rad (float32;
    # ~3e-154 in float64) underflows, and gave angle 0 with the default axis.
    s = scaled_norm(v)
    angle = 2.0 * jnp.arctan2(s, q[..., 0])
    default = jnp.zeros_like(v).at[..., 0].set(1.0)
    # `~(s <= 0)`, not `s > 0`: a NaN vector part takes the computing branch (NaN), not the default.
    has_axis = ~(s <= 0)
    safe_s = jnp.where(has_axis, s, jnp.ones_like(s))[..., None]
    axis = jnp.where(has_axis[..., None], v / safe_s, default)
    # A NaN w leaves v/|v| finite but its sign (the w ≥ 0 choice) undecided: report NaN, not a guess.
    axis = jnp.where(jnp.isnan(angle)[..., None], jnp.nan, axis)
    return (
        jnp.where(undefined[..., None], jnp.nan, axis),
        jnp.where(undefined, jnp.nan, angle),
    )


@eager_jit()
def from_rotvec(r: ArrayLike) -> Array:
    """The unit quaternion exp(r/2) = (cos(|r|/2), sin(|r|/2) r/|r|) of a rotation vector r.

    Series-switched at r = 0: value (1, 0, 0, 0), Jacobian ½·[0; I₃] (SciPy's and jax.scipy's are NaN).
    NaN when |r|² overflows (|r| above ~1.3e154 in float64, ~1.8e19 in float32), where one unit in
    the last place of |r| is already many turns; `exp((0, r/2))` takes such vectors too (at the cost
    of a second cos and sin, which this function, called in integrators' inner loops, avoids).
    """
    r = check_trailing(r, 3, "r")
    theta_sq = sum_squares(r)
    return jnp.concatenate(
        [cos_half(theta_sq)[..., None], sinc_half(theta_sq)[..., None] * r], axis=-1
    )


@eager_jit()
def to_rotvec(q: ArrayLike) -> Array:
    """The rotation vector r (|r| ≤ π) of the rotation q; `q` need not be unit (any finite nonzero
    magnitude; q = 0 or an infinite component gives NaN).

    r = 2·atan2(|v|, |w|)·sgn(w) v/|v|. Series-switched at the identity: value 0, Jacobian [0 | 2·I₃].
    At a half-turn (w = 0) r jumps to −r across w = 0 (|r| = π both sides), and the Jacobian there is
    that of the w ≥ 0 side, finite.
    """
    q = prescale(check_trailing(q, 4, "q"))[0]
    undefined = no_rotation(q)
    q = jnp.where(q[..., :1] < 0, -q, q)
    v = q[..., 1:]
    r = (2.0 * atan2_over(sum_squares(v), q[..., 0]))[..., None] * v
    return jnp.where(undefined[..., None], jnp.nan, r)


@eager_jit()
def to_matrix(q: ArrayLike) -> Array:
    """The 3×3 rotation matrix R with R v = q v q⁻¹; `q` need not be unit (uses 2/|q|², after
    scaling an extreme q by a power of two so that |q|² neither overflows nor underflows).

    Example: `to_matrix([1, 2, 3, 4])` is the seed's table
    `[[-2/3, 2/15, 11/15], [2/3, -1/3, 2/3], [1/3, 14/15, 2/15]]`.
    """
    q = prescale(check_trailing(q, 4, "q"))[0]
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
    matrix = jnp.stack([jnp.stack(row, axis=-1) for row in rows], axis=-2)
    return jnp.where(no_rotation(q)[..., None, None], jnp.nan, matrix)


@eager_jit()
def from_xyzw(q: ArrayLike) -> Array:
    """Reorder a scalar-last quaternion (x, y, z, w) (SciPy's default, ROS) to jaxquat's (w, x, y, z)."""
    q = check_trailing(q, 4, "q")
    return jnp.roll(q, 1, axis=-1)


@eager_jit()
def to_xyzw(q: ArrayLike) -> Array:
    """Reorder (w, x, y, z) to scalar-last (x, y, z, w)."""
    q = check_trailing(q, 4, "q")
    return jnp.roll(q, -1, axis=-1)


@eager_jit()
def from_matrix(m: ArrayLike) -> Array:
    r"""The unit quaternion (w ≥ 0) of the rotation matrix nearest to `m` in the Frobenius norm.

    Davenport's q-method in Bar-Itzhack's form (Bar-Itzhack 2000, "New method for extracting the
    quaternion from a rotation matrix", J. Guid. Control Dyn. 23(6)): for any 3×3 matrix M,
    $\operatorname{tr}(R(q)^\top M) = q^\top K q$ with the symmetric 4×4 matrix
    $K = \begin{bmatrix} \operatorname{tr} M & a^\top \\ a & M + M^\top - \operatorname{tr}(M) I \end{bmatrix}$,
    $a = (M_{32} - M_{23}, M_{13} - M_{31}, M_{21} - M_{12})$. Since
    $\|R - M\|_F^2 = \text{const} - 2\operatorname{tr}(R^\top M)$, the top eigenvector of K is the
    rotation nearest to M (the special-orthogonal Procrustes solution, i.e. the SVD projection with the
    determinant fixed). For an exact rotation the eigenvalues are (3, −1, −1, −1): well separated, so
    the result is accurate everywhere, including half-turns, with no branch on the largest diagonal.
    When every matrix of the batch is near a rotation, the eigenvector comes from eight power steps,
    kept only if a residual and eigenvalue-gap check proves them converged; otherwise from `eigh`.
    Under `jax.vmap` the whole mapped batch makes that choice once, as a batched call does.
    Either way the result is the same to round-off. On a 2-core CPU, 10⁵ rotations take 22 ms in
    float64, against 106 ms with `eigh` for every matrix and 28 ms for SciPy.

    **Arguments:**

    - `m`: matrices, shape `(..., 3, 3)`; need not be exactly orthogonal. A reflection (det < 0) is
      accepted, unlike SciPy's `Rotation.from_matrix`, and gives its nearest rotation; for an exact
      reflection such as −I, or the zero matrix, that rotation is not unique and one of them is
      returned, with NaN derivatives.

    **Returns:** unit quaternions, shape `(..., 4)`, canonicalised to w ≥ 0 (q and −q are the same
    rotation; `from_matrix(to_matrix(q))` is ±q); at w = 0 exactly, as `canonicalize` and SciPy's
    canonical form, the first non-zero of x, y, z is positive.

    **Gradient:** by perturbation theory of the simple top eigenvalue (`_numerics.top_eigenvector`):
    smooth wherever the nearest rotation is unique, finite at the identity. The sign choice w ≥ 0 makes
    the result jump to the other sheet across exact half-turns (w = 0).

    Example: the seed's matrix of a π/4 turn about z gives `[0.92388, 0, 0, 0.38268]`.
    """
    # The nearest rotation to s·M (s > 0) is that of M: an extreme scale is brought into range first
    # (a float32 1e19·R made K's power step overflow).
    m = prescale(check_matrix(m, "m"), axes=(-2, -1))[0]
    trace = m[..., 0, 0] + m[..., 1, 1] + m[..., 2, 2]
    a = jnp.stack(
        [m[..., 2, 1] - m[..., 1, 2], m[..., 0, 2] - m[..., 2, 0], m[..., 1, 0] - m[..., 0, 1]],
        axis=-1,
    )
    eye = jnp.broadcast_to(jnp.eye(3, dtype=m.dtype), m.shape)
    lower = m + jnp.swapaxes(m, -1, -2) - trace[..., None, None] * eye
    k = jnp.concatenate(
        [
            jnp.concatenate([trace[..., None, None], a[..., None, :]], axis=-1),
            jnp.concatenate([a[..., :, None], lower], axis=-1),
        ],
        axis=-2,
    )
    q = top_eigenvector(k, davenport=True)
    # One power step with K + I: for an exact rotation K + I = 4 q qᵀ (eigenvalues 3, −1, −1, −1 of K
    # shifted to 4, 0, 0, 0), so the step rebuilds q from the matrix entries themselves — eigh alone
    # drops components below ~ulp(1)/4 (float32: rotations under ~3e-8 rad came out as the identity).
    # The eigenvector is a fixed point of the step, and the step's derivative at it is the
    # eigenvector's, so derivatives are unchanged; trace K = 0 makes λ₁ + 1 ≥ 1 (no amplification).
    q = jnp.einsum("...ij,...j->...i", k, q) + q
    q = q / jnp.sqrt(sum_squares(q, keepdims=True))
    # w ≥ 0; at an exact half-turn (w = 0, e.g. any symmetric matrix of trace −1) the power steps and
    # `eigh` return either sign, so the result depended on the rest of the batch: SciPy's tie rule.
    return canonical_sign(q)


_AXIS_INDEX = {"x": 0, "y": 1, "z": 2}


def _parse_seq(seq) -> tuple[bool, tuple[int, int, int]]:
    """Validate an Euler sequence (SciPy's rule) → (extrinsic, axis indices)."""
    if not isinstance(seq, str):
        shape = getattr(seq, "shape", ())
        got = f"an array of shape {tuple(shape)}" if shape else repr(seq)
        raise ValueError(
            f"`seq` must be 3 axes in a string, such as 'xyz' or 'ZXZ'; got {got} (the arguments "
            "are from_euler(seq, angles) and to_euler(q, seq), as in SciPy)."
        )
    valid = (
        len(seq) == 3
        and (set(seq) <= set("xyz") or set(seq) <= set("XYZ"))
        and seq[0] != seq[1]
        and seq[1] != seq[2]
    )
    if not valid:
        raise ValueError(
            "`seq` must be 3 axes from 'xyz' (extrinsic) or from 'XYZ' (intrinsic), not mixing case, "
            f"with no axis repeated consecutively (e.g. 'xyz', 'ZXZ'); got {seq!r}."
        )
    return seq.islower(), tuple(_AXIS_INDEX[c] for c in seq.lower())


def _axis_numbers(ndim: int) -> Array:
    """(0, 1, 2) along the last of `ndim` axes (the others of size 1: no rank promotion)."""
    return jnp.arange(3).reshape((1,) * (ndim - 1) + (3,))


def _elementary(axis: int, angle: Array) -> Array:
    half = 0.5 * angle
    # The zero components by a select against sin(half/2), not a zeros_like(angle) stacked beside
    # it: under vmap over a batch sharded with explicit axis types, zeros_like loses the batch's
    # sharding and the stack of differently sharded operands is a ShardingTypeError.
    here = _axis_numbers(half.ndim + 1) == axis
    vector = jnp.where(here, jnp.sin(half)[..., None], jnp.zeros((), angle.dtype))
    return jnp.concatenate([jnp.cos(half)[..., None], vector], axis=-1)


def _hamilton(p: Array, q: Array) -> Array:
    pw, pv = p[..., :1], p[..., 1:]
    qw, qv = q[..., :1], q[..., 1:]
    w = pw * qw - jnp.sum(pv * qv, axis=-1, keepdims=True)
    return jnp.concatenate([w, pw * qv + qw * pv + cross(pv, qv)], axis=-1)


@eager_jit(("seq",))
def from_euler(seq: str, angles: ArrayLike) -> Array:
    """The unit quaternion of Euler angles, with SciPy's sequences and case rule.

    Upper-case `seq` (e.g. `"XYZ"`) is intrinsic: rotate about X, then about the *new* Y, then the new
    Z, i.e. q = q_X(α) ⊗ q_Y(β) ⊗ q_Z(γ). Lower-case (e.g. `"xyz"`) is extrinsic: about the fixed axes
    x, then y, then z, i.e. q = q_z(γ) ⊗ q_y(β) ⊗ q_x(α). All 12 sequences: the 6 Tait–Bryan
    (`xyz`, `xzy`, …) and the 6 proper Euler (`zxz`, `xyx`, …) ones, in either case.

    **Arguments:**

    - `seq`: the axis sequence, 3 characters.
    - `angles`: (α, β, γ) in radians, shape `(..., 3)`, in the order of `seq`.

    **Returns:** unit quaternions, shape `(..., 4)` (not sign-canonicalised). Smooth in the angles.

    Agrees with `scipy.spatial.transform.Rotation.from_euler(seq, angles)` (up to sign).
    """
    extrinsic, axes = _parse_seq(seq)
    angles = check_trailing(angles, 3, "angles")
    factors = [_elementary(axis, angles[..., n]) for n, axis in enumerate(axes)]
    q = factors[0]
    for factor in factors[1:]:
        q = _hamilton(factor, q) if extrinsic else _hamilton(q, factor)
    return q


# SciPy's threshold on the middle angle for declaring gimbal lock.
_GIMBAL_LOCK_EPS = 1e-7


@eager_jit(("seq",))
def to_euler(q: ArrayLike, seq: str) -> Array:
    r"""Euler angles of the rotation q for the sequence `seq` (SciPy's conventions and ranges).

    The quaternion algorithm of Bernardes & Bewley (2022), "Quaternion to Euler angles conversion:
    A direct, general and computationally efficient method", PLoS ONE 17(11): e0276302, as SciPy
    implements it, except that the Tait–Bryan middle angle comes from its sine and cosine: SciPy
    subtracts π/2 from a proper-Euler angle, an absolute error of ~eps·π/4 (6e-8 rad in float32,
    all of an angle below ~1e-7); here the sine's two products cancel for small angles, so the
    error is absolute too but smaller, a fraction of eps (at most 1.5e-8 rad in float32 over 3,000
    random middle angles below 1e-6, against exact values from mpmath).
    The first and third angles lie in [−π, π]; the middle one in [0, π] for proper Euler sequences
    (`zxz`, …) and in [−π/2, π/2] for Tait–Bryan ones (`xyz`, …). Within 1e-7 of gimbal lock
    (middle angle 0 or π; ±π/2 for Tait–Bryan; the distance to the lock computed without
    cancellation, in float32 too) the split between first and third angle is not unique:
    as SciPy does, the third angle is set to 0 — without SciPy's warning, since values are not
    inspected under `jit`.

    **Arguments:**

    - `q`: quaternions, shape `(..., 4)`; need not be unit (only the rotation matters, at any finite
      nonzero magnitude; q = 0 or an infinite component gives NaN angles); sign-invariant.
    - `seq`: 3 axes; lower case extrinsic, upper case intrinsic (see `from_euler`).

    **Returns:** angles in radians, shape `(..., 3)`, in the order of `seq`.

    **Gradient:** exact away from gimbal lock and from the ±π wrap of the first and third angles
    (where Euler angles themselves are not differentiable); finite (NaN-free) at gimbal lock.
    A NaN anywhere in `q` gives NaN angles.
    """
    extrinsic, axes = _parse_seq(seq)
    q = prescale(check_trailing(q, 4, "q"))[0]
    undefined = no_rotation(q)
    i, j, k = axes if extrinsic else axes[::-1]
    symmetric = i == k
    if symmetric:
        k = 3 - i - j
    sign = float((i - j) * (j - k) * (k - i) // 2)
    w, qi, qj, qk = q[..., 0], q[..., 1 + i], q[..., 1 + j], q[..., 1 + k]
    if symmetric:
        a, b, c, d = w, qi, qj, sign * qk
    else:
        a, b, c, d = w - qj, qi + sign * qk, qj + w, sign * qk - qi
    half_sum = safe_atan2(b, a)
    half_diff = safe_atan2(d, c)
    norm_ab = safe_norm(jnp.stack([a, b], axis=-1))
    norm_cd = safe_norm(jnp.stack([c, d], axis=-1))
    middle = 2.0 * jnp.arctan2(norm_cd, norm_ab)
    # SciPy's 1e-7 on both sides. The distance from π is 2·atan2(|a, b|, |c, d|), not π − middle:
    # that difference cancels (float32 cannot hold π − 1e-7 apart from π: it needed a window of
    # 4π·eps ≈ 1.5e-6, which locked rotations whose split float32 still determines to ~1e-7).
    at_zero = jnp.abs(middle) <= _GIMBAL_LOCK_EPS
    at_pi = 2.0 * jnp.arctan2(norm_ab, norm_cd) <= _GIMBAL_LOCK_EPS
    regular = ~(at_zero | at_pi)
    locked = jnp.where(at_zero, 2.0 * half_sum, (-2.0 if extrinsic else 2.0) * half_diff)
    zero = jnp.zeros_like(middle)
    third_sign = 1.0 if symmetric else sign
    if extrinsic:
        first = jnp.where(regular, half_sum - half_diff, locked)
        third = third_sign * jnp.where(regular, half_sum + half_diff, zero)
    else:
        first = third_sign * jnp.where(regular, half_sum + half_diff, locked)
        third = jnp.where(regular, half_sum - half_diff, zero)
    if not symmetric:
        # Not `middle − π/2`: that cancels near a Tait–Bryan middle angle of 0 (absolute error
        # ~eps·π/4, all of a float32 angle below ~1e-7). Its sine and cosine times 2|q|² instead:
        # |c, d|² − |a, b|² = 4(w q_j − sign q_i q_k) without cancellation, and 2|a, b||c, d|.
        middle = jnp.arctan2(4.0 * (w * qj - sign * qi * qk), 2.0 * norm_ab * norm_cd)
    angles = jnp.stack([first, middle, third], axis=-1)
    # Every angle is in [−2π, 2π]; one wrap into [−π, π] as SciPy does (±π are both kept).
    two_pi = 2.0 * jnp.pi
    angles = jnp.where(
        angles < -jnp.pi, angles + two_pi, jnp.where(angles > jnp.pi, angles - two_pi, angles)
    )
    return jnp.where(undefined[..., None], jnp.nan, angles)


@eager_jit()
def from_two_vectors(a: ArrayLike, b: ArrayLike) -> Array:
    r"""The shortest rotation taking the direction of `a` to the direction of `b`.

    With unit â, b̂, c = â × b̂ and the angle θ = atan2(|c|, â·b̂) ∈ [0, π]:

    - for â·b̂ ≥ 0, the half-angle (bisector) form q = (|h|/2, c/|h|), h = â + b̂, which is smooth
      at parallel vectors (value 1, derivative ½ dc there);
    - for â·b̂ < 0, q = (cos(θ/2), sin(θ/2) n̂) with n̂ = c/|c| after removing from c the rounding
      component along â (c ⟂ â exactly in real arithmetic). θ from atan2 avoids the cancellation in
      1 + â·b̂, and n̂ ⟂ â keeps `rotate(a, q)` on the right side even when c is at rounding level.
    - for antiparallel inputs (|c| ≤ 4 eps, i.e. to rounding) every half-turn about an axis ⟂ â is
      a shortest rotation; the one about â × e is returned, e the basis vector least aligned with â
      (the same with and without `jit`).

    **Arguments:**

    - `a`, `b`: non-zero vectors, shape `(..., 3)`, any lengths the dtype holds (|a|² may overflow);
      leading axes broadcast. XLA:CPU reads subnormal components as 0: such a component is lost
      (float32 (2e-38, 5e-39, 0) is taken along x), and an all-subnormal vector gives NaN.

    **Returns:** unit quaternions (w ≥ 0), shape `(..., 4)`, with `rotate(a, q)` parallel to `b`.

    **Gradient:** smooth except at antiparallel inputs, where the rotation is not unique: there it is
    finite (NaN-free), and near them it grows like 1/|â + b̂|. Zero vectors give NaN (no direction).
    """
    a = check_trailing(a, 3, "a")
    b = check_trailing(b, 3, "b")
    a, b = broadcast_batch((a, 1, "a"), (b, 1, "b"))
    a_unit, b_unit = unit_vector(a), unit_vector(b)
    cosine = jnp.sum(a_unit * b_unit, axis=-1, keepdims=True)
    c = cross(a_unit, b_unit)
    acute = cosine >= 0
    # Acute: bisector form (h is bounded away from 0 here).
    h_sq = sum_squares(a_unit + b_unit, keepdims=True)
    h_norm = jnp.sqrt(jnp.where(acute, h_sq, jnp.ones_like(h_sq)))
    bisector = jnp.concatenate([0.5 * h_norm, c / h_norm], axis=-1)
    # Obtuse: axis-angle form with the axis made exactly perpendicular to â.
    c_perp = c - jnp.sum(c * a_unit, axis=-1, keepdims=True) * a_unit
    s_sq = sum_squares(c_perp, keepdims=True)
    # Antiparallel to rounding: under `jit` the compiler contracts the cross product into fused
    # multiply-adds, and c of exactly antiparallel inputs comes out as noise of ~1e-16 (float64) in
    # a random direction instead of 0 (measured ≤ 1.2 eps). Below 4 eps (an angle of ~1e-15 rad
    # from antiparallel) the fallback axis is taken, so the result does not depend on compilation.
    tiny = 4.0 * float(jnp.finfo(a.dtype).eps)
    has_axis = ~(s_sq <= tiny * tiny)  # NaN takes the computing branch
    s = jnp.sqrt(jnp.where(has_axis, s_sq, jnp.ones_like(s_sq)))
    # The antiparallel fallback axis â × e, e the basis vector of â's smallest component.
    # (A comparison, not an indexed row of eye(3): a gather has no sharding JAX can infer for an
    # input sharded with explicit axis types.)
    smallest = jnp.argmin(jnp.abs(a_unit), axis=-1, keepdims=True)
    basis = (smallest == _axis_numbers(smallest.ndim)).astype(a.dtype)
    fallback = cross(a_unit, basis)
    fallback = fallback / jnp.sqrt(sum_squares(fallback, keepdims=True))
    axis = jnp.where(has_axis, c_perp / s, fallback)
    half = 0.5 * jnp.arctan2(jnp.where(has_axis, s, jnp.zeros_like(s)), cosine)
    # half ∈ [π/4, π/2]; cos(fl(π)/2) is −4e-8 in float32, so w is kept ≥ 0 as documented.
    obtuse = jnp.concatenate([jnp.maximum(jnp.cos(half), 0.0), jnp.sin(half) * axis], axis=-1)
    return jnp.where(acute, bisector, obtuse)
