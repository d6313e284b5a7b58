r"""Fixed-step orientation integrators over `lax.scan`.

The building blocks, also used by the rigid-body dynamics:

- `lie_step(method, field, t, q, x, h, *, frame)`: one step of a Lie-group method for the coupled system
  $\dot q = \tfrac12 \tilde ω q$ (world) / $\tfrac12 q \tilde ω$ (body), $\dot x = g$, with
  `field(t, q, x) -> (omega, g)`;
- `scan_steps(step_fn, carry, num_steps, *, save, save_every, checkpoint)`: a scan with bounded-memory
  reverse mode (nested scans, the outer body checkpointed, chunks of ≈ √T steps);

and the public `integrate` and `sampled` built on them.

Methods (docs/numerics.md §2): `"euler"` (Lie–Euler = the seed's corrected step with ω at the step start,
order 1, exact for piecewise-constant ω), `"midpoint"` (exponential midpoint / RKMK2, order 2),
`"magnus4"` (fourth-order Magnus with two Gauss points and one commutator; ω must not depend on q),
`"magnus6"` (sixth-order Magnus with three Gauss points and three commutators; ω must not depend on q),
`"magnus8"` (eighth-order Magnus with four Gauss points and ten commutators; ω must not depend on q),
`"cf4"` (the commutator-free fourth-order method of Celledoni, Marthinsen and Owren 2003), and the
baselines `"naive"` (normalised Euler with the plain rate) and `"rk4"` (classical RK4 in ℝ⁴, then
normalise).
"""

from __future__ import annotations

import fractions
import functools
import math
from collections.abc import Callable
from typing import Any

import equinox as eqx
import jax
import jax.extend.core as jex_core
import jax.numpy as jnp
import numpy as np
from jax import lax
from jaxtyping import Array, ArrayLike

from ._algebra import multiply, unit_quaternion
from ._fastpath import integrate_fast
from ._kinematics import rate
from ._numerics import (
    as_float_array,
    check_callable,
    check_choice,
    check_frame,
    check_trailing,
    compensated_add as _compensated_add,
    cos_half_minus_one,
    cross,
    integer_value,
    is_tracer,
    reusable_callable,
    sinc_half,
    sum_squares,
)
from ._rotation import from_rotvec
from ._sharding import settled

LIE_METHODS = ("euler", "midpoint", "magnus4", "magnus6", "magnus8", "cf4")
# The Magnus methods evaluate ω at Gauss points with q frozen: ω must not depend on q.
MAGNUS_METHODS = ("magnus4", "magnus6", "magnus8")
METHODS = LIE_METHODS + ("naive", "rk4")
# Classical order of each method on the orientation (and of its matching RK scheme on x).
ORDERS = {
    "euler": 1,
    "midpoint": 2,
    "magnus4": 4,
    "magnus6": 6,
    "magnus8": 8,
    "cf4": 4,
    "naive": 1,
    "rk4": 4,
}

_SQRT3 = math.sqrt(3.0)
_GAUSS_1 = 0.5 - _SQRT3 / 6.0
_GAUSS_2 = 0.5 + _SQRT3 / 6.0
_SQRT15 = math.sqrt(15.0)
# Four-point Gauss–Legendre on [0, 1]: nodes ½ ∓ v₁, ½ ∓ v₂ with weights w₁/2 (outer), w₂/2 (inner).
_GL4_OUTER = 0.5 * math.sqrt((3.0 + 2.0 * math.sqrt(6.0 / 5.0)) / 7.0)
_GL4_INNER = 0.5 * math.sqrt((3.0 - 2.0 * math.sqrt(6.0 / 5.0)) / 7.0)
_GL4_SPREAD = math.sqrt(5.0 / 6.0) / 6.0  # w₁ = ½ − spread, w₂ = ½ + spread
# The stage times t + c·h at which each method calls the field, in call order.
_STAGE_FRACTIONS = {
    "euler": (0.0,),
    "naive": (0.0,),
    "midpoint": (0.0, 0.5),
    "magnus4": (_GAUSS_1, _GAUSS_2),
    "magnus6": (0.5 - _SQRT15 / 10.0, 0.5, 0.5 + _SQRT15 / 10.0),
    "magnus8": (0.5 - _GL4_OUTER, 0.5 - _GL4_INNER, 0.5 + _GL4_INNER, 0.5 + _GL4_OUTER),
    "cf4": (0.0, 0.5, 0.5, 1.0),
    "rk4": (0.0, 0.5, 0.5, 1.0),
}


# ----------------------------------------------------------------------------------------------------
# Small helpers


def _act(q: Array, r: Array, frame: str) -> Array:
    """r ⊗ q (world frame, left action) or q ⊗ r (body frame, right action)."""
    return multiply(r, q) if frame == "world" else multiply(q, r)


def _rotate_by(q: Array, phi: Array, frame: str) -> Array:
    """exp(φ) ⊗ q (world) or q ⊗ exp(φ) (body) for a rotation vector φ."""
    return _act(q, from_rotvec(phi), frame)


def _rotation_minus_one(phi: Array) -> Array:
    """exp(φ) − 1 = (−2 sin²(|φ|/4), sin(|φ|/2) φ/|φ|) without cancellation (docs/numerics.md §5)."""
    theta_sq = sum_squares(phi)
    return jnp.concatenate(
        [cos_half_minus_one(theta_sq)[..., None], sinc_half(theta_sq)[..., None] * phi], axis=-1
    )


def _tree_axpy(x: Any, h: Array, *terms: tuple[float, Any], increment: bool = False) -> Any:
    """x + h Σ cᵢ gᵢ over a pytree x (None stays None), h cast to each leaf's dtype; with
    `increment`, the increment h Σ cᵢ gᵢ alone (for a compensated sum)."""
    if x is None:
        return None

    def leaf(xi, *gs):
        xi = jnp.asarray(xi)
        hi = jnp.asarray(h).astype(xi.dtype)
        total = None
        for (c, _), g in zip(terms, gs, strict=True):
            term = c * jnp.asarray(g).astype(xi.dtype)
            total = term if total is None else total + term
        return hi * total if increment else xi + hi * total

    return jax.tree_util.tree_map(leaf, x, *(g for _, g in terms))


def _call_field(field: Callable, t, q: Array, x: Any) -> tuple[Array, Any]:
    omega, g = field(t, q, x)
    omega = jnp.asarray(omega)
    if omega.ndim == 0 or omega.shape[-1] != 3:
        raise ValueError(
            f"the angular velocity returned by `field` must have shape (..., 3); got {tuple(omega.shape)}."
        )
    return omega.astype(q.dtype), g


def magnus6_exponent(u1: Array, u2: Array, u3: Array, frame: str) -> Array:
    """The sixth-order Magnus exponent Ω (a rotation vector) from uᵢ = hω(tₙ + cᵢh) at the three Gauss
    points (`_STAGE_FRACTIONS["magnus6"]`): Blanes, Casas, Oteo & Ros (2009), Phys. Rep. 470, §5.2,
    α₁ = u₂, α₂ = (√15/3)(u₃ − u₁), α₃ = (10/3)(u₃ − 2u₂ + u₁), C₁ = [α₁, α₂],
    C₂ = −[α₁, 2α₃ + C₁]/60, Ω = α₁ + α₃/12 + [−20α₁ − α₃ + C₁, α₂ + C₂]/240. The bracket of rotation
    vectors is a × b for the left action (world frame), b × a for the right (body frame). Written as
    α₁ plus corrections, so a constant ω gives exactly hω."""

    def bracket(a, b):
        return cross(a, b) if frame == "world" else cross(b, a)

    a1 = u2
    a2 = (_SQRT15 / 3.0) * (u3 - u1)
    a3 = (10.0 / 3.0) * ((u3 - u2) - (u2 - u1))
    c1 = bracket(a1, a2)
    c2 = bracket(a1, 2.0 * a3 + c1) * (-1.0 / 60.0)
    return a1 + (a3 * (1.0 / 12.0) + bracket(-20.0 * a1 - a3 + c1, a2 + c2) * (1.0 / 240.0))


def magnus8_exponent(u1: Array, u2: Array, u3: Array, u4: Array, frame: str) -> Array:
    """The eighth-order Magnus exponent Ω (a rotation vector) from uᵢ = hω(tₙ + cᵢh) at the four Gauss
    points (`_STAGE_FRACTIONS["magnus8"]`, nodes ½ ∓ v₁, ½ ∓ v₂ with weights w₁/2, w₂/2): Blanes, Casas
    & Ros (2000), BIT 40, 434–450, the order-8 scheme (ten brackets, each a cross product), in the moments
    B₀ = ½(w₁(u₁ + u₄) + w₂(u₂ + u₃)), B₁ = ½(v₁w₁(u₄ − u₁) + v₂w₂(u₃ − u₂)),
    B₂ = ½(v₁²w₁(u₁ + u₄) + v₂²w₂(u₂ + u₃)), B₃ = ½(v₁³w₁(u₄ − u₁) + v₂³w₂(u₃ − u₂)):

        Q₁ = [−38B₀/5 + 24B₂, B₃],  Q₂ = [63B₀/5 − 84B₂, −5B₁/28 + B₃],
        Q₃ = [19B₀/28 − 15B₂/7, [B₀, B₂ + 61Q₁/588 − Q₂/12]],  Q₄ = [B₃, 20Q₁/7 + 10Q₂],
        Q₅ = [−6025B₀/4116 + 2875B₂/343, [B₂, Q₁]],  Q₆ = [B₃, 20(Q₃ + Q₄)/7 + 820Q₅/189],
        Q₇ = −[B₀, [B₀, Q₃ − Q₄/3 + Q₅]]/42,         Ω = B₀ + Q₁ + … + Q₇

    (the powers of h of the paper are absorbed into the uᵢ). The bracket is a × b (world frame) or
    b × a (body frame), as in `magnus6_exponent`. For a constant ω every bracket vanishes exactly
    (B₁ = B₃ = 0, and B₂ enters [B₀, ·] only through its part off the line of B₀), so Ω = hω to the
    last bit, as for the other Magnus methods."""

    # Written on component tuples (structure of arrays), with no slice or stack per bracket.
    def vec(u):
        return (u[..., 0], u[..., 1], u[..., 2])

    def comb(*terms):  # Σ cᵢ aᵢ
        return tuple(sum(c * a[i] for c, a in terms) for i in range(3))

    def bracket(a, b):
        if frame != "world":
            a, b = b, a
        return (a[1] * b[2] - a[2] * b[1], a[2] * b[0] - a[0] * b[2], a[0] * b[1] - a[1] * b[0])

    v1, v2, spread = _GL4_OUTER, _GL4_INNER, _GL4_SPREAD
    w1, w2 = 0.5 - spread, 0.5 + spread
    u1, u2, u3, u4 = vec(u1), vec(u2), vec(u3), vec(u4)
    outer, inner = comb((1.0, u1), (1.0, u4)), comb((1.0, u2), (1.0, u3))
    outer_d, inner_d = comb((1.0, u4), (-1.0, u1)), comb((1.0, u3), (-1.0, u2))
    total, spread_d = comb((1.0, outer), (1.0, inner)), comb((1.0, inner), (-1.0, outer))
    b0 = comb((0.25, total), (0.5 * spread, spread_d))
    b1 = comb((0.5 * v1 * w1, outer_d), (0.5 * v2 * w2, inner_d))
    b3 = comb((0.5 * v1**3 * w1, outer_d), (0.5 * v2**3 * w2, inner_d))
    # B₂ = κB₀ + d₂, κ = 4α, with d₂ = α(Σuᵢ − 4B₀) + β·spread_d = 0 exactly when the four rates are
    # equal (then 4B₀ = Σuᵢ exactly). Written as αΣuᵢ − κB₀ it was not under jit: XLA contracts it
    # into a fused multiply-add that keeps κB₀'s rounding (|Ω − hω| 4e-6 at |hω| = 10 in float32).
    alpha = 0.25 * (v1 * v1 * w1 + v2 * v2 * w2)
    beta = 0.25 * (v2 * v2 * w2 - v1 * v1 * w1)
    kappa = 4.0 * alpha
    d2 = comb((alpha, comb((1.0, total), (-4.0, b0))), (beta, spread_d))
    b2 = comb((kappa, b0), (1.0, d2))
    q1 = bracket(comb((-38.0 / 5.0, b0), (24.0, b2)), b3)
    q2 = bracket(comb((63.0 / 5.0, b0), (-84.0, b2)), comb((-5.0 / 28.0, b1), (1.0, b3)))
    inner_bracket = bracket(b0, comb((1.0, d2), (61.0 / 588.0, q1), (-1.0 / 12.0, q2)))
    q3 = bracket(comb((19.0 / 28.0, b0), (-15.0 / 7.0, b2)), inner_bracket)
    q4 = bracket(b3, comb((20.0 / 7.0, q1), (10.0, q2)))
    q5 = bracket(comb((-6025.0 / 4116.0, b0), (2875.0 / 343.0, b2)), bracket(b2, q1))
    q6 = bracket(b3, comb((20.0 / 7.0, q3), (20.0 / 7.0, q4), (820.0 / 189.0, q5)))
    q7 = bracket(b0, bracket(b0, comb((1.0, q3), (-1.0 / 3.0, q4), (1.0, q5))))
    corrections = comb(
        (1.0, q1), (1.0, q2), (1.0, q3), (1.0, q4), (1.0, q5), (1.0, q6), (-1.0 / 42.0, q7)
    )
    # Assembled as Σᵢ Ωᵢ eᵢ, not stacked: XLA:CPU fuses a stack into one kernel that branches on the
    # output component and runs the whole bracket chain, unvectorised, once per component (N = 2·10⁴
    # bodies: 5.9 ms; with a `cross` per bracket 1.2 ms; as this sum 0.21 ms; one body, 52 steps of
    # the W4 coning motion: 50–56 µs stacked, 31–32 µs as this sum). Exact: the other terms are
    # products with 0.
    omega = [b0[i] + corrections[i] for i in range(3)]
    basis = jnp.eye(3, dtype=omega[0].dtype)[(slice(None),) + (None,) * omega[0].ndim]  # (3, 1…, 3)
    return sum(omega[i][..., None] * basis[i] for i in range(3))


def _stage_rates(
    field: Callable, t, h, q: Array, fractions: tuple[float, ...]
) -> tuple[Array, ...]:
    """ω at the times t + cᵢh with q frozen (the Magnus methods' Gauss points), as one vmapped
    evaluation: XLA:CPU runs one batched set of kernels instead of one set per point."""
    times = jnp.stack([t + c * h for c in fractions])
    rates = jax.vmap(lambda s: _call_field(field, s, q, None)[0])(times)
    return tuple(rates[i] for i in range(len(fractions)))


# ----------------------------------------------------------------------------------------------------
# One step


def _lie_parts(
    method: str, field: Callable, t, q: Array, x: Any, h, frame: str, *, x_increment: bool = False
):
    """The rotation vectors of one Lie-method step and the new x (with `x_increment`, x₁ − x as the
    method forms it, for a compensated sum).

    Returns `(phis, x1)`: the step is q₁ = exp(φₙ) ⊗ … ⊗ exp(φ₁) ⊗ q (world) or
    q ⊗ exp(φ₁) ⊗ … ⊗ exp(φₙ) (body), i.e. `_rotate_by` applied with φ₁ first.
    """
    hq = jnp.asarray(h).astype(q.dtype)
    if method == "euler":
        f1, g1 = _call_field(field, t, q, x)
        return (hq * f1,), _tree_axpy(x, h, (1.0, g1), increment=x_increment)
    if method == "midpoint":
        f1, g1 = _call_field(field, t, q, x)
        q_half = _rotate_by(q, (0.5 * hq) * f1, frame)
        x_half = _tree_axpy(x, h, (0.5, g1))
        f2, g2 = _call_field(field, t + 0.5 * h, q_half, x_half)
        return (hq * f2,), _tree_axpy(x, h, (1.0, g2), increment=x_increment)
    if method == "magnus4":
        if x is not None:
            raise ValueError(
                "`method`='magnus4' needs a state-independent angular velocity and cannot carry an "
                "additional state `x`; use 'cf4'."
            )
        f1, f2 = _stage_rates(field, t, h, q, _STAGE_FRACTIONS["magnus4"])
        # Left action (world): [A₂, A₁] with A = ½ω̃ gives ω₂ × ω₁; right action (body): ω₁ × ω₂.
        # h ω₁ × h ω₂, not h²·(ω₁ × ω₂): ω₁ × ω₂ overflowed float32 from |ω| ≈ 2e19 with h|ω| ≈ 1.
        g1, g2 = hq * f1, hq * f2
        commutator = cross(g2, g1) if frame == "world" else cross(g1, g2)
        phi = 0.5 * (g1 + g2) + (_SQRT3 / 12.0) * commutator
        return (phi,), None
    if method == "magnus6":
        if x is not None:
            raise ValueError(
                "`method`='magnus6' needs a state-independent angular velocity and cannot carry an "
                "additional state `x`; use 'cf4'."
            )
        f1, f2, f3 = _stage_rates(field, t, h, q, _STAGE_FRACTIONS["magnus6"])
        phi = magnus6_exponent(hq * f1, hq * f2, hq * f3, frame)
        return (phi,), None
    if method == "magnus8":
        if x is not None:
            raise ValueError(
                "`method`='magnus8' needs a state-independent angular velocity and cannot carry an "
                "additional state `x`; use 'cf4'."
            )
        f1, f2, f3, f4 = _stage_rates(field, t, h, q, _STAGE_FRACTIONS["magnus8"])
        phi = magnus8_exponent(hq * f1, hq * f2, hq * f3, hq * f4, frame)
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
        # (h/12)(3F₁ + 2F₂ + 2F₃ − F₄) and (h/12)(−F₁ + 2F₂ + 2F₃ + 3F₄), written as (h/2)F₁ plus
        # stage differences: exact halves for constant ω, which keeps float32 round-off unbiased.
        d2, d3, d4 = f2 - f1, f3 - f1, f4 - f1
        half = (0.5 * hq) * f1
        first = half + (hq / 12.0) * (2.0 * d2 + 2.0 * d3 - d4)
        second = half + (hq / 12.0) * (2.0 * d2 + 2.0 * d3 + 3.0 * d4)
        weights = ((1.0 / 6.0, g1), (2.0 / 6.0, g2), (2.0 / 6.0, g3), (1.0 / 6.0, g4))
        return (first, second), _tree_axpy(x, h, *weights, increment=x_increment)
    raise AssertionError(method)  # pragma: no cover


def _ambient_step(method: str, field: Callable, t, q: Array, x: Any, h, frame: str):
    """The baselines: normalised Euler and RK4 in ℝ⁴ with the plain rate, then normalise."""
    hq = jnp.asarray(h).astype(q.dtype)
    if method == "naive":
        f1, g1 = _call_field(field, t, q, x)
        return unit_quaternion(q + hq * rate(q, f1, frame=frame)), _tree_axpy(x, h, (1.0, g1))
    f1, g1 = _call_field(field, t, q, x)
    k1 = rate(q, f1, frame=frame)
    f2, g2 = _call_field(field, t + 0.5 * h, q + (0.5 * hq) * k1, _tree_axpy(x, h, (0.5, g1)))
    k2 = rate(q + (0.5 * hq) * k1, f2, frame=frame)
    f3, g3 = _call_field(field, t + 0.5 * h, q + (0.5 * hq) * k2, _tree_axpy(x, h, (0.5, g2)))
    k3 = rate(q + (0.5 * hq) * k2, f3, frame=frame)
    f4, g4 = _call_field(field, t + h, q + hq * k3, _tree_axpy(x, h, (1.0, g3)))
    k4 = rate(q + hq * k3, f4, frame=frame)
    q1 = unit_quaternion(q + (hq / 6.0) * (k1 + 2.0 * k2 + 2.0 * k3 + k4))
    x1 = _tree_axpy(x, h, (1.0 / 6.0, g1), (2.0 / 6.0, g2), (2.0 / 6.0, g3), (1.0 / 6.0, g4))
    return q1, x1


def lie_step(
    method: str, field: Callable, t, q: Array, x: Any, h, *, frame: str
) -> tuple[Array, Any]:
    r"""One step of `method` for $\dot q = \tfrac12 \tilde ω q$ (world) or $\tfrac12 q \tilde ω$ (body),
    coupled with $\dot x = g$, where `field(t, q, x) -> (omega, g)`.

    On q the Lie methods compose exponentials (|q| is kept to round-off); on x (any pytree of arrays,
    or `None` for pure kinematics, then `g` is ignored) the matching Runge–Kutta scheme is used:
    `"euler"` → explicit Euler, `"midpoint"` → explicit midpoint, `"cf4"` and `"rk4"` → classical RK4,
    `"naive"` → explicit Euler (docs/numerics.md §2).

    **Arguments:**

    - `method`: `"euler"`, `"midpoint"`, `"magnus4"`, `"magnus6"`, `"magnus8"`, `"cf4"`, `"naive"` or
      `"rk4"`. The Magnus methods evaluate ω at the Gauss points with q frozen at the step start, so
      they reach their order only for a q-independent ω, and they do not accept an `x` (raise
      `ValueError`).
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


def long_run_options(method: str, dtype, compensated, renormalize_every) -> tuple[bool, int | None]:
    """Validate `compensated` (None: on for a Lie method with a float32 or float16 state) and
    `renormalize_every` (a static int ≥ 1, or None) as `integrate` takes them."""
    if renormalize_every is not None:
        renormalize_every = _check_count(renormalize_every, "renormalize_every", 1)
    compensated = _check_flag(compensated, "compensated", allow_none=True)
    if compensated is None:
        compensated = method in LIE_METHODS and jnp.dtype(dtype).itemsize < 8
    elif compensated and method not in LIE_METHODS:
        raise ValueError(
            f"`compensated`=True needs a Lie method ({', '.join(LIE_METHODS)}); got method={method!r}."
        )
    return bool(compensated), renormalize_every


def _compensated_step(method: str, field: Callable, t, q: Array, c: Array, h, frame: str):
    """One Lie step in increment form q ← q + δ, δ = (R − 1) ⊗ q, with Kahan compensation `c`."""
    q, _, (c, _) = compensated_lie_step(method, field, t, q, None, (c, None), h, frame=frame)
    return q, c


def compensated_lie_step(
    method: str, field: Callable, t, q: Array, x: Any, c: tuple[Array, Any], h, *, frame: str
) -> tuple[Array, Any, tuple[Array, Any]]:
    """`lie_step` for a Lie method in the float32 long-run mode (docs/numerics.md §5): q advanced in
    increment form q ← q + δ, δ = (R − 1) ⊗ q, and x ← x + Δx as the method forms Δx, both by Kahan
    summation with the running compensations `c = (c_q, c_x)` (`c_x` a pytree like x, None when x
    is). Returns `(q1, x1, c1)`."""
    c_q, c_x = c
    phis, dx = _lie_parts(method, field, t, q, x, h, frame, x_increment=True)
    d = _rotation_minus_one(phis[0])
    for phi in phis[1:]:
        # (1 + d₂)(1 + d) − 1 = d₂ + d + d₂d (world; the body frame multiplies on the other side).
        d2 = _rotation_minus_one(phi)
        d = d2 + d + (multiply(d2, d) if frame == "world" else multiply(d, d2))
    q, c_q = _compensated_add(q, _act(q, d, frame), c_q)
    if x is None:
        return q, None, (c_q, None)
    leaves, structure = jax.tree_util.tree_flatten(x)
    pairs = [
        _compensated_add(*leaf)
        for leaf in zip(
            leaves, structure.flatten_up_to(dx), structure.flatten_up_to(c_x), strict=True
        )
    ]
    x = structure.unflatten([pair[0] for pair in pairs])
    c_x = structure.unflatten([pair[1] for pair in pairs])
    return q, x, (c_q, c_x)


def renormalized_when_due(index, q: Array, c: Array | None, every: int) -> tuple[Array, Any]:
    """q/|q| after global step `index` when `(index + 1) % every == 0` (and the Kahan compensation
    `c`, if any, reset); otherwise (q, c) unchanged.

    A conditional, not a select: the norm is taken only when due (a select takes it, and a division,
    every step: 2.3x the cost of a float64 Lie–Euler step, 3.6x in float32), and a zero body
    (padding) is not normalised between renormalisations (q/|q| = NaN there, whose derivative times
    a zero cotangent made every gradient NaN when a select computed it)."""
    due = (index + 1) % every == 0

    def renormalize(qc):
        q, c = qc
        return unit_quaternion(q), None if c is None else jnp.zeros_like(c)

    return lax.cond(due, renormalize, lambda qc: qc, (q, c))


# ----------------------------------------------------------------------------------------------------
# The scan


def _check_count(value, name: str, minimum: int) -> int:
    """A static integer ≥ `minimum` (bool is rejected: `True` is not a count)."""
    if isinstance(value, (bool, np.bool_)):
        raise ValueError(f"`{name}` must be a Python int (static); got {value!r} (a bool).")
    count = integer_value(value)
    if count is None:
        raise ValueError(f"`{name}` must be a Python int (static); got {type(value).__name__}.")
    value = count
    if value < minimum:
        raise ValueError(f"`{name}` must be >= {minimum}; got {value}.")
    return value


def _check_steps(num_steps, save: str, save_every) -> tuple[int, int]:
    """`num_steps` ≥ 0 and `save_every` ≥ 1 static ints (not bools); `save_every` divides `num_steps`
    when saving every state."""
    num_steps = _check_count(num_steps, "num_steps", 0)
    save_every = _check_count(save_every, "save_every", 1)
    if save == "all" and num_steps % save_every:
        raise ValueError(
            f"`save_every` must divide `num_steps`; got save_every={save_every}, num_steps={num_steps}."
        )
    return num_steps, save_every


def _check_flag(value, name: str, *, allow_none: bool = False) -> bool | None:
    """A static Python bool (or `None` where that means automatic); anything else is a `ValueError`."""
    if value is None and allow_none:
        return None
    if isinstance(value, (bool, np.bool_)):
        return bool(value)
    expected = "True, False or None" if allow_none else "True or False"
    raise ValueError(f"`{name}` must be {expected} (a static Python bool); got {value!r}.")


# Below this many steps a plain scan is used even when checkpointing (its residuals are small).
_PLAIN_SCAN_MAX = 64


def _leading_split(xs: Any, sizes: tuple[int, ...]) -> Any:
    """Reshape the leading axis (of length prod(sizes)) of every leaf of `xs` into `sizes`."""
    if xs is None:
        return None
    return jax.tree_util.tree_map(lambda a: a.reshape(sizes + a.shape[1:]), xs)


def _leading_slice(xs: Any, start: int, stop: int) -> Any:
    if xs is None:
        return None
    return jax.tree_util.tree_map(lambda a: a[start:stop], xs)


def _run(step_fn: Callable, kc, n: int, xs: Any, checkpoint: bool, unroll: int):
    """n steps of (k, carry) -> (k + 1, step_fn(k, carry[, x])), nested and checkpointed for large n.

    `xs` (or `None`) holds per-step inputs with leading axis n.
    """
    if n == 0:
        return kc

    def one(kc, x):
        k, c = kc
        c = step_fn(k, c) if xs is None else step_fn(k, c, x)
        return (k + 1, c), None

    def plain(kc, xs, length):
        return lax.scan(one, kc, xs, length=length, unroll=min(unroll, length))[0]

    if not checkpoint or n <= _PLAIN_SCAN_MAX:
        return plain(kc, xs, n)
    chunk_len = math.isqrt(n - 1) + 1  # ⌈√n⌉
    num_chunks, tail = divmod(n, chunk_len)

    @functools.partial(jax.checkpoint, prevent_cse=False)
    def chunk(kc, xs_chunk):
        return plain(kc, xs_chunk, chunk_len), None

    head = _leading_split(_leading_slice(xs, 0, num_chunks * chunk_len), (num_chunks, chunk_len))
    kc = lax.scan(chunk, kc, head, length=num_chunks)[0]
    if tail:
        kc = plain(kc, _leading_slice(xs, num_chunks * chunk_len, n), tail)
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
    xs: Any = None,
) -> tuple[Any, Any]:
    """Run `carry -> step_fn(k, carry)` `num_steps` times (k the integer step index, int32) with
    bounded-memory reverse mode.

    With `checkpoint=True` the steps run as nested scans whose outer body is checkpointed (chunks of
    ⌈√n⌉ steps), so reverse mode stores O(√n) carries instead of every step's residuals
    (benchmarks/README.md); the forward pass is unchanged, the backward pass recomputes each chunk once.
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
    - `xs`: optional per-step inputs, a pytree of arrays with leading axis `num_steps`; then the step is
      `step_fn(k, carry, xs[k])`. Reverse mode returns their cotangents stacked (O(num_steps)), where a
      closed-over array indexed by k would accumulate a full-size cotangent on every step.

    **Returns:** `(final_carry, saved)`; `saved` has a leading axis of `num_steps // save_every + 1` and
    is `None` for `save="final"`.
    """
    save = check_choice(save, ("all", "final"), "save")
    num_steps = _check_count(num_steps, "num_steps", 0)
    save_every = _check_count(save_every, "save_every", 1)
    unroll = _check_count(unroll, "unroll", 1)
    checkpoint = _check_flag(checkpoint, "checkpoint")
    if output is not None and not callable(output):
        raise ValueError(f"`output` must be a callable output(carry) or None; got {output!r}.")
    k0 = jnp.asarray(0, jnp.int32)
    if num_steps:
        # Under a mesh of explicit axes, a carry that one step shards (a shared q₀ turned by a
        # sharded ω) starts out sharded as well.
        def first_step(c):
            if xs is None:
                return step_fn(k0, c)
            return step_fn(k0, c, jax.tree_util.tree_map(lambda a: a[0], xs))

        carry = settled(first_step, carry)
    if save == "final":
        _, final = _run(step_fn, (k0, carry), num_steps, xs, checkpoint, unroll)
        return final, None
    if num_steps % save_every:
        raise ValueError(
            f"`save_every` must divide `num_steps` when saving; got save_every={save_every}, "
            f"num_steps={num_steps}."
        )
    if output is None:
        output = lambda c: c  # noqa: E731

    def block(kc, xs_block):
        kc = _run(step_fn, kc, save_every, xs_block, checkpoint, unroll)
        return kc, output(kc[1])

    if checkpoint:
        block = jax.checkpoint(block, prevent_cse=False)
    num_blocks = num_steps // save_every
    xs_blocks = _leading_split(xs, (num_blocks, save_every))
    (_, final), saved = lax.scan(block, (k0, carry), xs_blocks, length=num_blocks)
    saved = jax.tree_util.tree_map(
        lambda first, rest: jnp.concatenate([jnp.asarray(first)[None], rest], axis=0),
        output(carry),
        saved,
    )
    return final, saved


# ----------------------------------------------------------------------------------------------------
# Angular-velocity sources


class Sampled(eqx.Module):
    r"""Piecewise-constant angular velocity from samples: ω(t) = `omegas[k]` on
    $[t_0 + kΔt,\ t_0 + (k+1)Δt)$ (a zero-order hold). Build it with `jaxquat.sampled`.

    A callable PyTree (`equinox.Module`): `integrate` differentiates through `omegas`, `dt` and `t0`.
    Before `t0` the first sample is held, after the last interval the last one.
    """

    omegas: Array
    dt: Array
    t0: Array

    def __call__(self, t, q=None) -> Array:
        """ω at time `t`, shape `t.shape + omegas.shape[1:]` (`q` is ignored)."""
        t = jnp.asarray(t)
        index = self._index(t - self.t0, jnp.abs(t) + jnp.abs(self.t0), False)
        if index.ndim:  # times of any shape, as `AngularVelocityCurve` takes them
            return jnp.take(self.omegas, index, axis=0)
        return lax.dynamic_index_in_dim(self.omegas, index, axis=0, keepdims=False)

    def _index(self, offset, scale, backward, eps: float | None = None) -> Array:
        """The sample index at `offset` = t − t0 (int32, clipped to the samples), `scale` bounding the
        magnitudes of the times it was computed from. A time t0 + kΔt formed in floating point misses
        the k-th boundary by up to ~3 ε·scale/Δt samples (measured: 1.9 for t0 + kΔt, 3.0 for diffrax's
        t0 + (t1 − t0)·k/n), so a time within 4 ε(1 + scale/Δt) samples of a boundary counts as on it.
        ε is that of the offsets' dtype, or the coarser `eps` of the times they were formed from (a
        float32 Δt of 0.7 is 0.699999988: its steps fall 2e-8·k samples short of a float64 0.7 grid,
        which counts as on it, as `integrate`'s on-grid test `_same_value` has it).
        Forwards a boundary belongs to the interval after it; `backward` (a step going back in time, a
        bool or traced bool) gives it to the interval before, the one that step crosses, so the
        Lie–Euler step at the start of a backward step holds the sample it undoes."""
        s = offset / self.dt
        eps = max(float(jnp.finfo(s.dtype).eps), eps or 0.0)
        margin = 4.0 * eps * (1.0 + scale / jnp.abs(self.dt))
        index = jnp.where(backward, jnp.ceil(s - margin) - 1.0, jnp.floor(s + margin))
        return jnp.clip(index, 0, self.omegas.shape[0] - 1).astype(jnp.int32)

    def _relative(self, shift, backward, eps: float | None = None) -> Callable:
        """ω(τ, q) at the offset τ = t − t0 from the first sample, for integrators that form their times
        as `shift + k·h` (shift = their t0 − this t0): the lookup then carries the round-off of small
        offsets, not of large absolute times (float32 at t ≈ 10³ s resolves only ~6e-5 s)."""

        def omega(offset, q=None):
            index = self._index(offset, jnp.abs(offset) + jnp.abs(shift), backward, eps)
            return lax.dynamic_index_in_dim(self.omegas, index, axis=0, keepdims=False)

        return omega


def sampled(omegas: ArrayLike, dt: ArrayLike, *, t0: ArrayLike = 0.0) -> Sampled:
    """An angular-velocity callable `omega(t, q)` that holds `omegas[k]` on step k (zero-order hold).

    With `integrate(..., dt, method="euler")` on the same grid the integration is exact (to round-off):
    each step is the exact rotation by `omegas[k] * dt`. The interior stages of `"midpoint"`,
    and the Magnus methods see the same sample and are exact too; methods with a stage at the step end (`"cf4"`,
    `"rk4"`) see the next sample there.

    **Arguments:**

    - `omegas`: time-major samples, shape `(T, *batch, 3)` (rad/s). Gradients flow to them.
    - `dt`: the sampling interval (scalar, > 0; checked unless traced).
    - `t0`: the time of the first sample.

    Before `t0` the first sample is held and after the last interval the last one, so a run longer
    than the samples keeps turning at the last sampled ω (check `omegas.shape[0] >= num_steps` if that
    would be a mistake in your data).

    **Backwards and large times.** `integrate` with `dt < 0` holds, at each step's start, the sample of
    the interval the step crosses (the one before the boundary), so a backward Euler run undoes the
    forward one exactly. `integrate` also looks samples up by the time since `t0` (the step number
    times `dt`), not by absolute time, so float32 runs at large t stay exact. Called directly —
    `source(t)`, or by a diffrax solver — the module sees only the absolute time: a boundary belongs to
    the interval after it, and in float32 at |t| ≈ 10³ s times resolve only ~6e-5 s (samples then
    switch up to ~4 ε|t| early). With diffrax, integrate backwards over held samples with a solver whose
    stages are all interior (`Magnus4/6/8`, exact there) — not `LieEuler`, `ExpMidpoint` or
    `NormalizedEuler` (with `corrected_vector_field`), whose first stage sits at the step's start, a
    boundary that then reads the sample after it (ten random samples run back to t0: 0.35 rad off
    with `LieEuler` or `NormalizedEuler`, 3e-16 with `Magnus4`) — and count time from the first
    sample (`t0=0`) in float32.

    **Dense output with diffrax** (`SaveAt(ts=...)`, `sol.evaluate`). The steps of `LieEuler` and
    `ExpMidpoint` on the sampling grid are exact, but their cubic Hermite dense output takes its end
    slope from ω at the step's end, which reads the *next* sample: between the steps it is off by up
    to ≈ 0.15·Δt·|ω_{k+1} − ω_k| (ten N(0, 1) samples, Δt = 0.1: 0.08 rad mid-step, 3e-16 at the
    steps). `Magnus4/6/8` (and `NormalizedEuler` with `corrected_vector_field`, whose dense output is
    the geodesic) are exact between the steps too (3e-16).

    **Reverse mode.** With `integrate`'s default `method="euler"` the gradient w.r.t. `omegas` costs
    O(T) on the sampling grid and off it (each step reads its sample by index, and its cotangent is
    added in place). With the other methods this holds when `integrate` runs on the sampling grid
    (its `dt` and `t0` equal these, as Python numbers or concrete arrays): the samples are then
    scanned over as per-step inputs. Otherwise each step looks its sample up by time, and reverse
    mode adds a full-size cotangent per step (O(T²) for long runs) — sample on the integration grid
    when you differentiate long runs with them.

    **Returns:** a `Sampled` module, `Sampled(t, q) -> omegas[k]`.
    """
    omegas = check_trailing(omegas, 3, "omegas")
    if omegas.ndim < 2 or omegas.shape[0] < 1:
        raise ValueError(
            f"`omegas` must be time-major with shape (T, ..., 3), T >= 1; got {tuple(omegas.shape)}."
        )
    # Python numbers are kept as given: `integrate` can then tell, even under `jit`, that the samples lie
    # on its grid (they carry no gradient anyway). Arrays are used as arrays.
    dt = dt if _is_number(dt) else _check_scalar(dt, "dt")
    t0 = t0 if _is_number(t0) else _check_scalar(t0, "t0")
    if not is_tracer(dt):
        value = float(dt)
        if not (math.isfinite(value) and value > 0):
            raise ValueError(f"`dt` (the sampling interval) must be finite and > 0; got {value}.")
    if not is_tracer(t0) and not math.isfinite(float(t0)):
        raise ValueError(f"`t0` (the time of the first sample) must be finite; got {float(t0)}.")
    return Sampled(omegas, dt, t0)


def _is_number(x) -> bool:
    return isinstance(x, (int, float, np.integer, np.floating)) and not isinstance(x, bool)


def _same_value(a: Array, b: Array, scale: Array) -> bool:
    """Whether two concrete scalars agree to a few ulp of the coarser dtype (False for tracers)."""
    try:
        a_value, b_value, scale_value = float(a), float(b), abs(float(scale))
    except (TypeError, jax.errors.ConcretizationTypeError):
        return False
    eps = max(_eps_of(a), _eps_of(b))
    return abs(a_value - b_value) <= 8.0 * eps * max(abs(a_value), abs(b_value), scale_value)


def _eps_of(x) -> float:
    dtype = x.dtype if hasattr(x, "dtype") else np.float64
    return float(np.finfo(dtype).eps)


def _check_finite(x: Array, name: str) -> Array:
    """`x`, after a ValueError if it is concrete and not finite (a NaN t0 once picked sample 0)."""
    if not is_tracer(x) and not np.isfinite(np.asarray(x)):  # (NumPy: no tracer inside a jit)
        raise ValueError(f"`{name}` must be finite; got {float(x)}.")
    return x


def _check_scalar(x: ArrayLike, name: str) -> Array:
    x = as_float_array(x, name)
    if x.ndim != 0:
        raise ValueError(f"`{name}` must be a scalar; got shape {tuple(x.shape)}.")
    return x


def _check_finite_scalar(x: ArrayLike, name: str) -> Array:
    """`_check_scalar`, then `_check_finite` of `x` as given: under `jit` a Python number or a
    closed-over array is still known, although its conversion to an array is already traced."""
    checked = _check_scalar(x, name)
    _check_finite(x, name)
    return checked


def _band_spacing(
    magnitude: fractions.Fraction, eps: fractions.Fraction, tiny
) -> fractions.Fraction:
    """The spacing of the floating-point numbers in (2ⁿ⁻¹, 2ⁿ], the binade that holds `magnitude`
    (a power of two counts with the numbers below it), in a format with machine epsilon `eps` and
    smallest normal number `tiny` (exact arithmetic)."""
    if magnitude <= tiny:
        return tiny * eps  # subnormal numbers: evenly spaced
    e = magnitude.numerator.bit_length() - magnitude.denominator.bit_length()
    while fractions.Fraction(2) ** e < magnitude:
        e += 1
    while fractions.Fraction(2) ** (e - 1) >= magnitude:
        e -= 1
    return fractions.Fraction(2) ** (e - 1) * eps


def check_times_advance(
    t0,
    dt,
    num_steps: int,
    dtype,
    what: str,
    reads_time: Callable[[jax.ShapeDtypeStruct], bool],
    widen: str,
    method: str,
) -> None:
    """A `ValueError` when the times t0 + k·dt (k = 0..num_steps), formed in `dtype`, need not
    increase and the callable `what` reads them. Far from zero a float's spacing exceeds half a
    step, and rounding then makes consecutive times equal (they stand still, then jump by two
    steps): float32 times at a Unix time t0 = 1.7e9 are 128 s apart; at t0 = 1e20 even float64
    never moves. `widen` is the advice on a wider time dtype (left out when `dtype` has 64 bits
    already); `method` the integrator's,
    whose stage times are `_STAGE_FRACTIONS[method]`.

    Checked only when `t0` and `dt` are concrete (as given: a Python number under `jit` is), `dt`
    ≠ 0 and `num_steps` > 0, with `t0` and `dt` rounded to `dtype` (as the run uses them) and in
    exact arithmetic: the times are t0 + float(k)·dt, so the run's largest magnitude M is that of
    t0, of its end and of num_steps·dt (a run crossing zero). With the spacing S of `dtype` at M,
    the step times increase when S ≤ |dt|/2 (two roundings, each at most half a spacing, cannot
    undo a step), when S ≤ |dt| and every time is exact (|dt| a power of two, t0 a multiple of
    it), and when S < |dt| from t0 = 0 (one rounding of k·dt). A method with stages inside the
    step (c = ½ for midpoint, rk4 and cf4) needs its half steps told apart from the step ends too:
    t_k + ½dt = fl(t_k + fl(½dt)) is a third rounding, so there S < |dt|/5 (the bound that keeps
    t_{k+1} above it), S ≤ |dt|/4 for a power-of-two |dt| (k·dt exact), S ≤ |dt|/2 with exact
    times, or S < |dt|/3 from t0 = 0 (measured: half steps collapsed at |dt|/S up to 3.96 in
    float16 and bfloat16, e.g. float16 t0 = −13.2, dt = 0.0585). Gauss points (Magnus,
    c = ½ ∓ 0.29) still move by up to S/2 near M: those
    runs are accepted, at lower accuracy. Otherwise, and when a time overflows `dtype`,
    `reads_time(t)`, given the abstract time, is asked whether the callable's output depends on t
    (`_depends_on`, which sees into jit, cond, loops and custom derivatives): a damping torque
    −c·ω or an ω(q) never sees the time and is not rejected."""
    if num_steps == 0:
        return
    try:
        t0_value, dt_value = float(t0), float(dt)
    except TypeError:  # traced (jax.errors.ConcretizationTypeError is a TypeError): not checked
        return
    if not (math.isfinite(t0_value) and math.isfinite(dt_value)):
        return  # (the callers' own checks name a non-finite t0 or dt)
    dtype = jnp.dtype(dtype)
    widen = widen if dtype.itemsize < 8 else ""
    info = jnp.finfo(dtype)  # (np.finfo knows no bfloat16)
    with np.errstate(over="ignore", under="ignore"):
        t0_run, dt_run = (float(np.asarray(x, dtype)) for x in (t0_value, dt_value))  # as run
    if dt_run == 0.0:
        return
    largest = float(info.max)
    # A quick pass in float64 for the usual run, far inside the limit (a factor 8 of margin).
    far = abs(t0_run) + num_steps * abs(dt_run)
    if math.isfinite(far) and far * 8.0 * float(info.eps) <= abs(dt_run) and far < largest / 8:
        return

    def reads() -> bool:
        try:
            return bool(reads_time(jax.ShapeDtypeStruct((), dtype)))
        except Exception:  # noqa: BLE001 - the run itself reports a callable that cannot be traced
            return False

    def shown(name: str, given: float, run: float) -> str:
        rounded = f" ({run:.8g} in {dtype})" if run != given and math.isfinite(run) else ""
        return f"`{name}` = {given:g}{rounded}"

    problem = (
        f"so the times t0 + k·dt at which {what} is called cannot all be told apart (they would "
        "stand still, then jump)"
    )
    for name, given, run in [("t0", t0_value, t0_run), ("dt", dt_value, dt_run)]:
        if not math.isfinite(run):
            if reads():
                raise ValueError(
                    f"`{name}` = {given:g} overflows {dtype} (largest {largest:g}), so {what} "
                    f"would be called at infinite times. Use a smaller |{name}|{widen}."
                )
            return
    Fraction = fractions.Fraction
    t0_exact, dt_exact, n = Fraction(t0_run), Fraction(dt_run), num_steps
    end = t0_exact + n * dt_exact
    step = abs(dt_exact)
    magnitude = max(abs(t0_exact), abs(end), n * step)
    eps, tiny = Fraction(float(info.eps)), Fraction(float(info.smallest_normal))
    power_of_two = step.numerator.bit_count() == 1 and step.denominator.bit_count() == 1
    exact_grid = power_of_two and (t0_exact / step).denominator == 1
    inside = any(0.0 < c < 1.0 for c in _STAGE_FRACTIONS[method])  # stages inside the step

    def fine(m: Fraction) -> bool:
        spacing = _band_spacing(m, eps, tiny)
        if inside:  # (the step times and the half steps between them)
            return (
                5 * spacing < step
                or (power_of_two and 4 * spacing <= step)
                or (exact_grid and 2 * spacing <= step)
                or (t0_exact == 0 and 3 * spacing < step)
            )
        return (
            2 * spacing <= step
            or (exact_grid and spacing <= step)
            or (t0_exact == 0 and spacing < step)
        )

    if magnitude <= Fraction(largest) and fine(magnitude):
        return
    if not reads():
        return
    run = f"{shown('t0', t0_value, t0_run)}, {shown('dt', dt_value, dt_run)}"
    rule = f" (method {method!r} evaluates at half steps too, which need a finer spacing)"
    rule = rule if inside else ""
    if magnitude > Fraction(largest):
        raise ValueError(
            f"{run} and `num_steps` = {n:,} reach |t| = {float(magnitude):.6g}, beyond the largest "
            f"{dtype} ({largest:g}), so {what} would be called at infinite times. Split the run "
            f"into shorter runs, each counting time from its own start (with {what} shifted to "
            f"match){widen}."
        )
    first = max(abs(t0_exact), abs(t0_exact + dt_exact))
    if not fine(first):  # the origin is to blame: not even the first step is told apart
        spacing = float(_band_spacing(first, eps, tiny))
        raise ValueError(
            f"{run}: {dtype} times near |t0| are {spacing:.3g} apart, too coarse for steps of "
            f"{dt_run:g}{rule}, {problem}. Count time from a nearer origin (a smaller |t0|, with "
            f"{what} shifted to match){widen}."
        )
    spacing = float(_band_spacing(magnitude, eps, tiny))
    raise ValueError(  # the run's length is to blame
        f"{run} and `num_steps` = {n:,} reach |t| = {float(magnitude):.10g} (counting the "
        f"steps' span n·|dt|), where {dtype} times are {spacing:.3g} apart, too coarse for "
        f"steps of {dt_run:g}{rule}, {problem}. Split the run into shorter runs, each counting "
        f"time from its own start (with {what} shifted to match){widen}."
    )


def _reads_time(fn: Callable, *others) -> Callable[[jax.ShapeDtypeStruct], bool]:
    """For `check_times_advance`: whether `fn(t, *others)` depends on t (`others` taken abstract,
    with their shapes and dtypes; a list or number returned counts as an array)."""

    def call(t, *rest):
        return jax.tree.map(jnp.asarray, fn(t, *rest))

    def reads(t) -> bool:  # (the abstract operands formed only when asked: the usual run is not)
        abstract = [jax.ShapeDtypeStruct(jnp.shape(x), jnp.result_type(x)) for x in others]
        return _depends_on(call, t, *abstract, argnums=(0,))

    return reads


def _check_magnus_omega(omega: Callable, method: str, t, q: Array) -> None:
    """A `ValueError` for a Magnus `method` with an `omega(t, q)` that depends on q (`integrate` and
    `simulate_ensemble`)."""
    if method in MAGNUS_METHODS and _depends_on_q(omega, t, q):
        raise ValueError(
            f"`omega` depends on q, but `method`='{method}' needs a q-independent angular velocity "
            "ω(t) (it is evaluated at the Gauss points with q frozen); use 'cf4' or 'midpoint'."
        )


def _depends_on_q(omega: Callable, t, q: Array) -> bool:
    """Whether the output of `omega(t, q)` depends on q (a conservative data-flow check on its jaxpr)."""
    return _depends_on(lambda q_: omega(t, q_), q)


def _depends_on(fn: Callable, *operands, argnums: tuple[int, ...] | None = None) -> bool:
    """Whether the output of `fn(*operands)` depends on any leaf of the operands (or of those at
    `argnums`): a conservative data-flow check on its jaxpr (operands may be abstract,
    `jax.ShapeDtypeStruct`s; `_forward_dependence`).

    It looks inside nested calls: `jax.jit`, `eqx.filter_jit`, `jax.checkpoint`, `custom_jvp` and
    `custom_vjp` functions (their primal), `lax.cond`/`switch` branches and `lax.scan`/`while_loop`
    bodies that ignore an input do not count as using it. A primitive it does not know counts as
    using all of its inputs (a `pure_callback`, say), and one fed a used input marks the references
    it is given (`jax.new_ref`) as used too. Once a used input has reached a side effect, every
    effect that returns a value (an `io_callback`, before or after it) counts as using it, as the
    first may have stored it. An input multiplied by zero is used; one only printed
    (`jax.debug.print`) is not, as the output does not see it."""
    jaxpr = jax.make_jaxpr(fn)(*operands).jaxpr
    counts = [len(jax.tree.leaves(x)) for x in operands]
    chosen = set(range(len(operands)) if argnums is None else argnums)
    flags = [i in chosen for i, count in enumerate(counts) for _ in range(count)]
    return any(_forward_dependence(jaxpr, flags))


def _is_var(v) -> bool:
    return isinstance(v, jex_core.Var) and not isinstance(v, jex_core.Literal)


def _is_ref(v) -> bool:
    return type(getattr(v, "aval", None)).__name__ == "AbstractRef"


def _returns_effects(eqn) -> bool:
    """Whether an equation has effects that can hand a value back to the computation (an
    `io_callback`, a reference, a call holding one); debug printing and `jax.debug.callback`
    return nothing."""
    return any("Debug" not in type(effect).__name__ for effect in eqn.effects)


def _forward_dependence(jaxpr, dependent_inputs: list[bool], leaked: bool = False) -> list[bool]:
    """Which outputs of `jaxpr` depend on the inputs flagged (forward data flow, equation by
    equation; nested jaxprs by `_equation_dependence`).

    What one effect stores, another may return: an ordered `io_callback` that keeps q and one
    without operands that hands it back, after it in the same call or before it (then it returns
    the previous call's q), or a global `jax.new_ref` read and then written. Once a flagged value
    has reached any effect, the walk is made again with every effect that can return a value
    counted as depending on it (`leaked`). `eqn.effects` includes those of nested jaxprs, so a
    call or loop holding one is taken whole and the nested walks never meet an effect."""
    dependent = {v for v, flag in zip(jaxpr.invars, dependent_inputs, strict=True) if flag}
    leaks = False  # a flagged value reached a side effect, which may have stored it
    for eqn in jaxpr.eqns:
        inputs = [_is_var(v) and v in dependent for v in eqn.invars]
        # (`jax.debug.print` only prints: it stores nothing another effect could hand back.)
        leaks = leaks or (any(inputs) and bool(eqn.effects) and eqn.primitive.name != "debug_print")
        if leaked and _returns_effects(eqn):
            outputs = [True] * len(eqn.outvars)
        elif not any(inputs):
            continue
        else:
            outputs = _equation_dependence(eqn, inputs)
        dependent.update(v for v, flag in zip(eqn.outvars, outputs, strict=True) if flag)
        dependent.update(v for v in eqn.invars if _is_var(v) and _is_ref(v))  # written, maybe
    if leaks and not leaked:
        return _forward_dependence(jaxpr, dependent_inputs, leaked=True)
    return [_is_var(v) and v in dependent for v in jaxpr.outvars]


def _equation_dependence(eqn, inputs: list[bool]) -> list[bool]:
    """Which outputs of one equation depend on its inputs flagged: through the nested jaxpr of a
    call, a cond, a scan or a while loop (to a fixed point over the loop's carry); every output for
    any other primitive, for references among the operands, and whenever the structure is not the
    expected one (a JAX version that changed a primitive's parameters stays conservative)."""
    everything = [True] * len(eqn.outvars)
    params = eqn.params
    if any(_is_ref(v) for v in eqn.invars):
        return everything

    def run(jaxpr, flags):
        jaxpr = getattr(jaxpr, "jaxpr", jaxpr)  # (a ClosedJaxpr or a Jaxpr)
        if len(jaxpr.invars) != len(flags):
            raise ValueError("unexpected structure")
        return _forward_dependence(jaxpr, flags)

    try:
        name = eqn.primitive.name
        if name == "cond":
            if inputs[0]:  # the branch index
                return everything
            outputs = [False] * len(eqn.outvars)
            for branch in params["branches"]:
                outputs = [a or b for a, b in zip(outputs, run(branch, inputs[1:]), strict=True)]
        elif name == "scan":
            consts, carries = params["num_consts"], params["num_carry"]
            carry = inputs[consts : consts + carries]
            while True:
                outputs = run(params["jaxpr"], inputs[:consts] + carry + inputs[consts + carries :])
                merged = [a or b for a, b in zip(carry, outputs[:carries], strict=True)]
                if merged == carry:
                    break
                carry = merged
        elif name == "while":
            cond_consts, body_consts = params["cond_nconsts"], params["body_nconsts"]
            start = cond_consts + body_consts
            carry = inputs[start:]
            while True:
                new = run(params["body_jaxpr"], inputs[cond_consts:start] + carry)
                merged = [a or b for a, b in zip(carry, new, strict=True)]
                if merged == carry:
                    break
                carry = merged
            if any(run(params["cond_jaxpr"], inputs[:cond_consts] + carry)):
                return everything  # the number of iterations depends on the inputs
            outputs = carry
        else:
            inner = next(
                (params[k] for k in ("jaxpr", "call_jaxpr", "fun_jaxpr") if k in params), None
            )
            if inner is None:
                return everything
            outputs = run(inner, inputs)
        if len(outputs) != len(eqn.outvars):
            return everything
        return outputs
    except (KeyError, TypeError, ValueError, AttributeError):
        return everything


def _broadcast_shapes(a: tuple, b: tuple, name: str, received: tuple) -> tuple:
    try:
        return tuple(np.broadcast_shapes(a, b))
    except ValueError as e:
        raise ValueError(
            f"`{name}` must have shape (..., 3) with leading axes broadcasting with q0's {a}; got "
            f"shape {received}."
        ) from e


# ----------------------------------------------------------------------------------------------------
# integrate


def integrate(
    q0: ArrayLike,
    omega: ArrayLike | Callable,
    dt: ArrayLike,
    num_steps: int,
    *,
    frame: str = "world",
    method: str = "euler",
    t0: ArrayLike = 0.0,
    save: str = "all",
    save_every: int = 1,
    compensated: bool | None = None,
    renormalize_every: int | None = 1000,
    checkpoint: bool = True,
    unroll: int = 1,
) -> Array:
    r"""Integrate the orientation $\dot q = \tfrac12 \tilde ω q$ (world) or $\tfrac12 q \tilde ω$ (body)
    with `num_steps` fixed steps of size `dt` over `lax.scan`.

    The default `"euler"` is the seed's corrected scheme (the seed notes' equation quatRateOfChangeCorrected
    followed by renormalisation; README, Sources) computed as the exact exponential step
    $q_{k+1} = \exp(ω(t_k)Δt) ⊗ q_k$ (docs/numerics.md §1): exact for constant and piecewise-constant ω
    at any step size, first order for smoothly varying ω. Times are $t_k = t_0 + kΔt$ with an integer
    step count (no accumulated `t += dt`), in float64 when x64 is enabled.

    | method | order | ω evaluations / step | ω may depend on q |
    |---|---|---|---|
    | `"euler"` | 1 (exact for piecewise-constant ω) | 1 | yes |
    | `"midpoint"` (exponential midpoint, RKMK2) | 2 | 2 | yes |
    | `"magnus4"` (Gauss points + one commutator) | 4 | 2 | no (`ValueError`) |
    | `"magnus6"` (3 Gauss points + 3 commutators) | 6 | 3 | no (`ValueError`) |
    | `"magnus8"` (4 Gauss points + 10 commutators) | 8 | 4 | no (`ValueError`) |
    | `"cf4"` (Celledoni–Marthinsen–Owren 2003) | 4 | 4 | yes |
    | `"naive"` (normalised Euler, plain rate; baseline) | 1 | 1 | yes |
    | `"rk4"` (RK4 in ℝ⁴ + normalise; baseline) | 4 | 4 | yes |

    The naive step turns by 2·atan(|ω|Δt/2) < π per step however fast the body spins (the seed's
    "quarter of the way round the sphere"); RK4 + normalise lags by ≈ θ⁵/1920 per step.

    **Long runs in float32** (`compensated`): the Lie methods then accumulate the increment
    $δ = (R − 1) ⊗ q$ with $R − 1 = (−2\sin^2(θ/4), \sin(θ/2)\,\hat n)$ in Kahan-compensated summation
    and renormalise every `renormalize_every` steps (docs/numerics.md §5): 10⁶ steps of 10⁻³ rad stay within
    ~1e-4 rad instead of 1e-3–1e-2 for plain stepping. The default `None` switches it on for float32
    (and float16) states; the baselines `"naive"` and `"rk4"` do not have it. With `"euler"` and a
    constant ω array or `jaxquat.sampled` ω, the final state in this mode runs on the fast paths
    (kernels of grouped steps, the same derivative rules) as the plain mode does: N = 10⁵ bodies ×
    1,000 steps in 78 ms instead of 1.6 s (sampled) and 17 ms instead of 239 ms (constant), measured
    2026-11-27; so do the whole trajectories (`save="all"`): 112 ms instead of 465 ms for a constant
    ω, 0.37 s instead of 2.0 s for sampled ω.

    **Arguments:**

    - `q0`: initial orientation(s), shape `(*batch, 4)`, unit. It is not normalised for you: the
      exponential methods carry a non-unit q0's norm until the first renormalisation (step
      `renormalize_every`), which scales the state to |q| = 1; `"naive"` and `"rk4"` normalise
      after the first step.
    - `omega`: angular velocity (rad/s, in `frame`): an array `(..., 3)` broadcasting with `q0`'s batch
      (constant in time); a callable `omega(t, q) -> (..., 3)` (a function, or an `equinox.Module` whose
      array fields are differentiated); or `jaxquat.sampled(omegas, dt)` for sampled data.
    - `dt`: the step (scalar; negative integrates backwards). `num_steps`: a static Python int ≥ 0.
    - `frame`: `"world"` or `"body"`. `method`: see the table. `t0`: the initial time (scalar).
    - `save`: `"all"` → `(num_steps // save_every + 1, *batch, 4)` at steps 0, s, 2s, … (time-major,
      including q0); `"final"` → `(*batch, 4)`. `save_every`: s ≥ 1 (with `"all"` it must divide
      `num_steps`; `"final"` does not use it).
    - `compensated`: the float32 long-run mode (above); `None` = automatic.
    - `renormalize_every`: renormalise the Lie methods' state every this many steps (`None`: never).
      The exponential steps keep |q| = 1 to round-off; this removes the slow drift (7e-11 over 10⁶
      float64 steps).
    - `checkpoint`: bounded reverse-mode memory (nested scans, outer body checkpointed, chunks of ≈ √T):
      `jax.grad` through 10⁵ steps × 1,000 bodies stores O(√T) states, not O(T). Not needed (and
      ignored) for the final state of `"euler"` with a constant ω (closed-form derivative) or with
      on-grid or held `sampled` ω (an adjoint that steps back with the inverse rotations): these
      store no states at all.
    - `unroll`: unroll factor of the inner scans (speed only).

    **Returns:** the orientations, in the dtype of `q0`.

    **Gradients** flow to `q0`, `omega` (array, the callable's PyTree parameters, the samples), `dt` and
    `t0`, and are exact at ω = 0: there $∂q_T/∂ω = \tfrac12 TΔt\,[0; I_3]\,q_0$ (world frame, constant ω).
    For `"euler"` with a constant ω array and `save="final"` the derivative is the closed form of
    $d(r^T ⊗ q_0)$, $\dot q_T = (Hζ) ⊗ q_T + r^T ⊗ \dot q_0$ with $ζ = \dot r ⊗ \bar r$ and
    $H = \sum_{m<T} R(r)^m$ formed by doubling: `jax.grad` then costs about one forward pass and stores
    nothing per step.

    **Compilation.** The run is compiled once per shapes, dtypes and options and reused, as by
    `jax.jit`: a repeated call takes milliseconds instead of 0.15–0.3 s. New values of an array ω,
    of `jaxquat.sampled` data and of the arrays inside an `equinox.Module` ω reuse the program. A
    function, bound method or `functools.partial` is keyed by its identity and assumed pure, as
    `jax.jit` assumes: state it reads (a global, an attribute) is read when it is first traced, so
    pass changing values as a Module's arrays, or as a new callable. A callable that does not hash
    (a dataclass with `eq=True`) or a Module holding NumPy arrays or scalars (used as NumPy constants)
    is compiled again at each call.

    **Speed.** `"euler"` with a constant or sampled ω takes a restructured loop (structure-of-arrays
    carry, step rotation hoisted, series exponential for small steps, trajectories formed blockwise);
    see `benchmarks/README.md` for the measurements against SciPy, numpy-quaternion and jaxlie.

    **Errors:** a `ValueError` naming the argument for a bad `method`, `frame`, `save`, `save_every`,
    `num_steps`, `unroll` or `renormalize_every` (static ints; a bool is not accepted), a non-bool
    `checkpoint` / `compensated`, a non-scalar `dt`/`t0`, an `omega` of the wrong shape, a
    q-dependent `omega` with a Magnus method, or an `omega(t, q)` that reads t when its step times
    t0 + k·dt need not increase: far from zero the time dtype's spacing exceeds half a step (float32
    times at a Unix time such as t0 = 1.7e9 are 128 s apart; the message says whether t0 or the
    run's length is to blame; midpoint, rk4 and cf4 need their half steps told apart too, a finer
    spacing). Checked when t0 and dt are concrete; an `omega` whose output does not depend on t (a
    data-flow check that sees into `jax.jit`, `lax.cond`, loops and custom derivatives) is never
    rejected.

    Example:
    ```python
    q = jaxquat.integrate(jaxquat.identity(), jnp.array([0.0, 0.0, jnp.pi]), 0.01, 100, save="final")
    # half a turn about z: q ≈ (0, 0, 0, 1)
    ```
    """
    frame = check_frame(frame)
    method = check_choice(method, METHODS, "method")
    save = check_choice(save, ("all", "final"), "save")
    num_steps, save_every = _check_steps(num_steps, save, save_every)
    unroll = _check_count(unroll, "unroll", 1)
    checkpoint = _check_flag(checkpoint, "checkpoint")
    q0 = check_trailing(q0, 4, "q0")
    compensated, renormalize_every = long_run_options(
        method, q0.dtype, compensated, renormalize_every
    )
    dt_given, t0_given = dt, t0
    dt = _check_finite_scalar(dt, "dt")
    t0 = _check_finite_scalar(t0, "t0")
    if not callable(omega):
        omega = check_trailing(omega, 3, "omega")
    elif not isinstance(omega, Sampled):  # (samples are looked up by the time since their t0)
        # (A callable that cannot be traced, of the wrong arity say, is named by the run itself.)
        time_dtype = jnp.promote_types(jnp.result_type(t0, dt), q0.dtype)
        widen = (
            " or count time in float64 (jax_enable_x64, with t0 and dt Python numbers or float64)"
        )
        reads = _reads_time(omega, q0)
        check_times_advance(
            t0_given, dt_given, num_steps, time_dtype, "`omega(t, q)`", reads, widen, method
        )
    # Samples on the integration grid (same dt and t0, known before tracing) are fed to the scan as
    # per-step inputs: reverse mode then costs O(num_steps) instead of a full-size scatter per step.
    aligned = (
        isinstance(omega, Sampled)
        and _same_value(omega.dt, dt_given, dt_given)
        and _same_value(omega.t0, t0_given, dt_given)
    )
    time_eps = None
    if isinstance(omega, Sampled):
        omega = Sampled(
            omega.omegas,
            _check_scalar(omega.dt, "dt"),
            _check_finite_scalar(omega.t0, "t0"),
        )
        # Sample lookups by time allow the round-off of the coarsest time given (see `Sampled._index`).
        time_eps = max(_eps_of(x) for x in (dt, t0, omega.dt, omega.t0))
        if is_tracer(t0) or is_tracer(omega.t0):
            # A traced non-finite t0 (unchecked) would clip to the first or last sample and give a
            # plausible rotation: the run is NaN instead, as a non-finite input is everywhere else.
            q0 = jnp.where(jnp.isfinite(t0 - omega.t0), q0, jnp.nan)
    # Lie–Euler with a constant or sampled ω takes the restructured loop of `_fastpath` (issue 8).
    fast = integrate_fast(
        q0,
        omega,
        dt,
        t0,
        num_steps=num_steps,
        frame=frame,
        method=method,
        save=save,
        save_every=save_every,
        compensated=bool(compensated),
        renormalize_every=renormalize_every,
        unroll=unroll,
        aligned=aligned,
        time_eps=time_eps,
    )
    if fast is not None:
        return fast
    options = dict(
        aligned=aligned,
        time_eps=time_eps,
        num_steps=num_steps,
        frame=frame,
        method=method,
        save=save,
        save_every=save_every,
        compensated=bool(compensated),
        renormalize_every=renormalize_every,
        checkpoint=bool(checkpoint),
        unroll=unroll,
    )
    if (
        not callable(omega)
        or isinstance(omega, Sampled)
        or reusable_callable(omega, by_identity=True)
    ):
        return _integrate(q0, omega, dt, t0, **options)
    # A callable that does not hash, or a Module with NumPy fields: compiled for this call only,
    # with `omega` closed over (NumPy fields stay NumPy).
    return jax.jit(lambda q0, dt, t0: _integrate_run(q0, omega, dt, t0, **options))(q0, dt, t0)


def _integrate_run(
    q0,
    omega,
    dt,
    t0,
    *,
    aligned,
    time_eps,
    num_steps,
    frame,
    method,
    save,
    save_every,
    compensated,
    renormalize_every,
    checkpoint,
    unroll,
):
    state_dtype = q0.dtype
    time_dtype = jnp.promote_types(jnp.result_type(t0, dt), state_dtype)
    dt = dt.astype(time_dtype)
    t0 = t0.astype(time_dtype)
    batch = q0.shape[:-1]

    if callable(omega):
        check_callable(omega, "omega", "omega(t, q)", 2)
        user_omega = omega

        def omega(t, q):  # a list is an array (as for the diffrax fields), a string is an error
            return as_float_array(user_omega(t, q), "omega(t, q)")

        out = jax.eval_shape(omega, t0, q0)
        shape = tuple(getattr(out, "shape", ()))
        if len(shape) == 0 or shape[-1] != 3:
            raise ValueError(f"`omega(t, q)` must return shape (..., 3); got shape {shape}.")
        batch = _broadcast_shapes(batch, shape[:-1], "omega(t, q)", shape)
        q0 = jnp.broadcast_to(q0, batch + (4,))
        _check_magnus_omega(omega, method, t0, q0)
        source = omega
        if isinstance(user_omega, Sampled):
            # Times relative to the first sample (see `Sampled._relative`): `time(k)` below.
            shift = t0 - jnp.asarray(user_omega.t0).astype(time_dtype)
            source = user_omega._relative(shift, dt < 0, time_eps)
            t0 = shift
    else:
        batch = _broadcast_shapes(batch, omega.shape[:-1], "omega", tuple(omega.shape))
        q0 = jnp.broadcast_to(q0, batch + (4,))
        constant = omega.astype(state_dtype)
        source = lambda t, q: constant  # noqa: E731

    def field(t, q, x):
        return source(t, q), None

    xs = None
    if aligned:
        # Step k holds sample k on [t_k, t_{k+1}); a stage at the step end (c = 1) sees sample k + 1,
        # exactly as the time lookup of `Sampled.__call__` would; beyond the last sample it is held.
        rows = user_omega.omegas.astype(state_dtype)
        index = np.minimum(np.arange(num_steps + 1), rows.shape[0] - 1)
        fractions = _STAGE_FRACTIONS[method]
        xs = (rows[index[:-1]], rows[index[1:]] if 1.0 in fractions else None)

    lie = method in LIE_METHODS
    # A run shorter than the interval never renormalises: no per-step select at all.
    renormalize = lie and renormalize_every is not None and renormalize_every <= num_steps

    def time(k):
        return t0 + k.astype(time_dtype) * dt

    def renormalized(k, q, c=None):
        """q/|q| every `renormalize_every` steps (and the Kahan compensation `c`, if any, reset)."""
        return renormalized_when_due(k, q, c, renormalize_every)

    def step_field(x):
        if x is None:
            return field
        calls = iter(_STAGE_FRACTIONS[method])

        def sample_field(t, q, _):
            return (x[1] if next(calls) == 1.0 else x[0]), None

        return sample_field

    if compensated:

        def step_fn(k, carry, x=None):
            q, c = carry
            q, c = _compensated_step(method, step_field(x), time(k), q, c, dt, frame)
            if renormalize:
                q, c = renormalized(k, q, c)
            return q, c

        carry = (q0, jnp.zeros_like(q0))
        output = lambda carry: carry[0]  # noqa: E731
    else:

        def step_fn(k, q, x=None):
            q, _ = lie_step(method, step_field(x), time(k), q, None, dt, frame=frame)
            if renormalize:
                q, _ = renormalized(k, q)
            return q

        carry = q0
        output = None

    final, saved = scan_steps(
        step_fn,
        carry,
        num_steps,
        save=save,
        save_every=save_every,
        checkpoint=checkpoint,
        output=output,
        unroll=unroll,
        xs=xs,
    )
    if save == "final":
        return final[0] if compensated else final
    return saved


_integrate = eqx.filter_jit(_integrate_run)  # (arrays, `jaxquat.sampled` and `reusable_callable`s)
