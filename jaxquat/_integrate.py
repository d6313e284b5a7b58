r"""Fixed-step orientation integrators over `lax.scan`.

The building blocks, also used by the rigid-body dynamics:

- `lie_step(method, field, t, q, x, h, *, frame)`: one step of a Lie-group method for the coupled system
  $\dot q = \tfrac12 \tilde ω q$ (world) / $\tfrac12 q \tilde ω$ (body), $\dot x = g$, with
  `field(t, q, x) -> (omega, g)`;
- `scan_steps(step_fn, carry, num_steps, *, save, save_every, checkpoint)`: a scan with bounded-memory
  reverse mode (nested scans, the outer body checkpointed, chunks of ≈ √T steps);

and the public `integrate` and `sampled` built on them.

Methods (NUMERICS.md §2): `"euler"` (Lie–Euler = the seed's corrected step with ω at the step start,
order 1, exact for piecewise-constant ω), `"midpoint"` (exponential midpoint / RKMK2, order 2),
`"magnus4"` (fourth-order Magnus with two Gauss points and one commutator; ω must not depend on q),
`"cf4"` (the commutator-free fourth-order method of Celledoni, Marthinsen and Owren 2003), and the
baselines `"naive"` (normalised Euler with the plain rate) and `"rk4"` (classical RK4 in ℝ⁴, then
normalise).
"""

from __future__ import annotations

import functools
import math
import operator
from collections.abc import Callable
from typing import Any

import equinox as eqx
import jax
import jax.extend.core as jex_core
import jax.numpy as jnp
import numpy as np
from jax import lax
from jaxtyping import Array, ArrayLike

from ._algebra import multiply, normalize
from ._kinematics import rate
from ._numerics import (
    as_float_array,
    check_choice,
    check_frame,
    check_trailing,
    cos_half_minus_one,
    cross,
    sinc_half,
    sum_squares,
)
from ._rotation import from_rotvec

LIE_METHODS = ("euler", "midpoint", "magnus4", "cf4")
METHODS = LIE_METHODS + ("naive", "rk4")
# Classical order of each method on the orientation (and of its matching RK scheme on x).
ORDERS = {"euler": 1, "midpoint": 2, "magnus4": 4, "cf4": 4, "naive": 1, "rk4": 4}

_SQRT3 = math.sqrt(3.0)
_GAUSS_1 = 0.5 - _SQRT3 / 6.0
_GAUSS_2 = 0.5 + _SQRT3 / 6.0


# ----------------------------------------------------------------------------------------------------
# Small helpers


def _act(q: Array, r: Array, frame: str) -> Array:
    """r ⊗ q (world frame, left action) or q ⊗ r (body frame, right action)."""
    return multiply(r, q) if frame == "world" else multiply(q, r)


def _rotate_by(q: Array, phi: Array, frame: str) -> Array:
    """exp(φ) ⊗ q (world) or q ⊗ exp(φ) (body) for a rotation vector φ."""
    return _act(q, from_rotvec(phi), frame)


def _rotation_minus_one(phi: Array) -> Array:
    """exp(φ) − 1 = (−2 sin²(|φ|/4), sin(|φ|/2) φ/|φ|) without cancellation (NUMERICS.md §5)."""
    theta_sq = sum_squares(phi)
    return jnp.concatenate(
        [cos_half_minus_one(theta_sq)[..., None], sinc_half(theta_sq)[..., None] * phi], axis=-1
    )


def _tree_axpy(x: Any, h: Array, *terms: tuple[float, Any]) -> Any:
    """x + h Σ cᵢ gᵢ over a pytree x (None stays None), h cast to each leaf's dtype."""
    if x is None:
        return None

    def leaf(xi, *gs):
        xi = jnp.asarray(xi)
        hi = jnp.asarray(h).astype(xi.dtype)
        total = None
        for (c, _), g in zip(terms, gs):
            term = c * jnp.asarray(g).astype(xi.dtype)
            total = term if total is None else total + term
        return xi + hi * total

    return jax.tree_util.tree_map(leaf, x, *(g for _, g in terms))


def _call_field(field: Callable, t, q: Array, x: Any) -> tuple[Array, Any]:
    omega, g = field(t, q, x)
    omega = jnp.asarray(omega)
    if omega.ndim == 0 or omega.shape[-1] != 3:
        raise ValueError(
            f"the angular velocity returned by `field` must have shape (..., 3); got {tuple(omega.shape)}."
        )
    return omega.astype(q.dtype), g


# ----------------------------------------------------------------------------------------------------
# One step


def _lie_parts(method: str, field: Callable, t, q: Array, x: Any, h, frame: str):
    """The rotation vectors of one Lie-method step and the new x.

    Returns `(phis, x1)`: the step is q₁ = exp(φₙ) ⊗ … ⊗ exp(φ₁) ⊗ q (world) or
    q ⊗ exp(φ₁) ⊗ … ⊗ exp(φₙ) (body), i.e. `_rotate_by` applied with φ₁ first.
    """
    hq = jnp.asarray(h).astype(q.dtype)
    if method == "euler":
        f1, g1 = _call_field(field, t, q, x)
        return (hq * f1,), _tree_axpy(x, h, (1.0, g1))
    if method == "midpoint":
        f1, g1 = _call_field(field, t, q, x)
        q_half = _rotate_by(q, (0.5 * hq) * f1, frame)
        x_half = _tree_axpy(x, h, (0.5, g1))
        f2, g2 = _call_field(field, t + 0.5 * h, q_half, x_half)
        return (hq * f2,), _tree_axpy(x, h, (1.0, g2))
    if method == "magnus4":
        if x is not None:
            raise ValueError(
                "`method`='magnus4' needs a state-independent angular velocity and cannot carry an "
                "additional state `x`; use 'cf4'."
            )
        f1, _ = _call_field(field, t + _GAUSS_1 * h, q, x)
        f2, _ = _call_field(field, t + _GAUSS_2 * h, q, x)
        # Left action (world): [A₂, A₁] with A = ½ω̃ gives ω₂ × ω₁; right action (body): ω₁ × ω₂.
        commutator = cross(f2, f1) if frame == "world" else cross(f1, f2)
        phi = (0.5 * hq) * (f1 + f2) + ((_SQRT3 / 12.0) * hq * hq) * commutator
        return (phi,), None
    if method == "cf4":
        # Celledoni, Marthinsen & Owren (2003), the 4-stage commutator-free method; on x: classical RK4.
        f1, g1 = _call_field(field, t, q, x)
        q2 = _rotate_by(q, (0.5 * hq) * f1, frame)
        x2 = _tree_axpy(x, h, (0.5, g1))
        f2, g2 = _call_field(field, t + 0.5 * h, q2, x2)
        q3 = _rotate_by(q, (0.5 * hq) * f2, frame)
        x3 = _tree_axpy(x, h, (0.5, g2))
        f3, g3 = _call_field(field, t + 0.5 * h, q3, x3)
        q4 = _rotate_by(q2, (0.5 * hq) * (2.0 * f3 - f1), frame)
        x4 = _tree_axpy(x, h, (1.0, g3))
        f4, g4 = _call_field(field, t + h, q4, x4)
        first = (hq / 12.0) * (3.0 * f1 + 2.0 * f2 + 2.0 * f3 - f4)
        second = (hq / 12.0) * (-f1 + 2.0 * f2 + 2.0 * f3 + 3.0 * f4)
        x1 = _tree_axpy(x, h, (1.0 / 6.0, g1), (2.0 / 6.0, g2), (2.0 / 6.0, g3), (1.0 / 6.0, g4))
        return (first, second), x1
    raise AssertionError(method)  # pragma: no cover


def _ambient_step(method: str, field: Callable, t, q: Array, x: Any, h, frame: str):
    """The baselines: normalised Euler and RK4 in ℝ⁴ with the plain rate, then normalise."""
    hq = jnp.asarray(h).astype(q.dtype)
    if method == "naive":
        f1, g1 = _call_field(field, t, q, x)
        return normalize(q + hq * rate(q, f1, frame=frame)), _tree_axpy(x, h, (1.0, g1))
    f1, g1 = _call_field(field, t, q, x)
    k1 = rate(q, f1, frame=frame)
    f2, g2 = _call_field(field, t + 0.5 * h, q + (0.5 * hq) * k1, _tree_axpy(x, h, (0.5, g1)))
    k2 = rate(q + (0.5 * hq) * k1, f2, frame=frame)
    f3, g3 = _call_field(field, t + 0.5 * h, q + (0.5 * hq) * k2, _tree_axpy(x, h, (0.5, g2)))
    k3 = rate(q + (0.5 * hq) * k2, f3, frame=frame)
    f4, g4 = _call_field(field, t + h, q + hq * k3, _tree_axpy(x, h, (1.0, g3)))
    k4 = rate(q + hq * k3, f4, frame=frame)
    q1 = normalize(q + (hq / 6.0) * (k1 + 2.0 * k2 + 2.0 * k3 + k4))
    x1 = _tree_axpy(x, h, (1.0 / 6.0, g1), (2.0 / 6.0, g2), (2.0 / 6.0, g3), (1.0 / 6.0, g4))
    return q1, x1


def lie_step(method: str, field: Callable, t, q: Array, x: Any, h, *, frame: str) -> tuple[Array, Any]:
    r"""One step of `method` for $\dot q = \tfrac12 \tilde ω q$ (world) or $\tfrac12 q \tilde ω$ (body),
    coupled with $\dot x = g$, where `field(t, q, x) -> (omega, g)`.

    On q the Lie methods compose exponentials (|q| is kept to round-off); on x (any pytree of arrays,
    or `None` for pure kinematics, then `g` is ignored) the matching Runge–Kutta scheme is used:
    `"euler"` → explicit Euler, `"midpoint"` → explicit midpoint, `"cf4"` and `"rk4"` → classical RK4,
    `"naive"` → explicit Euler (NUMERICS.md §2).

    **Arguments:**

    - `method`: `"euler"`, `"midpoint"`, `"magnus4"`, `"cf4"`, `"naive"` or `"rk4"`. `"magnus4"` evaluates
      ω at the two Gauss points with q frozen at the step start, so it is fourth order only for a
      q-independent ω, and it does not accept an `x` (raises `ValueError`).
    - `field`: `field(t, q, x) -> (omega, g)`, ω of shape `(..., 3)` broadcasting with `q`, `g` a pytree
      like `x` (or anything when `x` is `None`).
    - `t`: time at the step start (any float dtype; stage times are `t + c h`).
    - `q`: orientation `(..., 4)`; `x`: the additional state or `None`.
    - `h`: the step size (may be negative).
    - `frame`: `"world"` or `"body"` (the frame ω is expressed in).

    **Returns:** `(q1, x1)`, q₁ in the dtype of `q` (x₁ is `None` when `x` is).
    """
    method = check_choice(method, METHODS, "method")
    frame = check_frame(frame)
    if method in LIE_METHODS:
        phis, x1 = _lie_parts(method, field, t, q, x, h, frame)
        for phi in phis:
            q = _rotate_by(q, phi, frame)
        return q, x1
    return _ambient_step(method, field, t, q, x, h, frame)


def _compensated_step(method: str, field: Callable, t, q: Array, c: Array, h, frame: str):
    """One Lie step in increment form q ← q + δ, δ = (R − 1) ⊗ q, with Kahan compensation `c`."""
    phis, _ = _lie_parts(method, field, t, q, None, h, frame)
    d = _rotation_minus_one(phis[0])
    for phi in phis[1:]:
        # (1 + d₂)(1 + d) − 1 = d₂ + d + d₂d (world; the body frame multiplies on the other side).
        d2 = _rotation_minus_one(phi)
        d = d2 + d + (multiply(d2, d) if frame == "world" else multiply(d, d2))
    delta = _act(q, d, frame)
    y = delta - c
    s = q + y
    c = (s - q) - y
    return s, c


# ----------------------------------------------------------------------------------------------------
# The scan


def _check_count(value, name: str, minimum: int) -> int:
    try:
        value = operator.index(value)
    except TypeError as e:
        raise ValueError(f"`{name}` must be a Python int (static); got {type(value).__name__}.") from e
    if value < minimum:
        raise ValueError(f"`{name}` must be >= {minimum}; got {value}.")
    return value


# Below this many steps a plain scan is used even when checkpointing (its residuals are small).
_PLAIN_SCAN_MAX = 64


def _run(step_fn: Callable, kc, n: int, checkpoint: bool, unroll: int):
    """n steps of (k, carry) -> (k + 1, step_fn(k, carry)), nested and checkpointed for large n."""
    if n == 0:
        return kc

    def one(kc, _):
        k, c = kc
        return (k + 1, step_fn(k, c)), None

    def plain(kc, length):
        return lax.scan(one, kc, None, length=length, unroll=min(unroll, length))[0]

    if not checkpoint or n <= _PLAIN_SCAN_MAX:
        return plain(kc, n)
    chunk_len = math.isqrt(n - 1) + 1  # ⌈√n⌉
    num_chunks, tail = divmod(n, chunk_len)

    @functools.partial(jax.checkpoint, prevent_cse=False)
    def chunk(kc, _):
        return plain(kc, chunk_len), None

    kc = lax.scan(chunk, kc, None, length=num_chunks)[0]
    if tail:
        kc = plain(kc, tail)
    return kc


def scan_steps(
    step_fn: Callable,
    carry: Any,
    num_steps: int,
    *,
    save: str = "all",
    save_every: int = 1,
    checkpoint: bool = True,
    output: Callable | None = None,
    unroll: int = 1,
) -> tuple[Any, Any]:
    """Run `carry -> step_fn(k, carry)` `num_steps` times (k the integer step index, int32) with
    bounded-memory reverse mode.

    With `checkpoint=True` the steps run as nested scans whose outer body is checkpointed (chunks of
    ⌈√n⌉ steps), so reverse mode stores O(√n) carries instead of every step's residuals
    (PERFORMANCE.md); the forward pass is unchanged, the backward pass recomputes each chunk once.
    When saving, each saved block is itself checkpointed, so only the saved carries are stored.

    **Arguments:**

    - `step_fn`: `step_fn(k, carry) -> carry` (same structure, shapes and dtypes).
    - `carry`: the initial pytree.
    - `num_steps`: number of steps (a static Python int ≥ 0).
    - `save`: `"all"` (stack the carry at steps 0, s, 2s, …, num_steps, time-major) or `"final"`.
    - `save_every`: s ≥ 1, must divide `num_steps` when `save="all"`.
    - `checkpoint`: use the bounded-memory structure (no cost in forward mode).
    - `output`: optional `output(carry) -> pytree` selecting what is saved (default: the whole carry).
    - `unroll`: unroll factor of the innermost scans.

    **Returns:** `(final_carry, saved)`; `saved` has a leading axis of `num_steps // save_every + 1` and
    is `None` for `save="final"`.
    """
    save = check_choice(save, ("all", "final"), "save")
    num_steps = _check_count(num_steps, "num_steps", 0)
    save_every = _check_count(save_every, "save_every", 1)
    unroll = _check_count(unroll, "unroll", 1)
    k0 = jnp.asarray(0, jnp.int32)
    if save == "final":
        _, final = _run(step_fn, (k0, carry), num_steps, checkpoint, unroll)
        return final, None
    if num_steps % save_every:
        raise ValueError(
            f"`save_every` must divide `num_steps` when saving; got save_every={save_every}, "
            f"num_steps={num_steps}."
        )
    if output is None:
        output = lambda c: c  # noqa: E731

    def block(kc, _):
        kc = _run(step_fn, kc, save_every, checkpoint, unroll)
        return kc, output(kc[1])

    if checkpoint:
        block = jax.checkpoint(block, prevent_cse=False)
    (_, final), saved = lax.scan(block, (k0, carry), None, length=num_steps // save_every)
    saved = jax.tree_util.tree_map(
        lambda first, rest: jnp.concatenate([jnp.asarray(first)[None], rest], axis=0),
        output(carry),
        saved,
    )
    return final, saved
