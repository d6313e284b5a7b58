"""Fast paths of `integrate` for its most common use: the Lie–Euler step with a constant or a sampled ω.

The results are those of the general scan in `_integrate.py` (the same steps, to round-off); only the
loop is restructured, as measured in benchmarks/README.md:

- the step rotation of a constant ω is formed once, outside the loop, and for the final state the loop
  steps only its powers r^k = a_k + b_k v (two numbers per body, 5 flops a step instead of a Hamilton
  product's 28) and applies r^T to q₀ once (`_constant_final`);
- the carry is structure-of-arrays (`(*batch,)` arrays) and the loop is unrolled, so XLA fuses
  several steps into one pass over the bodies instead of streaming an `(N, 4)` array every step;
- with sampled ω a group of steps is one kernel (`one_kernel`: XLA:CPU otherwise computes each of
  the four components in a loop of its own, repeating the exponential and the earlier steps for
  each), which reads each step's samples by index (no gathered copy, on or off the integration
  grid); the final state's derivatives store nothing per step: reverse mode is an adjoint that steps
  back with the inverse rotations, forward mode a tangent scan (`_sampled_final`);
- the final state for a constant ω has a closed-form derivative (`_constant_final`);
- the sampled run takes the exponential as a series in θ² (docs/numerics.md §4) instead of float64
  sin/cos, which XLA:CPU evaluates slowly, and checks as it goes that every step is small enough for
  it (|ω|Δt ≤ 0.5); if one is not, the run is made again with sin/cos;
- renormalisation every `renormalize_every` steps happens between groups of steps, not as a
  per-step select;
- float32's default compensated mode (Kahan-summed increments) runs on the same paths, for the final
  states (`_sampled_step`, `_constant_final`) and the trajectories, with the same derivative rules;
- `save="all"`: a constant ω's trajectory is formed blockwise (`_constant_trajectory`); with sampled
  ω the loop writes each step into the time-major output (no concatenation).

`integrate` calls `integrate_fast` first; it returns `None` when the arguments are outside what it
covers, and the general scan runs.
"""

from __future__ import annotations

import functools
import math

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jax import lax
from jax.extend.core import Primitive
from jax.interpreters import ad, batching, mlir
from jaxtyping import Array

from ._numerics import compensated_add, cos_half, cos_half_minus_one, sinc_half
from ._sharding import settled

# The series is used when θ² = |ω|²Δt² ≤ this for every step of the run (θ ≤ 0.5 rad per step).
SERIES_MAX_THETA_SQ = 0.25
# Steps fused into one pass over the bodies (one kernel).
UNROLL = 8
# Steps of a constant ω's powers (5 flops each) per kernel. W1 (N = 10⁵, T = 1,000, float64): 34 ms
# with 8, 29 with 16, 16 with 50, 18 with 100.
POWERS_UNROLL = 50
# The adjoint's kernels also write three numbers a step: beyond about a dozen outputs LLVM no longer
# vectorises the kernel (measured: 8 steps, 28 outputs, 2.5 s per W5 adjoint instead of 0.55 s).
ADJOINT_UNROLL = 3


def _series_coefficients(dtype, kind: str) -> tuple[float, ...]:
    """Taylor coefficients in θ² of cos(θ/2) (`kind="cos"`), sin(θ/2)/θ (`"sinc"`), 2 d/d(θ²) of
    sin(θ/2)/θ (`"slope"`), or of the adjoint's sin(θ)/(2θ) (`"half_sinc"`), (1 − cos θ)/(2θ²)
    (`"versine"`) and (θ − sin θ)/(2θ³) (`"jacobian"`), truncated where the next term is below
    round-off at θ² = SERIES_MAX_THETA_SQ."""
    eps = float(jnp.finfo(dtype).eps)
    coefficients = []
    for n in range(20):
        if kind == "cos":
            c = (-1.0) ** n / (4.0**n * math.factorial(2 * n))
        elif kind == "half_sinc":  # sin(θ)/(2θ)
            c = (-1.0) ** n / (2.0 * math.factorial(2 * n + 1))
        elif kind == "versine":  # (1 − cos θ)/(2θ²)
            c = (-1.0) ** n / (2.0 * math.factorial(2 * n + 2))
        elif kind == "jacobian":  # (θ − sin θ)/(2θ³)
            c = (-1.0) ** n / (2.0 * math.factorial(2 * n + 3))
        elif kind == "slope":  # 2 d/d(θ²) of sin(θ/2)/θ
            m = n + 1
            c = 2.0 * m * (-1.0) ** m / (2.0 ** (2 * m + 1) * math.factorial(2 * m + 1))
        else:
            c = (-1.0) ** n / (2.0 ** (2 * n + 1) * math.factorial(2 * n + 1))
        if n > 1 and abs(c) * SERIES_MAX_THETA_SQ**n < 0.01 * eps * abs(coefficients[0]):
            break
        coefficients.append(c)
    return tuple(coefficients)


def _horner(coefficients, x):
    result = jnp.full_like(x, coefficients[-1])
    for c in reversed(coefficients[:-1]):
        result = result * x + c
    return result


def _exp_soa(phi, series: bool):
    """exp(φ) of rotation vectors φ = (φx, φy, φz) as a structure-of-arrays quaternion."""
    x, y, z = phi
    theta_sq = x * x + y * y + z * z
    if series:
        real = _horner(_series_coefficients(theta_sq.dtype, "cos"), theta_sq)
        imag = _horner(_series_coefficients(theta_sq.dtype, "sinc"), theta_sq)
    else:
        real = cos_half(theta_sq)
        imag = sinc_half(theta_sq)
    return real, imag * x, imag * y, imag * z


def _one_kernel_cpu(*arrays):
    # −0 is the exact additive identity (x + (−0) = x, also for x = −0), so the sum over the padded
    # axis returns every array bit for bit, whatever order XLA adds in.
    zeros = tuple(jnp.array(-0.0, a.dtype) for a in arrays)
    padded = tuple(
        lax.pad(a[..., None], zero, [(0, 0, 0)] * a.ndim + [(0, 1, 0)])
        for a, zero in zip(arrays, zeros, strict=True)
    )
    return lax.reduce(
        padded,
        zeros,
        lambda left, right: tuple(x + y for x, y in zip(left, right, strict=True)),
        (arrays[0].ndim,),
    )


# The identity, as a primitive of its own: linear (its tangent and its transpose are itself, so
# derivatives and transposed maps are fused the same way) and lowered on CPU to one reduction.
_one_kernel_p = Primitive("jaxquat_one_kernel")
_one_kernel_p.multiple_results = True
_one_kernel_p.def_impl(lambda *arrays: list(arrays))
_one_kernel_p.def_abstract_eval(lambda *avals: list(avals))
mlir.register_lowering(
    _one_kernel_p, mlir.lower_fun(lambda *arrays: list(arrays), multiple_results=True)
)
mlir.register_lowering(
    _one_kernel_p,
    mlir.lower_fun(lambda *arrays: list(_one_kernel_cpu(*arrays)), multiple_results=True),
    platform="cpu",
)


def _one_kernel_jvp(primals, tangents):
    tangents = [ad.instantiate_zeros(t) for t in tangents]
    return _one_kernel_p.bind(*primals), _one_kernel_p.bind(*tangents)


def _one_kernel_transpose(cotangents, *arrays):
    cotangents = [
        jnp.zeros(a.aval.shape, a.aval.dtype) if type(c) is ad.Zero else c
        for c, a in zip(cotangents, arrays, strict=True)
    ]
    return _one_kernel_p.bind(*cotangents)


def _one_kernel_batch(arrays, axes):
    size = next(a.shape[d] for a, d in zip(arrays, axes, strict=True) if d is not None)
    arrays = [
        jnp.broadcast_to(a, (size,) + a.shape) if d is None else jnp.moveaxis(a, d, 0)
        for a, d in zip(arrays, axes, strict=True)
    ]
    return _one_kernel_p.bind(*arrays), [0] * len(arrays)


ad.primitive_jvps[_one_kernel_p] = _one_kernel_jvp
ad.primitive_transposes[_one_kernel_p] = _one_kernel_transpose
batching.primitive_batchers[_one_kernel_p] = _one_kernel_batch


def one_kernel(*arrays):
    """The arrays unchanged (same shape, floating dtypes), computed together by one loop on XLA:CPU.

    XLA:CPU emits every output of an elementwise computation as a loop of its own (it has no
    multi-output fusion of siblings), and each loop recomputes everything its output depends on. The
    four components of a quaternion that several unrolled steps produce share all of that work, so it
    ran four times over; a step's exponential, four times. One variadic reduction is one loop with
    all its outputs, and a sum over a trailing axis padded to two entries with −0 is an identity that
    XLA keeps as a reduction: everything the arrays depend on is then computed once per element, in
    registers. Measured on W3 (issue 8; N = 10⁵, T = 1,000, float64, 8 steps per group): 0.33 s
    against 1.08 s per call with four outputs, 1.6 s with each step's rotation materialised.

    Other backends fuse sibling outputs themselves: there this is the identity. It is linear, and its
    tangent and transpose are `one_kernel` again (derivative code is fused alike); vmap moves the
    batch axes to the front.
    """
    return tuple(_one_kernel_p.bind(*arrays))


def _fused(tree):
    """A pytree of same-shaped arrays, its leaves computed together by `one_kernel`."""
    leaves, structure = jax.tree_util.tree_flatten(tree)
    return jax.tree_util.tree_unflatten(structure, one_kernel(*leaves))


def _stepwise(step, separate: bool = False):
    """A group `advance(carry, ks)` for `_over_steps` from a single step `carry = step(carry, k)`; the
    carry is a tuple of same-shaped arrays, or of such tuples. The group ends in one kernel, or with
    `separate`, in one kernel per element of the carry: a linear map (a tangent scan, which JAX
    transposes) must not pass its constants and its linear values through one `one_kernel`, or
    JAX's partial evaluation takes the constants for linear values too."""

    def advance(carry, ks):
        for k in ks:
            carry = step(carry, k)
        return tuple(_fused(c) for c in carry) if separate else _fused(carry)

    return advance


def _multiply_soa(p, q):
    pw, px, py, pz = p
    qw, qx, qy, qz = q
    return (
        pw * qw - px * qx - py * qy - pz * qz,
        pw * qx + px * qw + py * qz - pz * qy,
        pw * qy - px * qz + py * qw + pz * qx,
        pw * qz + px * qy - py * qx + pz * qw,
    )


def _act_soa(q, r, frame: str):
    return _multiply_soa(r, q) if frame == "world" else _multiply_soa(q, r)


def _normalize(q):
    """q/|q| for a structure-of-arrays tuple or an `(..., 4)` array (the arithmetic of
    `_algebra.normalize`, so both paths round alike)."""
    if not isinstance(q, tuple):
        return q / jnp.sqrt(jnp.sum(q * q, axis=-1, keepdims=True))
    w, x, y, z = q
    norm = jnp.sqrt(w * w + x * x + y * y + z * z)
    return w / norm, x / norm, y / norm, z / norm


def _renormalized(carry, compensated: bool):
    """The carry with q/|q|: q itself, or (q, c) with the Kahan compensation c reset (`compensated`)."""
    if compensated:
        return _normalize(carry[0]), tuple(jnp.zeros_like(c) for c in carry[1])
    return _normalize(carry)


def _split(a: Array, size: int):
    return tuple(a[..., i] for i in range(size))


def _stack(q) -> Array:
    return jnp.stack(q, axis=-1)


def _run_all(step, carry, num_steps, renormalize_every, compensated=False):
    """q₀, q₁, …, q_T as a time-major `(T + 1, *batch, 4)` array, written by the scan itself;
    `step(carry, k)` takes step k (reading its own sample).

    The scan runs T + 1 iterations and saves the carry *before* each step, so q₀ is in place and no
    concatenation copies the trajectory; the last step's result is discarded (the caller's `step`
    reads step T − 1's sample again there: a sample the run does not use, NaN say, would otherwise
    make every reverse-mode derivative NaN through 0 · NaN). Against T iterations over the samples
    as xs followed by a concatenation (issue 8, N = 2·10⁴, T = 1,000, float64): 130 ms against
    207–259 ms per call, `jax.grad` 1.04 s against 1.28–1.33 s with the same gradient, and at
    N = 10⁵ in float32 the xs form's gradient ran out of 24 GiB where this one took 2.4 s. The whole
    trajectory is stored anyway, so nothing is checkpointed. Renormalisation is a conditional, taken
    only when due (a per-step select took 60–100 ms of a 0.4 s call at N = 10⁵, T = 1,000,
    float32). `compensated`: the carry is (q, c), q with its Kahan compensation c
    (`_sampled_step`); q is saved, and a renormalisation resets c.
    """
    every = (
        renormalize_every
        if renormalize_every is not None and renormalize_every <= num_steps
        else None
    )

    def advance(carry, k):
        carry = step(carry, k)
        if every is not None:
            carry = lax.cond((k + 1) % every == 0, renormalized, lambda c: c, carry)
        return carry

    def renormalized(carry):
        return _fused(_renormalized(carry, compensated))

    def saved(carry):
        return _stack(carry[0] if compensated else carry)

    ks = jnp.arange(num_steps + 1, dtype=jnp.int32)
    carry = settled(lambda c: advance(c, ks[0]), carry)
    _, states = lax.scan(lambda c, k: (advance(c, k), saved(c)), carry, ks)
    return states


def _next_power(c, w, v_sq):
    """(a, b) ↦ (a + b v)(w + v) = (a w − b |v|²) + (a + b w) v: one more power of r = w + v, held as
    its components in the plane of 1 and v (no division, so nothing singular at ω = 0)."""
    a, b = c
    return a * w - b * v_sq, a + b * w


def _constant_trajectory(q0, rotation, num_steps, frame, renormalize_every, w_minus_one=None):
    """q_k = r^k ⊗ q₀ (world; q₀ ⊗ r^k in the body frame) for k = 0 … T, time-major `(T + 1, *batch, 4)`.

    Blocked by the associativity of the product: with K ≈ √(T + 1) and k = jK + i, q_k = r^i ⊗ Q_j
    (world) with Q_j = r^(jK) ⊗ q₀. The powers of r = w + v all lie in the plane of 1 and v,
    r^i = a_i + b_i v with a_i = T_i(w), b_i = U_(i−1)(w) (Chebyshev polynomials; no division, so no
    singularity at ω = 0), so

        q_(jK+i) = a_i Q_j + b_i (v ⊗ Q_j)        (world;  a_i Q_j + b_i (Q_j ⊗ v) in the body frame)

    is one elementwise pass of two products and a sum per output component, writing the whole output
    in order on every core XLA uses; its per-row operands Q_j and v ⊗ Q_j stay in cache for the K rows
    that share them. These are the Lie–Euler steps' products, associated differently: each q_k is at
    most K + T/K products deep instead of k, so the round-off is smaller than stepping's. Measured
    against a full Hamilton product per element from 4-component power tables (issue 8, W2, N = 10⁵,
    T = 1,000, float64): 0.32 s against 0.44 s per call; a scan writing one `(N, 4)` slice per step ran
    at less than half that speed.

    The block rows lie in the same plane: r^(jK) = A_j + B_j b_K v by the same recurrence with
    r^K = a_K + b_K v as its step, two numbers per body and block, so with u = v ⊗ q₀ (body: q₀ ⊗ v)
    and v ⊗ v = −|v|²,

        Q_j = A_j q₀ + B_j b_K u,        v ⊗ Q_j = A_j u − B_j b_K |v|² q₀

    (the same in the body frame), one elementwise pass after a scan of two numbers. Against a scan of
    the quaternions Q_j (four numbers, four products per step): the same values to 5e-15, 4 % less
    time per W2 call (medians 0.210 s against 0.219 s, 25 interleaved rounds), and in float32 at small
    |ω|Δt up to 40× less round-off (T = 10⁴, |ω|Δt ≈ 1e-6: 1.5e-7 against 6.3e-6).

    Renormalisation: rotations keep the norm, so stepping's q_k is r^k ⊗ q₀ before the first
    renormalisation (step `renormalize_every`) and r^k ⊗ q₀/|q₀| from it on; the rows from that step on
    are scaled by 1/|q₀| (values and derivatives, including the radial part of dq₀, as stepping's).
    Each r^(jK) is then rescaled to unit norm, A_j² + B_j² b_K² |v|² = 1, against round-off drift
    (without it the error grew from 2e-15 to 7e-14 at T = 1,000 in float64).

    `w_minus_one` (w − 1 without cancellation) selects float32's compensated mode: both tables then
    hold (a − 1, b), advanced by Kahan-summed increments (docs/numerics.md §5).
    """
    length = num_steps + 1
    block = max(1, math.isqrt(length))
    num_blocks = -(-length // block)
    w, vx, vy, vz = rotation
    v_sq = vx * vx + vy * vy + vz * vz
    one, zero = jnp.ones_like(w), jnp.zeros_like(w)

    every = renormalize_every
    renormalized = every is not None and every <= num_steps
    if w_minus_one is not None:
        # Compensated (float32's long-run mode): both tables hold (a − 1, b), advanced by the
        # increments (a(w − 1) − b|v|², a + b(w − 1)) in Kahan summation; when renormalising, each
        # block row is rescaled to unit norm as below, by the increments of (a, b) ↦ (a, b)/|r|:
        # (a − 1) − (a − 1 − δ)/|r| and b(1 − 1/|r|) with δ = |r| − 1 = (2(a − 1) + (a − 1)² +
        # b²|v|²)/(1 + |r|) (no cancellation), Kahan-summed too.
        def powers(step_minus_one, step_sq, count, unit=False):
            def kahan(c, _):
                (alpha, b), (ca, cb) = c
                ta, ca = compensated_add(
                    alpha, alpha * step_minus_one + step_minus_one - b * step_sq, ca
                )
                tb, cb = compensated_add(b, (1.0 + alpha) + b * step_minus_one, cb)
                if unit:
                    size = jnp.sqrt((1.0 + ta) * (1.0 + ta) + tb * tb * step_sq)
                    excess = (2.0 * ta + ta * ta + tb * tb * step_sq) / (1.0 + size)
                    shrink = excess / size  # 1 − 1/|r|
                    ta, ca = compensated_add(ta, -ta * shrink - excess / size, ca)
                    tb, cb = compensated_add(tb, -tb * shrink, cb)
                return ((ta, tb), (ca, cb)), (alpha, b)

            (last, _), (alpha, b) = lax.scan(
                kahan, ((zero, zero), (zero, zero)), None, length=count
            )
            return last, 1.0 + alpha, b

        (alpha_block, b_block), a, b = powers(w_minus_one, v_sq, block)
        block_sq = b_block * b_block * v_sq
        _, big_a, big_b = powers(alpha_block, block_sq, num_blocks, unit=renormalized)
    else:

        def next_power(c, _):
            return _next_power(c, w, v_sq), c

        (a_block, b_block), (a, b) = lax.scan(next_power, (one, zero), None, length=block)
        # r^K = a_K + b_K v = a_K + v', with |v'|² = b_K² |v|².
        block_sq = b_block * b_block * v_sq

        def next_block(c, _):
            nxt = _next_power(c, a_block, block_sq)
            if renormalized:
                size = jnp.sqrt(nxt[0] * nxt[0] + nxt[1] * nxt[1] * block_sq)
                nxt = (nxt[0] / size, nxt[1] / size)
            return nxt, c

        _, (big_a, big_b) = lax.scan(next_block, (one, zero), None, length=num_blocks)
    big_b = big_b * b_block[None]  # (J, *batch)
    u = _act_soa(q0, (zero, vx, vy, vz), frame)  # v ⊗ q₀ (world), q₀ ⊗ v (body)
    q0s, us = _stack(q0)[None], _stack(u)[None]
    big_a, big_b = big_a[..., None], big_b[..., None]
    starts = big_a * q0s + big_b * us  # Q_j
    turned = big_a * us - (big_b * v_sq[None, ..., None]) * q0s  # v ⊗ Q_j (world), Q_j ⊗ v (body)
    starts, turned = starts[:, None], turned[:, None]  # (J, 1, *batch, 4)
    out = a[None, ..., None] * starts + b[None, ..., None] * turned  # (J, K, *batch, 4)
    out = out.reshape((num_blocks * block,) + out.shape[2:])[:length]
    if renormalized:
        norm0 = jnp.sqrt(sum(c * c for c in q0))
        steps = jnp.arange(length).reshape((length,) + (1,) * (norm0.ndim + 1))
        factor = jnp.where(steps >= every, 1.0 / norm0[None, ..., None], 1.0)
        out = out * factor.astype(out.dtype)
    return out


def _sampled_step(h, series: bool, frame: str, compensated: bool = False):
    """One Lie–Euler step with the per-step sample x (its three components): exp(x h) acting on a
    structure-of-arrays carry. `compensated`: the carry is (q, c) and the step is the float32
    long-run mode of `integrate` (docs/numerics.md §5), q ← q + δ with δ = (exp(x h) − 1) ⊗ q
    (world; q ⊗ (exp(x h) − 1) in the body frame) added by Kahan summation with the compensation
    c, exp(φ) − 1 = (cos(θ/2) − 1, S φ) formed without cancellation."""

    if not compensated:

        def step(carry, x):
            return _act_soa(carry, _exp_soa(tuple(h * c for c in x), series), frame)

        return step

    def kahan(carry, x):
        q, c = carry
        delta = _act_soa(q, _exp_minus_one_soa(tuple(h * u for u in x), series), frame)
        pairs = [compensated_add(*args) for args in zip(q, delta, c, strict=True)]
        return tuple(p[0] for p in pairs), tuple(p[1] for p in pairs)

    return kahan


def _step_minus_one(omega, h):
    """w − 1 = cos(θ/2) − 1 of the step rotation exp(ω h), θ = |ω h|, without cancellation."""
    return cos_half_minus_one(jnp.sum((omega * h) ** 2, axis=-1))


def _exp_minus_one_soa(phi, series: bool):
    """exp(φ) − 1 = (cos(θ/2) − 1, S φ), θ = |φ|, S = sin(θ/2)/θ, without cancellation: the series
    in θ² (`series`, for θ² ≤ SERIES_MAX_THETA_SQ) or −2 sin²(θ/4) from sin/cos."""
    x, y, z = phi
    theta_sq = x * x + y * y + z * z
    if series:
        real = theta_sq * _horner(_series_coefficients(theta_sq.dtype, "cos")[1:], theta_sq)
        imag = _horner(_series_coefficients(theta_sq.dtype, "sinc"), theta_sq)
    else:
        real = cos_half_minus_one(theta_sq)
        imag = sinc_half(theta_sq)
    return real, imag * x, imag * y, imag * z


def _over_steps(
    advance,
    carry,
    num_steps: int,
    renormalize_every,
    at_renormalization,
    reverse=False,
    unroll: int | None = None,
    pairs: bool = False,
):
    """`carry = advance(carry, ks)` over the steps k = 0 … T − 1, where `ks` is a list of consecutive
    step numbers (traced ints; descending, and the whole run in reverse order, if `reverse`), with
    `carry = at_renormalization(carry)` after every `renormalize_every`-th step (forward runs only:
    the adjoint, the one reverse run, applies renormalisations as a condition on k instead).

    `advance` runs its group of steps as one piece of straight-line code, which it ends with
    `one_kernel`: XLA then makes the whole group one loop over the bodies, the carry staying in
    registers between its steps. The groups are `unroll` steps long (default `UNROLL`), shortened to
    a divisor of `renormalize_every` so that renormalisations fall between groups, and one loop runs
    them all (a `lax.cond` after each group renormalises when due): the group's code is compiled once.
    The last T mod `unroll` steps are taken one at a time.

    With `pairs`, each iteration of the loop runs two groups: the carry then alternates between two
    sets of buffers instead of being copied back after every group (XLA cannot write a kernel's
    outputs over its inputs), for twice the group's code to compile.
    """
    every = (
        renormalize_every
        if renormalize_every is not None and renormalize_every <= num_steps
        else None
    )
    size = max(1, min(UNROLL if unroll is None else unroll, num_steps))
    if every is not None:
        size = max(d for d in range(1, size + 1) if every % d == 0)
    if reverse and every is not None:
        raise ValueError("_over_steps: renormalisation is for forward runs only")
    groups, rest = divmod(num_steps, size)
    twice = 2 if pairs and groups >= 2 else 1

    def group(g, c):
        first = g * size
        if reverse:
            return advance(c, [first + size - 1 - j for j in range(size)])
        c = advance(c, [first + j for j in range(size)])
        if every is not None:
            c = lax.cond((first + size) % every == 0, at_renormalization, lambda c: c, c)
        return c

    def remaining(c):
        start = groups * size
        if reverse:
            return lax.fori_loop(0, rest, lambda i, c: advance(c, [num_steps - 1 - i]), c)
        return lax.fori_loop(0, rest, lambda i, c: advance(c, [start + i]), c)

    carry = settled(lambda c: advance(c, [0] * (size if groups else 1)), carry)
    if reverse:
        carry = remaining(carry) if rest else carry
        return lax.fori_loop(0, groups, lambda i, c: group(groups - 1 - i, c), carry, unroll=twice)
    carry = lax.fori_loop(0, groups, group, carry, unroll=twice)
    return remaining(carry) if rest else carry


def _renormalized_blocks(num_steps: int, renormalize_every: int | None) -> int:
    """How many renormalisations a run makes (after steps k·every, k = 1 … blocks)."""
    every = renormalize_every
    return 0 if every is None or every > num_steps else num_steps // every


def _read(samples, indices):
    """The sample of step k as its three components: samples[k], or samples[indices[k]] (no gathered
    copy; on the grid `indices` is None, which saves the second lookup per step).

    Each component is a dynamic slice of its own: XLA:CPU estimates the code a fused producer costs
    by the shape-changing users it reaches, and one slice of the whole row, reached by three
    component slices and every output of a kernel, was refused fusion and copied (W5's adjoint: two
    of three rows, 0.15 s)."""
    batch = samples.shape[1:-1]

    def read(k):
        if indices is not None:
            k = lax.dynamic_index_in_dim(indices, k, keepdims=False)
        k = jnp.asarray(k)
        zeros = (jnp.zeros((), k.dtype),) * len(batch)
        return tuple(
            lax.dynamic_slice(
                samples, (k, *zeros, jnp.asarray(c, k.dtype)), (1, *batch, 1)
            ).reshape(batch)
            for c in range(3)
        )

    return read


def _exp_and_slope(phi, series: bool):
    """exp(φ) (structure of arrays) with S = sin(θ/2)/θ and S₂ = 2 dS/d(θ²), θ = |φ|, from which
    d exp(φ)[dφ] = (−½ S ⟨φ, dφ⟩, S dφ + S₂ ⟨φ, dφ⟩ φ)."""
    x, y, z = phi
    theta_sq = x * x + y * y + z * z
    real, ix, iy, iz = _exp_soa(phi, series)
    slope = _horner(_series_coefficients(theta_sq.dtype, "slope"), theta_sq)
    if series:
        sinc = _horner(_series_coefficients(theta_sq.dtype, "sinc"), theta_sq)
    else:
        sinc = sinc_half(theta_sq)
        # 2 dS/d(θ²) = (cos(θ/2)/2 − S)/θ², which cancels for small θ: the series up to θ² = 0.25.
        near = theta_sq <= SERIES_MAX_THETA_SQ
        safe = jnp.where(near, 1.0, theta_sq)
        slope = jnp.where(near, slope, (0.5 * real - sinc) / safe)
    return (real, ix, iy, iz), sinc, slope


def _conjugate_soa(q):
    w, x, y, z = q
    return w, -x, -y, -z


def _dot_soa(a, b):
    return sum(u * v for u, v in zip(a, b, strict=True))


def _cross_soa(a, b):
    ax, ay, az = a
    bx, by, bz = b
    return ay * bz - az * by, az * bx - ax * bz, ax * by - ay * bx


def _sampled_tangent(
    q0, samples, h, indices, dq0, dsamples, dh, series, frame, num_steps, renormalize_every
):
    """dq_T of the sampled run for tangents (dq₀, dsamples, dh) (`dh` may be None): one forward scan
    carrying (q, dq), with dq_k = d r_k ⊗ q_(k−1) + r_k ⊗ dq_(k−1) (world frame) and the tangent of
    q ↦ q/|q| at each renormalisation. (q and dq are separate carries: JAX transposes this map for
    second derivatives, and only dq is linear.)"""
    read, read_tangent = _read(samples, indices), _read(dsamples, indices)

    def step(carry, k):
        q, dq = carry
        xv = read(k)
        phi = tuple(h * c for c in xv)
        dphi = tuple(h * c for c in read_tangent(k))
        if dh is not None:
            dphi = tuple(a + dh * c for a, c in zip(dphi, xv, strict=True))
        r, sinc, slope = _exp_and_slope(phi, series)
        inner = _dot_soa(phi, dphi)
        dr = (-0.5 * sinc * inner,) + tuple(
            sinc * d + (slope * inner) * p for d, p in zip(dphi, phi, strict=True)
        )
        first, second = (dr, q), (r, dq)
        if frame == "body":
            first, second = (q, dr), (dq, r)
        dq = tuple(
            a + b for a, b in zip(_multiply_soa(*first), _multiply_soa(*second), strict=True)
        )
        return _act_soa(q, r, frame), dq

    def normalize(carry):
        q, dq = carry
        size = jnp.sqrt(_dot_soa(q, q))
        unit = tuple(a / size for a in q)
        radial = _dot_soa(unit, dq)
        return unit, tuple((d - radial * u) / size for d, u in zip(dq, unit, strict=True))

    carry = tuple(_split(c, 4) for c in jnp.broadcast_arrays(q0, dq0))
    final = _over_steps(
        _stepwise(step, separate=True),
        carry,
        num_steps,
        renormalize_every,
        normalize,
        # One step per kernel: unrolled, its second derivatives (forward over reverse) took ~4x as
        # long to compile, and forward mode is not the fast path.
        unroll=1,
    )
    return _stack(final[1])


def _sampled_adjoint_steps(
    q0,
    q_final,
    samples,
    h,
    indices,
    cotangent,
    series,
    frame,
    num_steps,
    renormalize_every,
    with_weight=True,
    unroll=None,
):
    """The cotangents of (samples, h, q₀) for the cotangent of q_T, by one reverse scan that carries a
    single quaternion per body: nothing is stored on the way forward, and the states are not rebuilt.

    Transposing dq_k = d r_k ⊗ q_(k−1) + r_k ⊗ dq_(k−1) (world frame): with λ_k the cotangent of q_k,
    λ_(k−1) = r̄_k ⊗ λ_k, and μ_k = λ_k ⊗ q̄_(k−1) is the cotangent of r_k (⟨a ⊗ b, c⟩ = ⟨b, ā ⊗ c⟩ =
    ⟨a, c ⊗ b̄⟩). Going back, q and λ are both multiplied on the left by the same r̄_k, so
    p_k = λ_k ⊗ q̄_k evolves by conjugation alone, and

        μ_k = p_k ⊗ r_k,        p_(k−1) = λ_(k−1) ⊗ q̄_(k−1) = r̄_k ⊗ μ_k

    (body frame: μ_k = q̄_(k−1) ⊗ λ_k = r_k ⊗ p_k with p = q̄ ⊗ λ, and p_(k−1) = μ_k ⊗ r̄_k). A
    renormalisation q = q̃/|q̃| maps λ to (λ − q⟨q, λ⟩)/|q̃| while q̃ = |q̃| q: λ ⊗ q̄ keeps its vector
    part and loses its scalar part ⟨λ, q⟩, so it sets p_w = 0. At the start, λ₀ = p₀ ⊗ q₀/|q₀|²
    (body: q₀ ⊗ p₀/|q₀|²).

    Conjugation keeps p_w and turns v = p_v by the angle θ = |φ| about φ (the sign ± is + in the
    world frame, − in the body frame):

        v ← cos θ v + 2S² ⟨v, φ⟩ φ ± 2cS (v × φ),        r = (c, S φ), c = cos(θ/2), S = sin(θ/2)/θ.

    Through d exp, the cotangent of φ_k is S μ_v + (−½ S μ_w + S₂ ⟨φ, μ_v⟩) φ (S₂ = 2 dS/d(θ²)),
    and with μ = p ⊗ r it is

        g = B ⟨v, φ⟩ φ + cS v ± S² (v × φ),        B = ½S² + c S₂ = (θ − sin θ)/(2θ³):

    p_w drops out exactly (its part of μ is p_w r, and ⟨r, d r⟩ = 0 for the unit r = exp(φ)), so only
    v is carried, and p_w enters only λ₀ (p_T's until the last renormalisation, 0 before it). With
    φ = Δt x the step takes the three coefficients Δt cS = Δt sin θ/(2θ), Δt² S² and Δt³ B as series
    in θ² (sin/cos off the series), cos θ = 1 − 2θ²S², and writes h g. (The form with p_w carried
    through μ took 107 operations a step against 96, the same time on the CPU of issue 8, whose
    adjoint is bound by memory traffic; both agree to round-off.) Per body and step this reads the
    sample, carries 3 numbers and writes 3 (the first form carried q and λ, rebuilt by inverse steps:
    8 numbers). A group of `unroll` steps (by default `ADJOINT_UNROLL` on the common path) is one
    kernel (`one_kernel`) that outputs v and the group's rows of the cotangent, which are then
    written into the carried output in place: as one block on the integration grid, one row at a
    time (added to the row of its held sample) off it. The Δt cotangent Σ⟨x_k, g_k⟩ = ½ Σ⟨v, x_k⟩
    (θ²B + cS = ½) is accumulated only `with_weight`.
    """
    sign = 1.0 if frame == "world" else -1.0
    read = _read(samples, indices)

    # Going back, p_w = ⟨λ, q⟩ is kept by every step and zeroed by every renormalisation: p₀'s is 0
    # if the run renormalised at all.
    renormalized = _renormalized_blocks(num_steps, renormalize_every) > 0

    h_sq = h * h
    if series:
        dtype = jnp.result_type(samples, h)
        scaled = tuple(
            tuple(scale * c for c in _series_coefficients(dtype, kind))
            for scale, kind in ((h, "half_sinc"), (h_sq, "versine"), (h_sq * h, "jacobian"))
        )

    def coefficients(xx):
        """(h sin θ/(2θ), h² (1 − cos θ)/(2θ²), h³ (θ − sin θ)/(2θ³)) for θ² = h² |x|²."""
        if series:
            return tuple(_horner(c, xx * h_sq) for c in scaled)
        theta_sq = xx * h_sq
        c, s = cos_half(theta_sq), sinc_half(theta_sq)
        # (θ − sin θ)/(2θ³) = (½ − cS)/θ², which cancels for small θ: the series up to θ² = 0.25.
        near = theta_sq <= SERIES_MAX_THETA_SQ
        series_value = _horner(_series_coefficients(theta_sq.dtype, "jacobian"), theta_sq)
        safe = jnp.where(near, 1.0, theta_sq)
        jacobian = jnp.where(near, series_value, (0.5 - c * s) / safe)
        return h * (c * s), h_sq * (s * s), (h_sq * h) * jacobian

    def advance(carry, ks):
        v, weight, total = carry
        rows = []
        for k in ks:
            xv = read(k)
            xx = _dot_soa(xv, xv)
            d = _dot_soa(v, xv)  # ⟨v, x⟩
            cross = _cross_soa(v, xv)  # v × x
            big_p, big_q, big_r = coefficients(xx)
            # h g = h³ B ⟨v, x⟩ x + h cS v ± h² S² (v × x), g = B ⟨v, φ⟩ φ + cS v ± S² (v × φ)
            along, e = big_r * d, sign * big_q
            rows.append(
                tuple(along * f + big_p * u + e * x for f, u, x in zip(xv, v, cross, strict=True))
            )
            if weight is not None:  # ⟨x, g⟩ = ⟨v, x⟩ (θ² B + cS) = ⟨v, x⟩/2
                weight = weight + d
            # v ← cos θ v + 2S² ⟨v, φ⟩ φ ± 2cS (v × φ): the turn of p_v (rotation by θ about φ)
            two_q = 2.0 * big_q
            turn, along_x, across = 1.0 - two_q * xx, two_q * d, 2.0 * sign * big_p
            v = [turn * u + along_x * f + across * x for u, f, x in zip(v, xv, cross, strict=True)]
        extra = () if weight is None else (weight,)
        outputs = one_kernel(*v, *extra, *(c for row in rows for c in row))
        v, extra, flat = outputs[:3], outputs[3 : 3 + len(extra)], outputs[3 + len(extra) :]
        rows = [_stack(flat[3 * i : 3 * i + 3]) for i in range(len(ks))]
        if indices is None:  # sample k is step k's alone; the group's steps descend from ks[0]
            block = jnp.stack(rows[::-1])
            total = lax.dynamic_update_slice_in_dim(total, block.astype(total.dtype), ks[-1], 0)
        else:  # a held sample serves several steps
            for k, row in zip(ks, rows, strict=True):
                index = lax.dynamic_index_in_dim(indices, k, keepdims=False)
                here = lax.dynamic_index_in_dim(total, index, keepdims=False)
                total = lax.dynamic_update_index_in_dim(total, here + row, index, 0)
        return tuple(v), (extra[0] if extra else None), total

    world = frame == "world"
    q_final, cotangent, start = (_split(a, 4) for a in jnp.broadcast_arrays(q_final, cotangent, q0))
    back = _conjugate_soa(q_final)
    p_end = _multiply_soa(cotangent, back) if world else _multiply_soa(back, cotangent)
    carry = (p_end[1:], jnp.zeros_like(p_end[0]) if with_weight else None, jnp.zeros_like(samples))
    v, weight, total = _over_steps(
        advance,
        carry,
        num_steps,
        None,
        None,
        reverse=True,
        unroll=min(ADJOINT_UNROLL, _group_size(series, indices)) if unroll is None else unroll,
        pairs=indices is None,
    )
    p = (jnp.zeros_like(v[0]) if renormalized else p_end[0], *v)
    # λ₀ = p₀ ⊗ q₀/|q₀|² with q₀ divided by its largest component first (|q₀|² of a float32 q₀
    # overflows above ~1e19 and underflows below ~1e-19).
    scale = functools.reduce(jnp.maximum, tuple(jnp.abs(c) for c in start))
    dead = scale == 0
    scale = jnp.where(dead, 1.0, scale)
    unit = tuple(c / scale for c in start)
    lam = _multiply_soa(p, unit) if world else _multiply_soa(unit, p)
    size_sq = scale * _dot_soa(unit, unit)
    lam = _stack(tuple(c / size_sq for c in lam))
    if _renormalized_blocks(num_steps, renormalize_every) == 0:
        # q₀ = 0 (a padded body) carries p ≡ 0, which holds no λ. Without renormalisation
        # q_T = Q ⊗ q₀ (body frame q₀ ⊗ Q) for the run's rotation Q, so λ₀ = Q̄ ⊗ λ_T (λ_T ⊗ Q̄): one
        # more forward run, from the identity, made only if some q₀ is zero.
        def through_the_rotation():
            one = jnp.ones_like(start[0])
            zero = jnp.zeros_like(start[0])
            # (A rare path: one step per kernel, to keep compilation short.)
            rotation, _ = _sampled_run(
                _stack((one, zero, zero, zero)),
                samples,
                h,
                indices,
                series,
                frame,
                num_steps,
                renormalize_every,
                unroll=1,
            )
            back = _conjugate_soa(_split(rotation, 4))
            return _stack(
                _multiply_soa(back, cotangent) if world else _multiply_soa(cotangent, back)
            )

        fallback = lax.cond(jnp.any(dead), through_the_rotation, lambda: jnp.zeros_like(lam))
        lam = jnp.where(dead[..., None], fallback, lam)
    return total, (0.5 * jnp.sum(weight) if with_weight else None), lam


# The adjoint's own derivatives (second derivatives of the run) are those of the same adjoint taken one
# step per kernel: they compile in a fraction of the time the unrolled loop's would.
_sampled_adjoint = jax.custom_jvp(_sampled_adjoint_steps, nondiff_argnums=(6, 7, 8, 9, 10, 11))


@_sampled_adjoint.defjvp
def _sampled_adjoint_jvp(
    series, frame, num_steps, renormalize_every, with_weight, unroll, primals, tangents
):
    def one_step_per_kernel(*arrays):
        return _sampled_adjoint_steps(
            *arrays, series, frame, num_steps, renormalize_every, with_weight, 1
        )

    return jax.jvp(one_step_per_kernel, primals, tangents)


@functools.partial(jax.custom_jvp, nondiff_argnums=(5, 6, 7, 8, 9))
def _sampled_final(
    q_given, q0, samples, h, indices, series, frame, num_steps, renormalize_every, compensated
):
    """The final state of the sampled Lie–Euler run, step k using samples[indices[k]], with the
    exponential's series in θ² (`series`) or sin/cos; `q_given` is that state when it has been
    computed already (the value is returned as it is, without derivative of its own), else None.

    Derivatives are exact (to round-off) and store nothing per step, in both modes:

    - forward mode (jvp, jacfwd) runs `_sampled_tangent`, a scan carrying (q, dq);
    - reverse mode (grad, jacrev) runs `_sampled_adjoint`, which steps back through the run with the
      inverse rotations instead of storing or recomputing the states (memory O(N), no checkpointing).

    The two are tied together as a linear map with a custom transpose through
    `lax.custom_linear_solve` (JAX has no public `custom_transpose`): with M the strictly
    block-lower-triangular operator that writes L(dsamples, dh, dq₀) = dq_T into an extra slot,
    (I − M)⁻¹ = I + M because M² = 0, so "solving" (I − M) x = (…, 0) is applying I + M, and its
    transpose I + Mᵀ is the adjoint scan. Being a true inverse pair, the primitive's own rules also give
    correct second derivatives (forward or reverse over reverse).
    """
    if q_given is not None:
        return q_given
    return _sampled_run(
        q0,
        samples,
        h,
        indices,
        series,
        frame,
        num_steps,
        renormalize_every,
        compensated=compensated,
    )[0]


def _group_size(series: bool, indices) -> int:
    """Steps per kernel: `UNROLL` on the common path, the series on the integration grid, and 1 on
    the others (each unrolled variant of a run or its adjoint adds about a second of compilation)."""
    return UNROLL if series and indices is None else 1


def _sampled_run(
    q0,
    samples,
    h,
    indices,
    series,
    frame,
    num_steps,
    renormalize_every,
    unroll=None,
    compensated=False,
):
    """The run of `_sampled_final` and, with the series (`series`), the largest θ² of its steps (else
    0); `unroll` steps per kernel, by default `_group_size`; `compensated`: `integrate`'s float32
    long-run mode (Kahan-summed increments, the compensation reset at each renormalisation). Never
    differentiated itself."""
    step = _sampled_step(h, series, frame, compensated)
    read = _read(samples, indices)
    q = _split(q0, 4)
    if compensated:
        q = (q, tuple(jnp.zeros_like(c) for c in q))
    renormalize = functools.partial(_renormalized, compensated=compensated)

    def state(final):
        return _stack(final[0] if compensated else final)

    unroll = _group_size(series, indices) if unroll is None else unroll
    if not series:
        final = _over_steps(
            _stepwise(lambda c, k: step(c, read(k))),
            q,
            num_steps,
            renormalize_every,
            renormalize,
            unroll=unroll,
        )
        return state(final), jnp.zeros((), q0.dtype)

    def tracked(carry, k):
        q, largest = carry
        sample = read(k)
        x, y, z = (h * c for c in sample)
        return step(q, sample), jnp.maximum(largest, x * x + y * y + z * z)

    final, largest = _over_steps(
        _stepwise(tracked),
        (q, jnp.zeros_like(q0[..., 0])),
        num_steps,
        renormalize_every,
        lambda c: (renormalize(c[0]), c[1]),
        unroll=unroll,
    )
    return state(final), jnp.max(largest, initial=0.0)


def _sum_of_none(a):
    """The sum of none of `a`'s entries: 0, computed from `a` (so linear in it, and tied to it in a
    jaxpr) without reading it. A slice to size 0 on every axis: reshaping or indexing an array
    sharded with explicit axis types (`jax.make_mesh`'s default) raises a ShardingTypeError, an empty
    slice of a sharded axis does not."""
    a = a[None] if a.ndim == 0 else a
    return jnp.sum(lax.slice(a, (0,) * a.ndim, (0,) * a.ndim))


def _sampled_final_jvp(series, frame, num_steps, renormalize_every, compensated, primals, tangents):
    from jax.custom_derivatives import SymbolicZero

    q_given, q0, samples, h, indices = primals
    # The primal by this function itself (free when the state is given): derivatives of higher order
    # then go through this rule again, never through the run's unrolled loop.
    q_final = _sampled_final(*primals, series, frame, num_steps, renormalize_every, compensated)
    names = tuple(
        name
        for name, t in zip(("q0", "samples", "h"), tangents[1:4], strict=True)
        if not isinstance(t, SymbolicZero)
    )
    values = tuple(t for t in tangents[1:4] if not isinstance(t, SymbolicZero))
    # custom_linear_solve transposes only right-hand sides that are linear in the tangents, so the
    # output slot's zero is made from a live tangent: the sum of none of its entries, whose transpose
    # pads an empty array, which XLA drops (one entry's transpose was a pass over the whole cotangent,
    # 2.4 GB for the samples at N = 10⁵).
    seed = _sum_of_none(values[0])
    zero = jnp.zeros_like(q_final) * seed.astype(q_final.dtype)

    # Checkpointed: its primal-only part (the states, the step rotations) would otherwise be split off
    # by JAX's partial evaluation and run in the forward pass of every reverse-mode derivative, where
    # nothing uses it (the transpose is the adjoint): one more run, with per-step residuals.
    @jax.checkpoint
    def tangent_map(inputs):
        given = dict(zip(names, inputs, strict=True))
        return _sampled_tangent(
            q0,
            samples,
            h,
            indices,
            given.get("q0", jnp.zeros_like(q0)),
            given.get("samples", jnp.zeros_like(samples)),
            given.get("h"),
            series,
            frame,
            num_steps,
            renormalize_every,
        )

    def matvec(x):  # I − M
        # Every slot times (1 + 0 · a sum over none of every primal's entries): unchanged and still
        # linear, but tied to all the primals, so that the primitive's rule for derivatives w.r.t.
        # its constants gives every slot a tangent whichever primal an outer derivative is taken
        # w.r.t. (it leaves slots without one as known zeros, which cannot be transposed: reverse
        # over reverse failed when the slot was tied to nothing, reverse w.r.t. the samples over
        # forward w.r.t. q₀ when it was tied to its own primal only). A product, not a sum: JAX
        # derives the transposed map (vecmat) by transposing this one, which drops additive
        # constants but keeps the factor (a loss linear in q_T failed).
        anchor = sum(_sum_of_none(p) for p in (q0, samples, h))
        *inputs, out = x
        tied = tuple(a * (1.0 + 0.0 * anchor.astype(a.dtype)) for a in (*inputs, out))
        return tied[:-1] + (tied[-1] - tangent_map(inputs),)

    def solve(_, b):  # (I − M)⁻¹ = I + M
        *inputs, out = b
        return tuple(inputs) + (out + tangent_map(inputs),)

    def transpose_solve(_, b):  # (I + M)ᵀ = I + Mᵀ
        *inputs, out = b
        total, weight, lam = _sampled_adjoint(
            q0,
            q_final,
            samples,
            h,
            indices,
            out,
            series,
            frame,
            num_steps,
            renormalize_every,
            with_weight="h" in names,
        )
        cotangents = {"q0": lam, "samples": total, "h": weight}
        return tuple(
            a + cotangents[n].astype(a.dtype) for a, n in zip(inputs, names, strict=True)
        ) + (out,)

    x = lax.custom_linear_solve(matvec, values + (zero,), solve, transpose_solve)
    return q_final, x[-1]


_sampled_final.defjvp(_sampled_final_jvp, symbolic_zeros=True)


def _matmul3(a, b):
    """Product of 3×3 matrices held as row-major tuples of nine arrays (elementwise, fuses well)."""
    return tuple(
        a[3 * i] * b[j] + a[3 * i + 1] * b[3 + j] + a[3 * i + 2] * b[6 + j]
        for i in range(3)
        for j in range(3)
    )


def _rotation_sums(matrix, count: int):
    """Σ_{m=0}^{count−1} R^m for rotation matrices R `(..., 3, 3)`, by binary doubling (O(log count)
    products; exact at R = I, no special angles)."""
    entries = tuple(matrix[..., i, j] for i in range(3) for j in range(3))
    zero, one = jnp.zeros_like(entries[0]), jnp.ones_like(entries[0])
    eye = tuple(one if i % 4 == 0 else zero for i in range(9))
    power, total = eye, (zero,) * 9  # (R^n, Σ_{m<n} R^m) for n = 0
    base_power, base_total = entries, eye  # … for n = 1, then 2, 4, …
    n = count
    while n:
        if n & 1:
            product = _matmul3(power, base_total)
            power = _matmul3(power, base_power)
            total = tuple(t + p for t, p in zip(total, product, strict=True))
        n >>= 1
        if n:
            product = _matmul3(base_power, base_total)
            base_power = _matmul3(base_power, base_power)
            base_total = tuple(t + p for t, p in zip(base_total, product, strict=True))
    return jnp.stack(total, axis=-1).reshape(matrix.shape)


@functools.partial(jax.custom_jvp, nondiff_argnums=(3, 4, 5, 6, 7))
def _constant_final(q0, omega, h, frame, num_steps, renormalize_every, unroll, compensated=False):
    """q_T = r^T ⊗ q₀ (world; q₀ ⊗ r^T in the body frame), r = exp(ω h), by stepping the powers of r.

    Its derivative is the closed form of the product's derivative rather than the derivative of the
    loop: with ṙ = ζ ⊗ r (world), d(r^T) = Σ_{m<T} Ad_{r^m}(ζ) ⊗ r^T, so
    q̇_T = (H ζ) ⊗ q_T + r^T ⊗ q̇₀ with H = Σ_{m<T} R(r)^m formed by doubling in O(log T). Reverse
    mode then costs about one forward pass and stores nothing per step (W5). The steps are the same
    products, so this is the derivative of the computed result to round-off (O(Tε)).

    `compensated` (float32's default long-run mode): the powers advance by their increments,
    r^(k+1) − r^k = r^k ⊗ (r − 1) = (a (w − 1) − b |v|²) + (a + b (w − 1)) v with w − 1 formed without
    cancellation, Kahan-summed (the compensation reset at each renormalisation).
    """
    # Every power of r = w + v lies in the plane of 1 and v: r^k = a_k + b_k v (`_next_power`, the
    # step's product restricted to that plane). Stepping those two components and applying r^T once
    # is the same products associated differently (r^T ⊗ q₀ rather than r ⊗ (r ⊗ (… ⊗ q₀))), at
    # 5 flops a step instead of the Hamilton product's 28.
    w, vx, vy, vz = _exp_soa(_split(omega * h, 3), False)
    v_sq = vx * vx + vy * vy + vz * vz

    def normalize(c):  # |a + b v|
        a, b = c
        norm = jnp.sqrt(a * a + b * b * v_sq)
        return a / norm, b / norm

    if compensated:
        w_minus_one = _step_minus_one(omega, h)

        def kahan(c, _):
            (a, b), (ca, cb) = c
            next_a, ca = compensated_add(a, a * w_minus_one - b * v_sq, ca)
            next_b, cb = compensated_add(b, a + b * w_minus_one, cb)
            return (next_a, next_b), (ca, cb)

        (a, b), _ = _over_steps(
            _stepwise(kahan),
            ((jnp.ones_like(w), jnp.zeros_like(w)), (jnp.zeros_like(w), jnp.zeros_like(w))),
            num_steps,
            renormalize_every,
            lambda c: (normalize(c[0]), (jnp.zeros_like(w), jnp.zeros_like(w))),
            unroll=unroll,
        )
    else:
        a, b = _over_steps(
            _stepwise(lambda c, _: _next_power(c, w, v_sq)),
            (jnp.ones_like(w), jnp.zeros_like(w)),
            num_steps,
            renormalize_every,
            normalize,
            unroll=unroll,
        )
    # Renormalised stepping ends at r^T ⊗ q₀/|q₀| (rotations keep the norm), unrenormalised at r^T ⊗ q₀.
    start = _split(q0, 4)
    if renormalize_every is not None and renormalize_every <= num_steps:
        start = _normalize(start)
    # v ⊗ q₀ (world), q₀ ⊗ v (body)
    turned = _act_soa(start, (jnp.zeros_like(vx), vx, vy, vz), frame)
    return _stack(tuple(a * s + b * t for s, t in zip(start, turned, strict=True)))


@_constant_final.defjvp
def _constant_final_jvp(
    frame, num_steps, renormalize_every, unroll, compensated, primals, tangents
):
    from ._algebra import conjugate, inverse, multiply
    from ._rotation import from_rotvec, to_matrix, to_rotvec

    q0, omega, h = primals
    dq0, domega, dh = tangents
    q_final = _constant_final(
        q0, omega, h, frame, num_steps, renormalize_every, unroll, compensated
    )
    # The step rotation and its tangent, through the same (series-switched) exponential.
    phi, dphi = omega * h, domega * h + omega * dh
    r, dr = jax.jvp(lambda p: _stack(_exp_soa(_split(p, 3), False)), (phi,), (dphi,))
    total = _rotation_sums(to_matrix(r), num_steps)  # H = Σ_{m<T} R^m
    # With renormalisation the result is r^T ⊗ q₀/|q₀| (rotations keep the norm); without, r^T ⊗ q₀.
    renormalized = renormalize_every is not None and renormalize_every <= num_steps
    if renormalized:
        start, dstart = jax.jvp(_normalize, (q0,), (dq0,))
    else:
        start, dstart = q0, dq0
    world = frame == "world"
    # ζ = ṙ ⊗ r̄ (world) or r̄ ⊗ ṙ (body), pure; the sum is H ζ (world) or Hᵀ ζ (body).
    zeta = (multiply(dr, conjugate(r)) if world else multiply(conjugate(r), dr))[..., 1:]
    spin = jnp.einsum("...ij,...j->...i" if world else "...ji,...j->...i", total, zeta)
    spin = jnp.concatenate([jnp.zeros_like(spin[..., :1]), spin], axis=-1)
    # r^T = q_T ⊗ start⁻¹ (world) or start⁻¹ ⊗ q_T (body); for a zero start (a padded body, without
    # renormalisation) that is 0/0, and r^T = exp(T log r) is formed instead, only when some start
    # is zero (`lax.cond`; the same rotation as the stepped powers to O(Tε)).
    zero = jnp.all(start == 0, axis=-1, keepdims=True)
    safe = jnp.where(zero, jnp.ones_like(start), start)
    power = multiply(q_final, inverse(safe)) if world else multiply(inverse(safe), q_final)
    if not renormalized:
        power = lax.cond(
            jnp.any(zero),
            lambda: jnp.where(zero, from_rotvec(num_steps * to_rotvec(r)), power),
            lambda: power,
        )
    if world:
        tangent = multiply(spin, q_final) + multiply(power, dstart)
    else:
        tangent = multiply(q_final, spin) + multiply(dstart, power)
    return q_final, tangent


def integrate_fast(
    q0,
    omega,
    dt,
    t0,
    *,
    num_steps,
    frame,
    method,
    save,
    save_every,
    compensated,
    renormalize_every,
    unroll,
    aligned=False,
    time_eps=None,
):
    """`integrate` for `method="euler"` with a constant ω array or `jaxquat.sampled` data, uncompensated
    or compensated (the float32 default), saving the final state or every step; `None` for anything
    else.

    Arguments as validated by `integrate` (q0, dt, t0 arrays; ω an array `(..., 3)` or a callable).
    Nothing here is differentiated through a loop (the final states have derivative rules of their
    own, trajectories store every step anyway), so `integrate`'s `checkpoint` does not apply; `unroll`
    raises the constant-ω steps per kernel above `POWERS_UNROLL`.
    """
    from ._integrate import Sampled

    if method != "euler" or save_every != 1 or num_steps < 1:
        return None
    if isinstance(omega, Sampled):
        if omega.omegas.shape[0] < num_steps or jnp.dtype(omega.omegas.dtype) != jnp.dtype(
            q0.dtype
        ):
            return None
        try:
            batch = np.broadcast_shapes(q0.shape[:-1], omega.omegas.shape[1:-1])
        except ValueError:
            raise ValueError(
                f"`omegas` of shape {tuple(omega.omegas.shape)} (time-major (T, *batch, 3)) do not "
                f"broadcast with `q0` of shape {tuple(q0.shape)}."
            ) from None
    elif callable(omega):
        return None
    else:
        try:
            batch = np.broadcast_shapes(q0.shape[:-1], omega.shape[:-1])
        except ValueError:
            return None
    return _integrate_fast(
        q0,
        omega,
        dt,
        t0,
        batch=tuple(batch),
        num_steps=num_steps,
        frame=frame,
        save=save,
        compensated=bool(compensated),
        renormalize_every=renormalize_every,
        unroll=max(unroll, POWERS_UNROLL),
        on_grid=aligned,
        time_eps=time_eps,
    )


@functools.partial(
    eqx.filter_jit,
)
def _integrate_fast(
    q0,
    omega,
    dt,
    t0,
    *,
    batch,
    num_steps,
    frame,
    save,
    compensated,
    renormalize_every,
    unroll,
    on_grid,
    time_eps,
):
    from ._integrate import Sampled

    dtype = q0.dtype
    q0 = jnp.broadcast_to(q0, batch + (4,))
    time_dtype = jnp.promote_types(jnp.result_type(t0, dt), dtype)
    h = dt.astype(time_dtype).astype(dtype)

    if not isinstance(omega, Sampled):
        # Constant ω: one step rotation, computed once (exact cos/sin, series-switched at 0); the final
        # state steps its powers, `unroll` of them per kernel. When saving every step the loop is bound
        # by the output.
        omega = jnp.broadcast_to(omega.astype(dtype), batch + (3,))
        if save == "all":
            rotation = _exp_soa(_split(omega * h, 3), False)
            minus_one = _step_minus_one(omega, h) if compensated else None
            return _constant_trajectory(
                _split(q0, 4), rotation, num_steps, frame, renormalize_every, minus_one
            )
        return _constant_final(
            q0, omega, h, frame, num_steps, renormalize_every, unroll, compensated
        )

    # Step k uses sample indices[k], by the module's own zero-order-hold rule at the step's start, timed
    # from the first sample (small offsets, not large absolute times; a backward step holds the sample
    # before its start): on the integration grid indices[k] = k, off it the same loop reads the held
    # samples (no gathered copy of the samples either way).
    shift = t0.astype(time_dtype) - jnp.asarray(omega.t0).astype(time_dtype)
    offsets = shift + jnp.arange(num_steps, dtype=time_dtype) * dt.astype(time_dtype)
    indices = omega._index(offsets, jnp.abs(offsets) + jnp.abs(shift), dt < 0, time_eps)
    length = omega.omegas.shape[0]
    # (L, *sample batch, 3) against the bodies' batch: align the batch axes from the right, never
    # the time axis (a plain broadcast_to would pair L with the first body axis).
    samples = omega.omegas
    missing = len(batch) - (samples.ndim - 2)
    samples = samples.reshape((length,) + (1,) * missing + samples.shape[1:])
    samples = jnp.broadcast_to(samples, (length,) + batch + (3,))
    # On the grid step k holds sample k. `on_grid`: `integrate` found dt and t0 equal to the samples'
    # (`_same_value`, the rule of its other methods), whatever the lookup by time would give.
    aligned = on_grid or jnp.all(indices == jnp.arange(num_steps, dtype=indices.dtype))

    def final_state(indices, samples):
        # The run takes the exponential's series in θ² (no sin/cos, which XLA:CPU evaluates slowly)
        # and reports the largest θ² of its steps, a check that rides along in its kernels (a pass of
        # its own over W3's 2.4 GB of samples took 0.17 s, as long as the run). Only if a step was
        # too large for the series, the run is made again with sin/cos (NaN samples take that branch
        # too, and stay NaN). Derivatives come from `_sampled_final`'s rule for the branch taken
        # (so only one adjoint runs); the unrolled run itself is never differentiated.
        constants = lax.stop_gradient((q0, samples, h))
        q, largest = _sampled_run(
            *constants, indices, True, frame, num_steps, renormalize_every, compensated=compensated
        )

        def final(series):
            def run(q_given, q0, samples, h):
                return _sampled_final(
                    q_given if series else None,
                    q0,
                    samples,
                    h,
                    indices,
                    series,
                    frame,
                    num_steps,
                    renormalize_every,
                    compensated,
                )

            return run

        # (The arrays are the cond's operands, not closed over: JAX then passes the samples on to
        # the adjoint as they are, where as a constant they were copied, a second T × N × 3 array.)
        return lax.cond(
            largest <= SERIES_MAX_THETA_SQ, final(True), final(False), q, q0, samples, h
        )

    def trajectory(series, indices, samples):
        # Saving every step: one step per iteration (each writes its row of the output), the step
        # computed by one kernel from a structure-of-arrays carry (compensated: q and its Kahan
        # compensation c, both in the kernel).
        sampled_step = _sampled_step(h, series, frame, compensated)

        def step(carry, x):
            return _fused(sampled_step(carry, x))

        start = _split(q0, 4)
        if compensated:
            start = (start, tuple(jnp.zeros_like(c) for c in start))
        read = _read(samples, indices)
        # (The discarded step T rereads step T − 1's sample, not sample T, which the run does not use.)
        last = num_steps - 1
        return _run_all(
            lambda c, k: step(c, read(jnp.minimum(k, last))),
            start,
            num_steps,
            renormalize_every,
            compensated,
        )

    def trajectory_on_grid(samples):
        # The series needs every step small. Here it is decided before the run, which writes the
        # whole trajectory (a run to discard would double the memory): on the grid the steps use the
        # first num_steps samples, and θ² = |ω|²Δt² ≤ 3 max|ωᵢ|² Δt² needs only their max and min,
        # one vectorised pass (W3's 2.4 GB: 0.17 s, against 0.44 s for max |ω|²).
        # (initial=0: an empty batch has no samples and takes the series; NaN still propagates.)
        used = samples[:num_steps]
        largest = jnp.maximum(jnp.max(used, initial=0.0), -jnp.min(used, initial=0.0))
        small = 3.0 * largest * largest * (h * h) <= SERIES_MAX_THETA_SQ
        return lax.cond(
            small,
            functools.partial(trajectory, True, None),
            functools.partial(trajectory, False, None),
            samples,
        )

    if save == "final":
        if aligned is True:
            return final_state(None, samples)
        return lax.cond(
            aligned,
            functools.partial(final_state, None),
            functools.partial(final_state, indices),
            samples,
        )
    if aligned is True:
        return trajectory_on_grid(samples)
    return lax.cond(
        aligned, trajectory_on_grid, functools.partial(trajectory, False, indices), samples
    )
