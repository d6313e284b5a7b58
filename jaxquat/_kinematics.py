"""Quaternion kinematics: the rate of change, the seed's corrected rate, one exact step, and its inverse.

World frame (default): q̇ = ½ ω̃ q. Body frame: q̇ = ½ q ω̃.
"""

from __future__ import annotations

import jax.numpy as jnp
from jaxtyping import Array, ArrayLike

from ._algebra import conjugate, from_vector, multiply
from ._numerics import (
    as_float_array,
    broadcast_batch,
    check_frame,
    check_trailing,
    eager_jit,
    sum_squares,
    tan_half_over,
)
from ._rotation import from_rotvec, to_rotvec


def _apply(q: Array, generator: Array, frame: str) -> Array:
    """ω̃ ⊗ q (world) or q ⊗ ω̃ (body) for a pure quaternion built from the 3-vector `generator`."""
    g = from_vector(generator)
    return multiply(g, q) if frame == "world" else multiply(q, g)


@eager_jit(("frame",))
def rate(q: ArrayLike, omega: ArrayLike, *, frame: str = "world") -> Array:
    """The quaternion rate of change q̇ = ½ ω̃ q (world frame) or ½ q ω̃ (body frame).

    The seed's equation quatRateOfChange. q̇ is tangent to the sphere at q (q·q̇ = 0).

    **Arguments:**

    - `q`: orientations, shape `(..., 4)`.
    - `omega`: angular velocity in rad/s, shape `(..., 3)`; leading axes broadcast with `q`.
    - `frame`: `"world"` (ω in world coordinates) or `"body"` (ω in body coordinates).

    **Returns:** q̇, shape `(..., 4)`.
    """
    frame = check_frame(frame)
    q = check_trailing(q, 4, "q")
    omega = check_trailing(omega, 3, "omega")
    q, omega = broadcast_batch((q, 1, "q"), (omega, 1, "omega"))
    return _apply(q, 0.5 * omega, frame)


@eager_jit(("frame",))
def corrected_rate(q: ArrayLike, omega: ArrayLike, dt: ArrayLike, *, frame: str = "world") -> Array:
    r"""The seed's corrected rate of change $\dot q_{\Delta t} = \frac{\tan(|ω|Δt/2)}{|ω|Δt}\,\tilde ω q$.

    Equation quatRateOfChangeCorrected of the seed notes (README, Sources): one Euler step
    `q + dt * corrected_rate(q, omega, dt)` followed by renormalisation is exactly the rotation by
    ωΔt (for |ω|Δt < π), i.e. `step(q, omega, dt)`.

    **Arguments:**

    - `q`: orientations `(..., 4)`; `omega`: angular velocity `(..., 3)` in rad/s; `dt`: the step the
      correction is made for, scalar or `(...)`. `frame`: `"world"` (ω̃ q) or `"body"` (q ω̃).

    **Returns:** q̇_Δt, shape `(..., 4)`.

    **Singular points.** At ω = 0 (or Δt = 0) the factor tan(θ/2)/θ, θ = |ω|Δt, is evaluated by its
    series: value ½ (the plain rate), derivative w.r.t. ω exactly that of ½ ω̃ q. At θ = π (mod 2π)
    tan has poles: there the floating-point tan is returned (finite but ~1e16 in float64), and its
    derivative is wrong within ~1e-9 of the pole (float64, ~1e-6 float32). Past θ = π the Euler step
    lands on −q (same rotation, other sheet). Use `step` to advance; this function is the seed's
    equation verbatim, for use as a vector field.
    """
    frame = check_frame(frame)
    q = check_trailing(q, 4, "q")
    omega = check_trailing(omega, 3, "omega")
    dt = as_float_array(dt, "dt")
    q, omega, dt = broadcast_batch((q, 1, "q"), (omega, 1, "omega"), (dt, 0, "dt"))
    # θ² as |ω dt|², not |ω|²·dt²: |ω|² left float32's range from |ω| ≈ 1.8e19 (or 1e-19) while θ
    # was 1 (helper-53).
    factor = tan_half_over(sum_squares(omega * dt[..., None]))
    return _apply(q, factor[..., None] * omega, frame)


@eager_jit(("frame",))
def step(q: ArrayLike, omega: ArrayLike, dt: ArrayLike, *, frame: str = "world") -> Array:
    """One corrected step: exp(ωΔt) ⊗ q (world frame) or q ⊗ exp(ωΔt) (body frame).

    Equal to `normalize(q + dt * corrected_rate(q, omega, dt))` for |ω|Δt < π (docs/numerics.md §1), but
    computed with cos/sin: no tan pole, no sign flip past half a turn, no norm growth. Exact for
    constant ω at any step size. At ω = 0: value q, Jacobian w.r.t. ω ½Δt·[0; I₃]·q (world).

    **Arguments:**

    - `q`: orientations `(..., 4)`; `omega`: angular velocity `(..., 3)` (rad/s); `dt`: scalar or `(...)`.
    - `frame`: `"world"` or `"body"`.

    **Returns:** the orientation after Δt, shape `(..., 4)` (unit if `q` is unit).
    """
    frame = check_frame(frame)
    q = check_trailing(q, 4, "q")
    omega = check_trailing(omega, 3, "omega")
    dt = as_float_array(dt, "dt")
    q, omega, dt = broadcast_batch((q, 1, "q"), (omega, 1, "omega"), (dt, 0, "dt"))
    increment = from_rotvec(omega * dt[..., None])
    return multiply(increment, q) if frame == "world" else multiply(q, increment)


@eager_jit(("frame",))
def angular_velocity(qs: ArrayLike, dt: ArrayLike, *, frame: str = "world") -> Array:
    """The piecewise-constant angular velocity that `step` maps `qs[k]` to `qs[k + 1]` with.

    The exact inverse of `step` along a trajectory, taking the shortest rotation between neighbours
    (sign-invariant: `qs` may mix q and −q): ω_k = to_rotvec(q_{k+1} q_k*)/Δt (world) or
    to_rotvec(q_k* q_{k+1})/Δt (body).

    **Arguments:**

    - `qs`: a time-major trajectory `(T, ..., 4)` with T ≥ 2.
    - `dt`: the time step: a scalar, or time-major `(T - 1,)` / `(T - 1, ...)` for non-uniform sampling.
    - `frame`: `"world"` or `"body"`.

    **Returns:** ω, shape `(T - 1, ..., 3)`.

    A non-finite Δt gives NaN (an infinite one gave a plausible ω = 0), a zero Δt inf or NaN: bad
    values propagate, as everywhere in jaxquat's math functions.
    """
    frame = check_frame(frame)
    qs = check_trailing(qs, 4, "qs")
    if qs.ndim < 2 or qs.shape[0] < 2:
        raise ValueError(
            f"`qs` must be a trajectory of shape (T, ..., 4) with T >= 2; got shape {tuple(qs.shape)}."
        )
    dt = as_float_array(dt, "dt")
    before, after = qs[:-1], qs[1:]
    if frame == "world":
        relative = multiply(after, conjugate(before))
    else:
        relative = multiply(conjugate(before), after)
    rotvec = to_rotvec(relative)
    batch = rotvec.shape[:-1]
    given = tuple(dt.shape)
    if dt.ndim > len(batch):
        raise ValueError(
            f"`dt` must be a scalar or of shape {batch} (time-major); got {tuple(dt.shape)}."
        )
    # Non-scalar dt is time-major: align its leading axis with the time axis.
    dt = dt.reshape(dt.shape + (1,) * (len(batch) - dt.ndim))
    try:
        dt = jnp.broadcast_to(dt, batch)
    except ValueError as e:
        raise ValueError(
            f"`dt` must be a scalar or of shape {batch} (time-major); got {given}."
        ) from e
    finite = jnp.isfinite(dt)[..., None]
    return jnp.where(finite, rotvec / jnp.where(finite, dt[..., None], 1.0), jnp.nan)
