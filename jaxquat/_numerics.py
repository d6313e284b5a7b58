"""Safe numerics shared by every jaxquat module.

Everything that is singular (or loses precision) at a point lives here: a norm with a usable gradient
at zero, and the coefficient functions of the exponential map written as functions of the *squared*
angle, switched to a Taylor series in θ² near zero behind a double `jnp.where` (mask the input before
the unsafe operation, select after; docs/numerics.md §4).  Other modules never write their own guard.

Also here: input validation helpers that raise a `ValueError` at trace time naming the argument.
"""

from __future__ import annotations

import functools
import inspect
import operator
from collections.abc import Callable, Sequence

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, ArrayLike

# Below these values of θ² the series (terms through θ⁶) is used.  The first dropped term is then
# below 1e-17 (float64) / 1e-10 (float32) relative, i.e. round-off, and the direct formula is still
# accurate (value and gradient) just above the switch.
_SERIES_THRESHOLD = {
    jnp.dtype("float64"): 1e-3,
    jnp.dtype("float32"): 1e-2,
    jnp.dtype("float16"): 1e-1,
}


def default_float_dtype() -> jnp.dtype:
    """The dtype `jnp.asarray(1.0)` has: float64 when `jax_enable_x64` is on, else float32."""
    return jnp.asarray(1.0).dtype


def series_threshold(dtype) -> float:
    """Value of θ² below which the coefficient functions switch to their series (per dtype)."""
    return _SERIES_THRESHOLD.get(jnp.dtype(dtype), 1e-2)


def as_float_array(x: ArrayLike, name: str = "x") -> Array:
    """`jnp.asarray(x)`, promoting integer / bool input to the default float dtype, weakly typed.

    Floating input keeps its dtype (float32 in → float32 out). Integers become a weakly typed float,
    as a Python float would be, so `slerp(p32, q32, 1)` stays float32 when x64 is on (as
    `p32 * jnp.asarray(1)` does); a strong float64 would have widened the float32 operands. `None`,
    strings, ragged nested lists and other non-numeric input raise a `ValueError` naming the
    argument.
    """
    if x is None:
        raise ValueError(f"`{name}` must be an array of numbers; got None.")
    try:
        x = jnp.asarray(x)
    except (TypeError, ValueError) as e:
        raise ValueError(
            f"`{name}` must be an array of numbers; got {type(x).__name__} that is not one "
            f"(a number, a rectangular nested list or an array is expected): {e}"
        ) from e
    if not jnp.issubdtype(x.dtype, jnp.floating):
        if jnp.issubdtype(x.dtype, jnp.complexfloating):
            raise ValueError(f"`{name}` must be real; got dtype {x.dtype}.")
        # `x * 1.0`: JAX's promotion of any integer with a Python float is the weakly typed default
        # float (`astype` would make it strong), under the standard promotion rules (a user's
        # "strict" mode refuses it), from at least 8 bits (int4 does not promote).
        if jnp.issubdtype(x.dtype, jnp.integer) and jnp.iinfo(x.dtype).bits < 8:
            x = x.astype(jnp.int8 if jnp.issubdtype(x.dtype, jnp.signedinteger) else jnp.uint8)
        with jax.numpy_dtype_promotion("standard"):
            x = x * 1.0
    return x


def integer_value(value) -> int | None:
    """`value` as a Python int if it is an integer of any kind (Python, NumPy, a concrete JAX
    scalar), else `None`: bools (`True` is not a count), floats, arrays and traced values."""
    if isinstance(value, (bool, np.bool_)):
        return None
    try:
        return operator.index(value)
    except TypeError:  # (a tracer's TracerIntegerConversionError is one)
        return None


def check_shape(shape, name: str = "shape") -> tuple[int, ...]:
    """Validate a batch-shape argument: a non-negative int or a tuple/list of them → a tuple of ints.

    Integers of any kind (Python, NumPy) are accepted; bools, floats, `None` and negative sizes raise a
    `ValueError` naming the argument.
    """

    def size(n) -> int:
        n = integer_value(n)
        if n is None or n < 0:
            raise TypeError
        return n

    try:
        if isinstance(shape, (tuple, list)):
            return tuple(size(n) for n in shape)
        return (size(shape),)
    except TypeError:
        raise ValueError(
            f"`{name}` must be a non-negative int or a tuple of non-negative ints; got {shape!r}."
        ) from None


def check_float_dtype(dtype, name: str = "dtype") -> jnp.dtype:
    """Validate a `dtype=` argument: `None` (JAX's default float) or a floating dtype."""
    if dtype is None:
        return default_float_dtype()
    try:
        resolved = jnp.dtype(dtype)
    except (TypeError, ValueError):
        resolved = None
    if resolved is None or not jnp.issubdtype(resolved, jnp.floating):
        raise ValueError(f"`{name}` must be a float dtype (e.g. jnp.float32); got {dtype!r}.")
    return resolved


def broadcasts_to(shape: tuple[int, ...], target: tuple[int, ...]) -> bool:
    """Whether an array of `shape` broadcasts to `target` without adding or growing axes of it."""
    try:
        return np.broadcast_shapes(tuple(shape), tuple(target)) == tuple(target)
    except ValueError:
        return False


def check_trailing(x: ArrayLike, size: int, name: str) -> Array:
    """Convert `x` to a float array and check that its last axis has `size` entries.

    Raises a `ValueError` naming the argument, the expected and the received shape.
    """
    x = as_float_array(x, name)
    if x.ndim == 0 or x.shape[-1] != size:
        raise ValueError(f"`{name}` must have shape (..., {size}); got shape {tuple(x.shape)}.")
    return x


def check_matrix(x: ArrayLike, name: str) -> Array:
    """Convert `x` to a float array of shape `(..., 3, 3)` or raise a `ValueError`."""
    x = as_float_array(x, name)
    if x.ndim < 2 or x.shape[-2:] != (3, 3):
        raise ValueError(f"`{name}` must have shape (..., 3, 3); got shape {tuple(x.shape)}.")
    return x


def check_choice(value, choices: Sequence[str], name: str) -> str:
    """Check that `value` is one of the strings `choices` (raises a `ValueError` naming `name`)."""
    if not isinstance(value, str) or value not in choices:
        expected = ", ".join(repr(c) for c in choices)
        raise ValueError(f"`{name}` must be one of {expected}; got {value!r}.")
    return value


def check_callable(fn, name: str, call: str, num_args: int) -> None:
    """Check that `fn` is callable with `num_args` positional arguments, as `call` (e.g.
    "omega(t, q)"); a `ValueError` naming `name` otherwise. Callables whose signature Python cannot
    read (some builtins) pass the arity check."""
    if not callable(fn):
        raise ValueError(f"`{name}` must be a callable {call}; got {type(fn).__name__}.")
    try:
        signature = inspect.signature(fn)
    except (TypeError, ValueError):
        return
    try:
        signature.bind(*([None] * num_args))
    except TypeError:
        raise ValueError(
            f"`{name}` must be callable as {call} ({num_args} positional argument"
            f"{'s' if num_args != 1 else ''}); its signature is {signature}."
        ) from None


def reusable_callable(function, *, by_identity: bool = False) -> bool:
    """Whether a compiled run that calls `function` (an ω, a torque, a shape; or None) may be cached
    and reused at later calls, keyed as `equinox.filter_jit` keys it: by its PyTree structure and
    its leaves that are not JAX arrays (`static_key`).

    Always for None, and for an `equinox.Module` whose key hashes and that holds no NumPy array or
    scalar: a Module is immutable and its JAX arrays are traced, so new values reuse the program.
    Never for a callable whose key does not hash (a JIT cache cannot hold it) or that holds NumPy
    values (they would be traced, and the callable may call NumPy on them). Any other callable (a
    function, a bound method, a `functools.partial`) only `by_identity`: `jax.jit`'s rule, under
    which the first call's program is replayed, so state the callable reads (a global gain, an
    attribute set to a tracer of an outer `jax.grad`) is read once; without `by_identity` such a run
    is traced again at each call."""
    if function is None:
        return True
    leaves = jax.tree_util.tree_leaves(function)
    if any(isinstance(leaf, (np.ndarray, np.generic)) for leaf in leaves):
        return False  # (NumPy values would be traced: the callable may call NumPy on them)
    if not (by_identity or isinstance(function, eqx.Module)):
        return False
    try:
        hash(static_key(function))
    except TypeError:
        return False
    return True


def static_key(tree) -> tuple:
    """The PyTree structure of `tree` and its leaves that are not arrays (None in the arrays' places):
    what a JIT cache keys a callable on when its arrays are traced (`equinox.filter_jit`'s rule).
    Hashable where those leaves are, whatever containers (lists, dicts) hold them."""
    leaves, structure = jax.tree_util.tree_flatten(tree)
    return structure, tuple(None if eqx.is_array(leaf) else leaf for leaf in leaves)


def check_frame(frame) -> str:
    """Validate a `frame=` argument: `"world"` or `"body"`."""
    return check_choice(frame, ("world", "body"), "frame")


def broadcast_batch(*named: tuple) -> tuple[Array, ...]:
    """Broadcast the leading (batch) axes of arrays whose trailing `k` axes are their own.

    Each argument is `(array, k)` or `(array, k, name)` where the last `k` axes are the element shape.
    Raises a `ValueError` naming the arguments (where given) when the batch shapes are incompatible.
    """
    batch_shapes = [item[0].shape[: item[0].ndim - item[1]] for item in named]
    try:
        batch = np.broadcast_shapes(*batch_shapes)
    except ValueError as e:
        parts = [
            (
                f"`{item[2]}` has shape {tuple(item[0].shape)}"
                if len(item) > 2
                else f"shape {tuple(item[0].shape)}"
            )
            for item in named
        ]
        raise ValueError(f"leading (batch) axes do not broadcast: {'; '.join(parts)}.") from e
    return tuple(
        jnp.broadcast_to(item[0], batch + item[0].shape[item[0].ndim - item[1] :]) for item in named
    )


def sum_squares(x: Array, axis: int = -1, keepdims: bool = False) -> Array:
    """Σ x², the smooth squared norm (use it instead of `norm(x)**2`)."""
    return jnp.sum(x * x, axis=axis, keepdims=keepdims)


def unit_vector(x: Array) -> Array:
    """x/|x| along the last axis for vectors of any magnitude the dtype holds: an x whose |x|² would
    overflow or underflow is first scaled by an exact power of two (`prescale`), so a float32 vector
    of length 1e20 or 1e-20 has a direction too. Value and derivative are those of x/|x| (the scale
    is held constant: x/|x| does not depend on it); NaN for x = 0.
    """
    x = prescale(x)[0]
    return x / jnp.sqrt(sum_squares(x, keepdims=True))


def _power_of_two(e: Array, dtype) -> tuple[Array, Array]:
    """2^e as two factors that are each representable (2^e alone overflows for e near the dtype's
    exponent range, e.g. 2^148 in float32 to bring a subnormal up to 1)."""
    half = e // 2
    one = jnp.ones((), dtype)
    return jnp.ldexp(one, half), jnp.ldexp(one, e - half)


def prescale(
    x: Array, axes: tuple[int, ...] = (-1,), limit: int | None = None
) -> tuple[Array, Array]:
    """(x·2⁻ᵉ, e): `x` scaled by an exact power of two so that products of its components can neither
    overflow nor underflow, for scale-invariant formulas (normalisation, q v q⁻¹, 2/|q|²).

    e is the binary exponent of the largest |component| over `axes` when that lies outside
    [2⁻ᴸ, 2ᴸ], L = `limit` or a quarter of the dtype's exponent range (float32: 32, float64: 256),
    so that a float32 quaternion of norm 1e20 or 1e-20 is still a rotation; otherwise, and for zero,
    NaN or infinite inputs, e = 0 and `x` is returned bit for bit. `limit=0` always brings the
    largest |component| into [½, 1), for formulas that multiply x by quantities of another scale
    (|q|²·|v| in q v q⁻¹). Powers of two scale exactly: a formula that does not depend on the scale
    gives bit for bit the unscaled result wherever that neither overflows nor underflows. The
    factor is held constant under differentiation: the formulas it feeds do not depend on it.
    """
    limit = jnp.finfo(x.dtype).maxexp // 4 if limit is None else limit
    big = jax.lax.stop_gradient(jnp.max(jnp.abs(x), axis=axes, keepdims=True))
    _, e = jnp.frexp(big)
    ordinary = ~jnp.isfinite(big) | (big == 0) | (jnp.abs(e) <= limit)
    e = jnp.where(ordinary, jnp.zeros_like(e), e)
    down1, down2 = _power_of_two(-e, x.dtype)
    return x * down1 * down2, jnp.squeeze(e, axis=axes)


def power_of_two_times(y: Array, e: Array) -> Array:
    """y·2ᵉ exactly (the inverse of `prescale`'s factor; `e` broadcasts against `y`)."""
    up1, up2 = _power_of_two(e, y.dtype)
    return y * up1 * up2


def scaled_norm(x: Array) -> Array:
    """|x| over the last axis for any finite x the dtype holds (|x|² would overflow or underflow:
    x is scaled by an exact power of two first, `prescale`); gradient 0 at x = 0 (`safe_norm`)."""
    x, e = prescale(x)
    return power_of_two_times(safe_norm(x), e)


def safe_norm(x: Array, axis: int = -1, keepdims: bool = False) -> Array:
    """Euclidean norm whose gradient at `x = 0` is 0 instead of NaN.

    Value: |x| everywhere (NaN if `x` contains NaN). Gradient: x/|x| for x ≠ 0 and exactly 0 at x = 0
    (the norm is not differentiable there; 0 is the minimum-norm subgradient).
    """
    sq = sum_squares(x, axis=axis, keepdims=keepdims)
    # `~(sq <= 0)`, not `sq > 0`: a NaN must take the computing branch (and come out NaN), not be
    # reported as a zero norm.
    nonzero = ~(sq <= 0)
    safe_sq = jnp.where(nonzero, sq, jnp.ones_like(sq))
    return jnp.where(nonzero, jnp.sqrt(safe_sq), jnp.zeros_like(sq))


def _polyval(coeffs: Sequence[float], x: Array) -> Array:
    """Σ coeffs[k] x^k by Horner's rule with Python-float coefficients (keeps x's dtype)."""
    result = jnp.full_like(x, coeffs[-1])
    for c in reversed(coeffs[:-1]):
        result = result * x + c
    return result


def _switched(
    theta_sq: Array, series: Sequence[float], direct: Callable[[Array], Array], threshold=None
) -> Array:
    """Evaluate `direct(θ)` away from 0 and `series` (in θ²) near 0, with NaN-free gradients."""
    theta_sq = jnp.asarray(theta_sq)
    if threshold is None:
        threshold = series_threshold(theta_sq.dtype)
    small = theta_sq < threshold
    safe_sq = jnp.where(small, jnp.full_like(theta_sq, 1.0), theta_sq)
    return jnp.where(small, _polyval(series, theta_sq), direct(jnp.sqrt(safe_sq)))


def cos_half(theta_sq: ArrayLike) -> Array:
    """cos(θ/2) as a function of θ².

    At θ = 0: value 1, derivative w.r.t. θ² is −1/8.
    """
    return _switched(
        theta_sq, (1.0, -1.0 / 8.0, 1.0 / 384.0, -1.0 / 46080.0), lambda t: jnp.cos(0.5 * t)
    )


def sinc_half(theta_sq: ArrayLike) -> Array:
    """sin(θ/2)/θ as a function of θ².

    At θ = 0: value 1/2, derivative w.r.t. θ² is −1/48.
    """
    return _switched(
        theta_sq,
        (0.5, -1.0 / 48.0, 1.0 / 3840.0, -1.0 / 645120.0),
        lambda t: jnp.sin(0.5 * t) / t,
    )


def compensated_add(q: Array, delta: Array, c: Array) -> tuple[Array, Array]:
    """q + δ by Kahan summation with the running compensation `c`: the new (q, c)."""
    y = delta - c
    s = q + y
    return s, (s - q) - y


def cos_half_minus_one(theta_sq: ArrayLike) -> Array:
    """cos(θ/2) − 1 without cancellation, computed as −2 sin²(θ/4) = −(θ²/2)·(2 sin(θ/4)/θ)².

    At θ = 0: value 0, derivative w.r.t. θ² is −1/8.
    """
    theta_sq = jnp.asarray(theta_sq)
    # 2 sin(θ/4)/θ = sin(φ/2)/φ with φ = θ/2, i.e. sinc_half(θ²/4).
    s = sinc_half(0.25 * theta_sq)
    return -0.5 * theta_sq * s * s


def tan_half_over(theta_sq: ArrayLike) -> Array:
    """tan(θ/2)/θ as a function of θ² (the seed's correction factor).

    At θ = 0: value 1/2, derivative w.r.t. θ² is 1/24. Poles at θ = π (mod 2π): there the direct
    formula returns the floating-point value of tan (large but finite, ±1.6e16/θ in float64).
    """
    # The direct form's derivative cancels ((θ/2)sec²(θ/2) − tan(θ/2) ~ θ³/12 from terms ~θ/2: relative
    # error ~6ε/θ²), and ∂/∂Δt of the corrected rate is all of that derivative: switching at the
    # generic θ² = 1e-2 (float32) / 1e-3 (float64) left it 7e-5 / 1.4e-12 wrong just past the switch.
    # Two more series terms let it switch later (the first dropped one, 21844 θ¹²/(6081075·2¹³), is
    # below 2e-6 / 1e-14 relative in the derivative at the switch); measured against mpmath over
    # θ ∈ [1e-12, 3.1]: ∂/∂Δt within 1e-7 (float32) / 1.6e-13 (float64) relative (helper-62).
    theta_sq = jnp.asarray(theta_sq)
    threshold = {jnp.dtype("float64"): 1e-2, jnp.dtype("float32"): 0.5}.get(
        jnp.dtype(theta_sq.dtype), None
    )
    return _switched(
        theta_sq,
        (0.5, 1.0 / 24.0, 1.0 / 240.0, 17.0 / 40320.0, 31.0 / 725760.0, 691.0 / 159667200.0),
        lambda t: jnp.tan(0.5 * t) / t,
        threshold=threshold,
    )


def dexpinv_coeff(theta_sq: ArrayLike) -> Array:
    """c(θ) = (1 − (θ/2)·cot(θ/2))/θ², the coefficient of u×(u×v) in dexp⁻¹_u(v) on so(3).

    At θ = 0: value 1/12, derivative w.r.t. θ² is 1/720. Singular at θ = 2π.
    """

    def direct(t):
        half = 0.5 * t
        return (1.0 - half * jnp.cos(half) / jnp.sin(half)) / (t * t)

    # The direct form cancels (relative error ~ε·12/θ², and its AD derivative ~ε·144/θ⁴: 43 % wrong
    # in float32 at θ² = 1e-2), so this function switches much later, with one more series term
    # (the first dropped one, 691 θ¹⁰/1.3e12, is below 2e-15 / 2e-10 relative at the switch).
    theta_sq = jnp.asarray(theta_sq)
    threshold = 0.05 if theta_sq.dtype == jnp.float64 else 0.5
    return _switched(
        theta_sq,
        (1.0 / 12.0, 1.0 / 720.0, 1.0 / 30240.0, 1.0 / 1209600.0, 1.0 / 47900160.0),
        direct,
        threshold=threshold,
    )


def atan2_over(s_sq: ArrayLike, w: ArrayLike) -> Array:
    """atan2(s, w)/s for s = √(s²) ≥ 0, the coefficient of the logarithm of a quaternion (w, v), s = |v|.

    For w > 0 and small s/w a series in x = s²/w² is used: (1 − x/3 + x²/5 − x³/7 + x⁴/9)/w.
    At s = 0 and w > 0: value 1/w, derivative w.r.t. s² is −1/(3w³). At s = 0 and w ≤ 0 the function is
    singular (atan2(0, −1) = π); the value returned there is π/s evaluated at the masked s = 1, i.e. π,
    finite (`log` and `to_rotvec` handle that point themselves).
    """
    s_sq = jnp.asarray(s_sq)
    w = jnp.asarray(w)
    x_threshold = 1e-4 if s_sq.dtype == jnp.float64 else 1e-2
    # The switch compares s² with w²·threshold (no division, so nothing overflows for tiny w). The
    # series is then evaluated on inputs masked to a harmless point outside its lanes: near a
    # half-turn (w ≈ 0⁺, e.g. float32 cos(π/2) = −4.4e-8 flipped to w ≥ 0) the unmasked x = s²/w²
    # made x⁴ overflow, and the unused branch's inf·0 turned reverse-mode gradients NaN.
    use_series = (w > 0) & (s_sq < x_threshold * (w * w))
    series_w = jnp.where(use_series, w, jnp.ones_like(w))
    x = jnp.where(use_series, s_sq, jnp.zeros_like(s_sq)) / (series_w * series_w)
    safe_s_sq = jnp.where(use_series | (s_sq <= 0), jnp.ones_like(s_sq), s_sq)
    s = jnp.sqrt(safe_s_sq)
    direct = jnp.arctan2(jnp.where(s_sq <= 0, jnp.zeros_like(s), s), w) / s
    series = _polyval((1.0, -1.0 / 3.0, 1.0 / 5.0, -1.0 / 7.0, 1.0 / 9.0), x) / series_w
    return jnp.where(use_series, series, direct)


def cross(a: Array, b: Array) -> Array:
    """Cross product over the last axis with explicit broadcasting of leading axes."""
    a0, a1, a2 = a[..., 0], a[..., 1], a[..., 2]
    b0, b1, b2 = b[..., 0], b[..., 1], b[..., 2]
    return jnp.stack([a1 * b2 - a2 * b1, a2 * b0 - a0 * b2, a0 * b1 - a1 * b0], axis=-1)


def is_tracer(x) -> bool:
    """True when `x` is an abstract value under a JAX transformation."""
    return isinstance(x, jax.core.Tracer)


def _jit_argument(x) -> bool:
    """True for an argument `jax.jit` takes as one concrete array exactly as `jnp.asarray` would: a
    concrete JAX array, a NumPy array or scalar of numbers, a Python number, or None."""
    if x is None or isinstance(x, (bool, int, float, complex)):
        return True
    if is_tracer(x):
        return False
    if isinstance(x, jax.Array):
        return True
    return isinstance(x, (np.ndarray, np.generic)) and x.dtype.kind in "biufc"


def eager_jit(static_argnames: Sequence[str] = ()) -> Callable[[Callable], Callable]:
    """Decorator: run a public function as one compiled XLA program when it is called eagerly.

    Called op by op, a function of a few dozen `jax.numpy` operations dispatches (and on first use
    compiles) each of them: 0.6-9.7 ms a call on 7 quaternions on a 2-core CPU, and up to 3 s for the
    first call with a new shape. Compiled whole it is one dispatch (30-100 µs) and one compilation
    (0.1-0.9 s; README, "What is inside").
    Inside a transformation (`jit`, `grad`, `vmap`: any argument a tracer) the function runs as
    written, so traced programs are unchanged. Arguments jit would not take as the same array (lists,
    strings, objects) also run it as written, and so does a call whose compilation raises: a bad
    argument's `ValueError` is then raised by the function's own checks, exactly as without this
    decorator (message, traceback and no JAX notes). Static arguments (strings naming a frame or an
    axis sequence) must be strings. Functions whose checks depend on values, not only on shapes and
    dtypes (`mean`, `check_unit`, those that inspect concrete masses or times), are not wrapped.
    """
    static = tuple(static_argnames)

    def decorate(function: Callable) -> Callable:
        compiled = jax.jit(function, static_argnames=static)
        names = list(inspect.signature(function).parameters)

        def takes(name, value) -> bool:
            return isinstance(value, str) if name in static else _jit_argument(value)

        @functools.wraps(function)
        def wrapper(*args, **kwargs):
            # (Too many arguments or an unknown keyword: the call as written raises Python's error.)
            pairs = [*zip(names, args, strict=False), *kwargs.items()]
            if len(args) <= len(names) and all(n in names and takes(n, v) for n, v in pairs):
                try:
                    return compiled(*args, **kwargs)
                except Exception:  # bad input: raised below as without compilation (see above)
                    pass
            return function(*args, **kwargs)

        wrapper.compiled = compiled  # (for tests: its `_cache_size()` counts the compilations)
        return wrapper

    return decorate


def safe_atan2(y: Array, x: Array) -> Array:
    """atan2(y, x) whose gradient at (0, 0) is 0 instead of NaN.

    Value: `jnp.arctan2(y, x)` everywhere (0 at the origin, NaN if x or y is NaN). Gradient:
    (x, −y)/(x² + y²) away from the origin; at the origin (where atan2 is discontinuous) exactly 0.
    """
    nonzero = ~((x * x + y * y) <= 0)
    safe_x = jnp.where(nonzero, x, jnp.ones_like(x))
    safe_y = jnp.where(nonzero, y, jnp.zeros_like(y))
    return jnp.where(nonzero, jnp.arctan2(safe_y, safe_x), jnp.zeros_like(x))


@functools.partial(jax.custom_jvp, nondiff_argnums=(1,))
def _top_eigenvector(k: Array, davenport: bool = False) -> Array:
    """The unit eigenvector of the largest eigenvalue of symmetric matrices `k` of shape `(..., n, n)`.

    Value from `jnp.linalg.eigh` (its sign is arbitrary; callers fix it), or with `davenport` from
    power steps (`_davenport_power`) when they are proven converged for every matrix of the batch.
    Derivative by first-order perturbation theory, dv = (λI − K)⁺ dK v, computed as the solve
    (λI − K + v vᵀ) dv = (I − v vᵀ) dK v. Unlike differentiating `eigh` itself, this involves only the
    gaps to the *largest* eigenvalue, so it is finite (and NaN-free in reverse mode) when the other
    eigenvalues are degenerate — e.g. the eigenvalues (3, −1, −1, −1) of Davenport's matrix of an exact
    rotation. Requires the largest eigenvalue to be simple.
    """
    return _power_or_eigh_top(k) if davenport else _eigh_top(k)


@jax.custom_batching.custom_vmap
def _power_or_eigh_top(k: Array) -> Array:
    """`_davenport_power`'s vectors if all of them are proven converged, else `eigh`'s."""
    power, converged = _davenport_power(k)
    return jax.lax.cond(jnp.all(converged), lambda k: power, _eigh_top, k)


@_power_or_eigh_top.def_vmap
def _power_or_eigh_top_vmap(axis_size, in_batched, k):
    # The function is batched over leading axes already: under `jax.vmap` it runs once on the whole
    # batch, so one `lax.cond` picks a branch for all of it (vmap's rule for a `cond` whose predicate
    # is batched computes both branches and selects).
    if not in_batched[0]:
        k = jnp.broadcast_to(k, (axis_size, *k.shape))
    return _power_or_eigh_top(k), True


def _eigh_top(k: Array) -> Array:
    _, vectors = jnp.linalg.eigh(k)
    return vectors[..., :, -1]


DAVENPORT_POWER_STEPS = 8


def _davenport_power(k: Array) -> tuple[Array, Array]:
    """The top eigenvector of Davenport's 4×4 matrices K (`_rotation.from_matrix`) of matrices near
    rotations by power steps, and whether it is proven to be the top one to round-off.

    For M = s R (s > 0), K has the eigenvalues (3s, −s, −s, −s) and ‖K‖_F = √12 s, so
    B = K + (‖K‖_F/√12) I = 4s q qᵀ has rank one: its column of largest diagonal entry is q (scaled
    by 4s|q_j| ≥ 2s, Shepperd's choice), and a power step with B gives q from any start not
    orthogonal to it. For M near a rotation the other eigenvalues of B are small against 4s and each
    step multiplies the error by their ratio (`DAVENPORT_POWER_STEPS` = 8 reach round-off for
    matrices 1e-2 from a rotation, entry-wise noise). The result is accepted with two facts, checked
    per matrix: its residual r = ‖Kq − λq‖ (λ = qᵀKq) is at most 16 ulp of ‖K‖_F, and
    λ − √(‖K‖_F² − λ²) > ‖K‖_F/4. The second bounds every other eigenvalue μ below λ (μ² ≤
    ‖K‖_F² − λ²), by a gap g > ‖K‖_F/4, so the angle to the top eigenvector is at most r/g ≤ 64 ulp.
    Matrices far from rotations fail the check (a batch holding one goes through `eigh`).

    On issue 8's CPU, 10⁵ exact rotations: 9 ms against 95–106 ms for `eigh` (a LAPACK call per
    matrix), the same quaternions to 4e-16 (float32: 2.3e-7)."""
    f2 = jnp.sum(k * k, axis=(-2, -1))
    eye = jnp.broadcast_to(jnp.eye(4, dtype=k.dtype), k.shape)
    shifted = k + jnp.sqrt(f2 / 12.0)[..., None, None] * eye
    column = jnp.argmax(jnp.diagonal(shifted, axis1=-2, axis2=-1), axis=-1)
    q = jnp.take_along_axis(shifted, column[..., None, None], axis=-1)[..., 0]
    for _ in range(DAVENPORT_POWER_STEPS):
        q = q / jnp.sqrt(jnp.sum(q * q, axis=-1, keepdims=True))
        q = jnp.einsum("...ij,...j->...i", shifted, q)
    q = q / jnp.sqrt(jnp.sum(q * q, axis=-1, keepdims=True))
    kq = jnp.einsum("...ij,...j->...i", k, q)
    lam = jnp.sum(q * kq, axis=-1)
    residual = jnp.sqrt(jnp.sum((kq - lam[..., None] * q) ** 2, axis=-1))
    size = jnp.sqrt(f2)
    gap = lam - jnp.sqrt(jnp.maximum(f2 - lam * lam, 0.0))
    ulp = jnp.finfo(k.dtype).eps
    return q, (gap > 0.25 * size) & (residual <= 16.0 * ulp * size)


def at_least_float32(x: Array) -> Array:
    """`x` in float32 if its dtype is narrower (float16, bfloat16): XLA:CPU's eigh, solve and det have
    no half-precision kernels. Differentiable (a cast)."""
    return x.astype(jnp.promote_types(x.dtype, jnp.float32))


def top_eigenvector(k: Array, *, davenport: bool = False) -> Array:
    """The unit eigenvector of the largest eigenvalue of symmetric matrices `k` (`_top_eigenvector`;
    `davenport`: 4×4 Davenport matrices, usually of rotations), computed in at least float32 and
    returned in the dtype of `k`."""
    return _top_eigenvector(at_least_float32(k), davenport).astype(k.dtype)


@_top_eigenvector.defjvp
def _top_eigenvector_jvp(davenport, primals, tangents):
    (k,), (dk,) = primals, tangents
    v = _top_eigenvector(k, davenport)
    # K and dK at scale 1 (v and dv do not depend on it): the deflation term v vᵀ below has norm 1,
    # lost against a K of 1e16 and dominating one of 1e-30 (weighted `mean`'s gradient 8 % off in
    # float32 for weights of 1e5, NaN for 1e-10; helper-53).
    k, e = prescale(k, axes=(-2, -1), limit=0)
    dk = power_of_two_times(dk, -e[..., None, None])
    dk = 0.5 * (dk + jnp.swapaxes(dk, -1, -2))
    kv = jnp.einsum("...ij,...j->...i", k, v)
    lam = jnp.sum(v * kv, axis=-1)
    outer = v[..., :, None] * v[..., None, :]
    eye = jnp.broadcast_to(jnp.eye(k.shape[-1], dtype=k.dtype), k.shape)
    shifted = lam[..., None, None] * eye - k + outer
    dkv = jnp.einsum("...ij,...j->...i", dk, v)
    rhs = dkv - jnp.sum(v * dkv, axis=-1, keepdims=True) * v
    dv = jnp.linalg.solve(shifted, rhs[..., None])[..., 0]
    return v, dv
