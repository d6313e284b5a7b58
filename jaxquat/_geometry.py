"""Geometry of the rotation group on unit quaternions: distance, interpolation, averaging, sampling.

Quaternions are `(..., 4)` arrays (w, x, y, z); q and −q are the same rotation, and every function here
that returns a *rotation* (rather than a point on the sphere) says how it treats the sign.
"""

from __future__ import annotations

import math
import operator

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, ArrayLike

from ._algebra import canonical_sign, conjugate, exp, log, multiply
from ._numerics import (
    as_float_array,
    broadcast_batch,
    check_float_dtype,
    check_shape,
    check_trailing,
    cross,
    eager_jit,
    is_tracer,
    prescale,
    scaled_norm,
    sum_squares,
    top_eigenvector,
    unit_vector,
)
from ._rotation import from_rotvec, to_rotvec


@eager_jit()
def angle_between(p: ArrayLike, q: ArrayLike) -> Array:
    r"""The geodesic angle θ ∈ [0, π] of the rotation taking `p` to `q`.

    $θ = 2\operatorname{atan2}(|\operatorname{vec}(p^* q)|, |w(p^* q)|)$ (never an arccos): sign-invariant (p, −p and q,
    −q give the same θ), scale-invariant (inputs need not be unit), and accurate to round-off for
    tiny angles, where $2\arccos|⟨p, q⟩|$ floors at ~2e-8 rad (docs/numerics.md §4). XLA:CPU reads
    subnormal components as 0: such a component is lost (float32 (2e-38, 5e-39, 0, 0) is 0 rad from
    the identity, not 0.49), and an all-subnormal input gives NaN.

    **Arguments:**

    - `p`, `q`: quaternions, shape `(..., 4)`; leading axes broadcast.

    **Returns:** angles in radians, shape `(...)`.

    **Gradient:** θ is a cone |δ| at p = q and has a ridge at θ = π; elsewhere smooth.
    At p = q exactly the gradient is 0 (the minimum-norm subgradient; safe norm, no NaN);
    at θ = π the one-sided derivative of |w| is taken (sign of w, 0 at w = 0). Because θ itself is
    not differentiable at p = q, neither is any function of it by the chain rule: `angle_between(p,
    q)**2` has gradient 0 there but *Hessian 0* instead of 2·I. For a smooth squared angle (losses,
    Newton steps, curvature at the optimum) use `jnp.sum(to_rotvec(multiply(conjugate(p), q))**2,
    axis=-1)` with unit p, q: the same value, Hessian 2·I at p = q.
    """
    p = check_trailing(p, 4, "p")
    q = check_trailing(q, 4, "q")
    p, q = broadcast_batch((p, 1, "p"), (q, 1, "q"))
    # Unit first: with |p| ≫ |q| the difference below would swamp q in rounding. (Through
    # `unit_vector`: |p|² of a float32 p of length 1e20 overflows, and gave θ = 0 for any q.)
    p_given, q_given = p, q
    p = unit_vector(p)
    q = unit_vector(q)
    w = jnp.sum(p * q, axis=-1)  # w(p* q) = ⟨p, q⟩
    # vec(p* q) = p_w q_v − q_w p_v − p_v × q_v, written in the difference d = ±q − p (sign of ⟨p, q⟩):
    # p_w d_v − d_w p_v − p_v × d_v. Exactly 0 when q = ±p (the product form is not, once the
    # compiler contracts it into fused multiply-adds), and free of cancellation for tiny angles.
    sign = jnp.where(w < 0, -1.0, 1.0).astype(q.dtype)[..., None]
    d = sign * q - p
    # d is exactly 0 for q = ±p only if XLA normalised p and q with the same instructions; for some
    # shapes it fuses the two differently (one float32 quaternion gave θ(q, q) = 5e-8 rad, a batch of
    # two exactly 0). Inputs equal up to sign are therefore matched as given.
    d = jnp.where(jnp.all(sign * q_given == p_given, axis=-1, keepdims=True), 0.0, d)
    vector = p[..., :1] * d[..., 1:] - d[..., :1] * p[..., 1:] - cross(p[..., 1:], d[..., 1:])
    # |w| as w·sign(w): the same value, and the derivative sign(w), 0 at w = 0 (θ = π), where
    # `jnp.abs` would take the one-sided 1.
    # |vector| prescaled: its square underflows for angles below ~2e-19 rad in float32 (~3e-154 in
    # float64), which gave θ = 0.
    return 2.0 * jnp.arctan2(scaled_norm(vector), w * jnp.sign(w))


@eager_jit()
def slerp(p: ArrayLike, q: ArrayLike, t: ArrayLike) -> Array:
    r"""Spherical linear interpolation along the shortest arc: $p \exp(t \log(p^* q))$.

    Computed as `p ⊗ from_rotvec(t · to_rotvec(p* ⊗ q))`: constant angular velocity, the relative
    rotation taken the short way round (|angle| ≤ π), so q and −q give the same path. At t = 0 the
    result is exactly `p`; at t = 1 it is q or −q (whichever is nearer p). `t` outside [0, 1]
    extrapolates along the same geodesic. (Shoemake 1985, "Animating rotation with quaternion curves".)

    **Arguments:**

    - `p`, `q`: unit quaternions, shape `(..., 4)`.
    - `t`: interpolation parameter, shape `(...)`; all leading axes broadcast.

    **Returns:** unit quaternions, shape `(..., 4)`.

    **Gradient:** smooth at p = ±q (series-switched `to_rotvec` / `from_rotvec`); the path jumps
    where the relative rotation is exactly a half-turn (two shortest arcs).
    """
    p = check_trailing(p, 4, "p")
    q = check_trailing(q, 4, "q")
    t = as_float_array(t, "t")
    p, q, t = broadcast_batch((p, 1, "p"), (q, 1, "q"), (t, 0, "t"))
    relative = to_rotvec(multiply(conjugate(p), q))
    return multiply(p, from_rotvec(t[..., None] * relative))


@eager_jit()
def squad(p: ArrayLike, a: ArrayLike, b: ArrayLike, q: ArrayLike, t: ArrayLike) -> Array:
    r"""Shoemake's spherical quadrangle interpolation between `p` (t = 0) and `q` (t = 1).

    $\operatorname{squad}(p, a, b, q; t) = \operatorname{slerp}(\operatorname{slerp}(p, q; t),
    \operatorname{slerp}(a, b; t); 2t(1-t))$ with inner control points `a`, `b`. With the control
    points of `squad_control_points` on a sequence of key orientations the piecewise curve is C¹:
    its angular velocity is continuous at the keys. (Shoemake 1987, "Quaternion calculus and fast
    animation", SIGGRAPH course notes; Eberly, "Quaternion algebra and calculus".)

    Signs: q is taken on p's side (⟨p, q⟩ ≥ 0), a on p's and b on q's, once per segment; each of the
    three interpolations then follows the great arc of the unit sphere between its two ends, as in
    Shoemake's formula, without choosing the short way again at every t (which flipped the curve by
    a half-turn mid-segment once the keys were more than ~90° apart). The curve therefore depends
    only on the rotations, not on the signs of the four quaternions.

    **Arguments:**

    - `p`, `q`: the key orientations at t = 0 and t = 1, shape `(..., 4)`.
    - `a`, `b`: the inner control points of the segment, shape `(..., 4)`.
    - `t`: shape `(...)`; everything broadcasts.

    **Returns:** unit quaternions, shape `(..., 4)`.
    """
    p = check_trailing(p, 4, "p")
    a = check_trailing(a, 4, "a")
    b = check_trailing(b, 4, "b")
    q = check_trailing(q, 4, "q")
    t = as_float_array(t, "t")
    p, a, b, q, t = broadcast_batch((p, 1, "p"), (a, 1, "a"), (b, 1, "b"), (q, 1, "q"), (t, 0, "t"))
    # Signs fixed once per segment (q on p's side, a on p's, b on q's): the curve is then sign-
    # invariant, and each interpolation follows the great arc of S³ between its ends as they are,
    # with no per-t choice of the short way. (The outer `slerp` made that choice at every t, and
    # flipped the curve by a half-turn mid-segment where the two inner curves passed π apart as
    # rotations: half of all segments between keys 120° apart.)
    q = jnp.where(jnp.sum(p * q, axis=-1, keepdims=True) < 0, -q, q)
    a = jnp.where(jnp.sum(p * a, axis=-1, keepdims=True) < 0, -a, a)
    b = jnp.where(jnp.sum(q * b, axis=-1, keepdims=True) < 0, -b, b)
    return _arc(_arc(p, q, t), _arc(a, b, t), 2.0 * t * (1.0 - t))


def _arc(p: Array, q: Array, t: Array) -> Array:
    """p ⊗ exp(t · vec log(p* ⊗ q)): the great arc of S³ from p to q as given (up to a full turn as a
    rotation; no short-way fold)."""
    half = log(multiply(conjugate(p), q))[..., 1:]
    pure = jnp.concatenate([jnp.zeros_like(half[..., :1]), t[..., None] * half], axis=-1)
    return multiply(p, exp(pure))


@eager_jit()
def squad_control_points(previous: ArrayLike, current: ArrayLike, following: ArrayLike) -> Array:
    r"""The inner `squad` control point at the key `current` between its neighbours.

    $s = q \exp\!\big(-\tfrac14(\log(q^* q_{+}) + \log(q^* q_{-}))\big)$, with the relative rotations
    taken the short way round, so the keys' signs do not matter.

    **Arguments:**

    - `previous`, `current`, `following`: unit quaternions $q_-$, $q$, $q_+$, shape `(..., 4)`.

    **Returns:** the control point, shape `(..., 4)`. Segment i of a spline through keys qᵢ is
    `squad(q[i], s[i], s[i + 1], q[i + 1], t)` with `s[i] = squad_control_points(q[i-1], q[i], q[i+1])`.
    """
    previous = check_trailing(previous, 4, "previous")
    current = check_trailing(current, 4, "current")
    following = check_trailing(following, 4, "following")
    previous, current, following = broadcast_batch(
        (previous, 1, "previous"), (current, 1, "current"), (following, 1, "following")
    )
    inverse = conjugate(current)
    forward = to_rotvec(multiply(inverse, following))
    backward = to_rotvec(multiply(inverse, previous))
    return multiply(current, from_rotvec(-0.25 * (forward + backward)))


@eager_jit()
def canonicalize(q: ArrayLike) -> Array:
    """The representative of ±q with w ≥ 0 (ties at w = 0 broken like SciPy: first non-zero of x, y, z
    positive).

    Use it only for sign-invariant outputs (display, hashing, comparison), never inside an integrator
    or an interpolation (the sign jumps where w changes sign). Gradient: ±identity, by the locally
    constant sign.

    **Arguments:** `q`, shape `(..., 4)`. **Returns:** shape `(..., 4)`.
    """
    return canonical_sign(check_trailing(q, 4, "q"))


def random(key: Array, shape: int | tuple[int, ...] = (), dtype=None) -> Array:
    """Unit quaternions distributed uniformly (Haar measure) on the rotation group.

    A 4-D standard Gaussian is rotation-invariant, so its direction is uniform on the 3-sphere, which
    is the Haar measure on SO(3) (Shoemake 1992, "Uniform random rotations", Graphics Gems III). The
    rotation angle θ then has density (1 − cos θ)/π on [0, π].

    **Arguments:**

    - `key`: one `jax.random` key: `jax.random.key(seed)`, or a legacy `jax.random.PRNGKey(seed)`
      (uint32 key data). For a batch of keys use `jax.vmap` (or one key and a batch `shape`).
    - `shape`: batch shape: a non-negative int or a tuple of them.
    - `dtype`: floating dtype; defaults to JAX's default float.

    **Returns:** shape `(*shape, 4)`, not sign-canonicalised (uniform on the whole sphere).

    **Raises:** `ValueError` for anything but one key, a negative / non-integer `shape` or a
    non-floating `dtype`.
    """
    key = _check_key(key, "key")
    shape = check_shape(shape, "shape")
    dtype = check_float_dtype(dtype, "dtype")
    x = jax.random.normal(key, shape + (4,), dtype=dtype)
    return x / jnp.sqrt(sum_squares(x, keepdims=True))


def _check_key(key, name: str):
    """`key` as one typed `jax.random` key, or a ValueError naming `name` (JAX's own errors for a seed,
    a float array or a batch of keys are TypeErrors about key data)."""
    what = f"shape {tuple(key.shape)}, dtype {key.dtype}" if hasattr(key, "dtype") else repr(key)
    if hasattr(key, "dtype") and jax.dtypes.issubdtype(key.dtype, jax.dtypes.prng_key):
        typed = key
    else:
        try:
            typed = jax.random.wrap_key_data(jnp.asarray(key))
        except (TypeError, ValueError) as e:
            raise ValueError(
                f"`{name}` must be a jax.random key (jax.random.key(seed), or the uint32 key data of "
                f"jax.random.PRNGKey(seed)); got {what}."
            ) from e
    if typed.shape != ():
        raise ValueError(
            f"`{name}` must be one key; got a batch of keys ({what}). Use jax.vmap over keys, or "
            "one key with a batch `shape`."
        )
    return typed


def mean(
    q: ArrayLike, weights: ArrayLike | None = None, *, axis: int | tuple[int, ...] | None = None
) -> Array:
    r"""The chordal L2 mean of rotations (Markley et al. 2007), as SciPy's `Rotation.mean`.

    The unit quaternion maximising $\sum_i w_i ⟨q_i, \bar q⟩^2$, i.e. the top eigenvector of
    $M = \sum_i w_i q_i q_i^\top$. It minimises the weighted sum of squared chordal (Frobenius)
    distances between rotation matrices, and is sign-invariant: each qᵢ may be replaced by −qᵢ.

    **Arguments:**

    - `q`: quaternions, shape `(..., 4)`; need not be unit (each is normalised first, as SciPy's
      `Rotation` does, so a quaternion's length does not weight it; any finite non-zero length the
      dtype holds). XLA:CPU reads subnormal components as 0: they are lost, and a quaternion whose
      components are all subnormal makes the mean NaN.
    - `weights`: optional non-negative weights, broadcastable to `q.shape[:-1]` (a negative, NaN or
      infinite weight is a `ValueError`, except under `jit`, where it cannot be seen: a negative
      weight then gives a meaningless result, a non-finite one NaN).
      Weights that sum to zero over the averaged axes leave nothing to average: a `ValueError`, and
      NaN under `jit` (SciPy returns the identity).
    - `axis`: the batch axes to average over: `None` (all, SciPy's default), an int or a tuple (each
      axis once). They must hold at least one quaternion (else `ValueError`).

    **Returns:** the mean rotation, w ≥ 0 (it is a sign-invariant output), shape of the batch axes
    that were not averaged + `(4,)`.

    **Gradient:** by perturbation theory of the top eigenvalue of M (finite at coincident rotations);
    undefined when that eigenvalue is degenerate (no unique mean, e.g. two rotations a half-turn apart).
    """
    q = check_trailing(q, 4, "q")
    batch_ndim = q.ndim - 1
    if axis is None:
        axis = tuple(range(batch_ndim))
    elif _is_int(axis):
        axis = (axis,)
    if not isinstance(axis, tuple) or not all(_is_int(n) for n in axis):
        raise ValueError(f"`axis` must be None, an int or a tuple of ints; got {axis!r}.")
    axis = tuple(operator.index(n) for n in axis)
    if any(not -batch_ndim <= n < batch_ndim for n in axis):
        raise ValueError(
            f"`axis` {axis} is out of range for the batch shape {tuple(q.shape[:-1])} of `q`."
        )
    if len({n % batch_ndim for n in axis}) < len(axis):
        raise ValueError(f"`axis` {axis} repeats an axis (as in NumPy, each may appear once).")
    axis = tuple(sorted(n % batch_ndim for n in axis))
    count = math.prod(q.shape[n] for n in axis)
    if count == 0:
        raise ValueError(
            "at least one quaternion is needed to take a mean: the averaged axes "
            f"{axis} of `q` (shape {tuple(q.shape)}) are empty."
        )
    q = unit_vector(q)  # (|q|² of a float32 q of length 1e25 overflows)
    outer = q[..., :, None] * q[..., None, :]
    if weights is not None:
        weights = as_float_array(weights, "weights")
        given = None if is_tracer(weights) else np.asarray(weights)
        if given is not None:  # the index in the weights as given, before broadcasting
            bad = ~(np.isfinite(given) & (given >= 0))  # NaN is bad (SciPy: LinAlgError)
            if bad.any():
                index = tuple(int(i) for i in np.argwhere(bad)[0])
                raise ValueError(
                    "`weights` must be finite and non-negative (as for SciPy's `Rotation.mean`); "
                    f"got {given[index]} at index {index}."
                )
        try:
            weights = jnp.broadcast_to(weights, q.shape[:-1])
        except ValueError as e:
            raise ValueError(
                f"`weights` must broadcast to the batch shape {tuple(q.shape[:-1])} of `q`; "
                f"got shape {tuple(weights.shape)}."
            ) from e
        # The mean does not depend on the weights' scale: brought into range by a power of two over
        # the averaged axes (float64 weights of 1e308 overflowed the moment, and gave (0, 0, 0, 1)).
        weights = prescale(weights, axes=axis)[0]
        total = jnp.sum(weights, axis=axis)
        if not is_tracer(weights) and bool(jnp.any(total == 0)):
            values = np.asarray(total)
            index = tuple(int(i) for i in np.argwhere(values == 0)[0])
            where = f" (batch index {index} of the mean)" if index else ""
            nonzero = np.any(np.broadcast_to(given, q.shape[:-1]) != 0, axis=axis)[index]
            why = (
                f"they are all below the smallest normal number {np.finfo(given.dtype).tiny:.3g} "
                "of their dtype, which XLA on the CPU reads as 0: scale them up"
                if nonzero
                else "there is nothing to average, and no mean rotation"
            )
            raise ValueError(f"`weights` sum to zero over the averaged axes {axis}{where}: {why}.")
        outer = weights.astype(q.dtype)[..., None, None] * outer
    moment = jnp.sum(outer, axis=axis)
    if weights is not None:
        # Zero total weight (seen only under jit): NaN rather than an arbitrary eigenvector of 0,
        # with the identity's moment in its place so that its eigenvector derivative (which divides
        # by the eigenvalue gap, 0 here) sends no NaN into the other means' gradients.
        empty = (total == 0)[..., None, None]
        identity = jnp.zeros((4, 4), moment.dtype).at[0, 0].set(1.0)
        moment = jnp.where(empty, jnp.broadcast_to(identity, moment.shape), moment)
    result = top_eigenvector(moment)
    result = jnp.where(result[..., :1] < 0, -result, result)
    if weights is not None:
        result = jnp.where(empty[..., 0], jnp.nan, result)
    return result


def _is_int(n) -> bool:
    """An integer of any kind (Python, NumPy), not a bool (`True` is not axis 1)."""
    return isinstance(n, (int, np.integer)) and not isinstance(n, (bool, np.bool_))


def check_unit(q: ArrayLike, *, atol: float | None = None) -> Array:
    """Return `q` unchanged, raising at run time if some |q| differs from 1 by more than `atol`.

    Opt-in value check (jaxquat's functions do not inspect values otherwise) built on
    `equinox.error_if`: works eagerly and under `jit`, `vmap` and autodiff (derivative: the
    identity). A failing check raises at run time an error whose message contains "not unit"
    (`equinox.EquinoxRuntimeError` eagerly; through XLA's callback machinery under `jax.jit`, a
    `jax.errors.JaxRuntimeError` or `ValueError`). NaN norms fail too.

    **Arguments:**

    - `q`: quaternions, shape `(..., 4)`.
    - `atol`: tolerance on |q| − 1, a finite number ≥ 0 (a Python or NumPy scalar); default √ε of
      the dtype (1.5e-8 float64, 3.5e-4 float32).

    **Returns:** `q`.
    """
    q = check_trailing(q, 4, "q")
    if atol is None:
        atol = float(jnp.finfo(q.dtype).eps) ** 0.5
    elif not (
        isinstance(atol, (int, float, np.integer, np.floating))
        and not isinstance(atol, (bool, np.bool_))
        and math.isfinite(atol)
        and atol >= 0
    ):
        raise ValueError(f"`atol` must be a finite non-negative number; got {atol!r}.")
    deviation = jnp.abs(jnp.sqrt(sum_squares(q)) - 1.0)
    return eqx.error_if(
        q, ~(deviation <= atol), f"`q` is not unit: |q| - 1 exceeds atol={atol:.3g}."
    )
