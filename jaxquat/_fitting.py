r"""Fitting angular velocity (and a torque-free body's inertia) to observed orientations.

The fits are nonlinear least squares solved by `optimistix` (Levenberg–Marquardt, then a few
Gauss–Newton steps that reach the optimum to round-off) through
the forward models of the lower layers: the closed-form exponential for constant ω (`step`), the
fixed-step integrators for time-varying ω (`integrate`), and `simulate_rigid_body` for a torque-free
body. Every fit finds its own starting point from the log-differences of neighbouring observations
(`angular_velocity`), because Levenberg–Marquardt started at ω = 0 falls into a wrong minimum once
the data span more than about half a turn.

**Residual.** For a model orientation q and an observation r the residual is the 3-vector

$$\rho(q, r) = 2\,\operatorname{sgn}(w(e))\,\operatorname{vec}(e), \qquad
e = q \otimes r^* \ (\text{world frame}) \quad\text{or}\quad e = r^* \otimes q \ (\text{body frame}),$$

i.e. $2\sin(\theta/2)\,\hat n$ for the error rotation of angle $\theta \in [0, \pi]$ about $\hat n$: the
error in radians to third order. It is invariant under $r \to -r$ and $q \to -q$, linear (so
Gauss–Newton is well conditioned) with the exact Jacobian at zero residual, and its squared norm
$|\rho|^2 = 4(1 - \langle q, r\rangle^2)$ is smooth everywhere (docs/numerics.md §4): the sign switch at
$\theta = \pi$ flips the vector but changes neither the loss nor its gradient $J^\top\rho$.
"""

from __future__ import annotations

import functools
from typing import Any

import equinox as eqx
import jax
import jax.numpy as jnp
import lineax as lx
import numpy as np
import optimistix as optx
from jax import lax
from jaxtyping import Array, ArrayLike

from ._algebra import conjugate, multiply, normalize
from ._dynamics import simulate_rigid_body
from ._geometry import angle_between
from ._integrate import integrate
from ._kinematics import angular_velocity, step
from ._numerics import (
    as_float_array,
    check_choice,
    check_frame,
    check_trailing,
    cross,
    integer_value,
    is_tracer,
    safe_norm,
)
from ._rotation import from_rotvec, rotate_unchecked

_MODELS = ("constant", "piecewise_linear", "spline")
# Turns between neighbouring observations this close to π (rad) may be on either branch (`_unwrap`).
_NEAR_HALF_TURN = 0.25


# --------------------------------------------------------------------------------------------------
# Results


class AngularVelocityFit(eqx.Module):
    """The result of `fit_angular_velocity` (a PyTree: fits `jax.vmap` and `jax.jit`).

    **Fields:**

    - `omega`: the fitted angular velocity. For `model="constant"` an array `(3,)` in rad/s; for the
      time-varying models an `AngularVelocityCurve`, a callable `omega(t) -> (..., 3)`.
    - `q0`: the fitted orientation at the first observation time `t0`, shape `(4,)`, in the
      hemisphere of the first observation.
    - `t0`: the first observation time (the model's time origin), in the dtype of `times`.
    - `fitted`: the model orientations at the observation times, shape `(T, 4)`.
    - `residual_angles`: geodesic angle in [0, π] between model and observation, shape `(T,)` (rad).
    - `loss`: the final objective ½ Σₖ wₖ |ρₖ|² (`optimistix`'s convention; see the module docstring).
    - `num_steps`: the number of solver steps taken (Levenberg–Marquardt plus the Gauss–Newton polish).
    - `converged`: whether the solver (or the polish after it) met its tolerances within its step limit.
    - `frame`, `model`: the options the fit was made with (static).
    """

    omega: Any
    q0: Array
    t0: Array
    fitted: Array
    residual_angles: Array
    loss: Array
    num_steps: Array
    converged: Array
    frame: str = eqx.field(static=True)
    model: str = eqx.field(static=True)


# --------------------------------------------------------------------------------------------------
# Shared pieces


def _orientation_residuals(model_qs: Array, observed: Array, frame: str) -> Array:
    """ρ = 2 sgn(w(e)) vec(e), shape `(..., 3)`; see the module docstring."""
    if frame == "world":
        error = multiply(model_qs, conjugate(observed))
    else:
        error = multiply(conjugate(observed), model_qs)
    vec = error[..., 1:]
    return 2.0 * jnp.where(error[..., :1] < 0, -vec, vec)


def _act(q: Array, rotation: Array, frame: str) -> Array:
    """rotation ⊗ q (world frame, left action) or q ⊗ rotation (body frame, right action)."""
    return multiply(rotation, q) if frame == "world" else multiply(q, rotation)


def _perturb(reference: Array, delta: Array, frame: str) -> Array:
    """exp(δ) ⊗ q (world frame) or q ⊗ exp(δ) (body frame): the minimal chart around `reference`."""
    return _act(reference, from_rotvec(delta), frame)


def _default_solver(dtype) -> optx.AbstractLeastSquaresSolver:
    tol = 1e-6 if jnp.dtype(dtype) == jnp.float64 else 1e-4
    return optx.LevenbergMarquardt(rtol=tol, atol=tol)


def _polish_solver(dtype) -> optx.AbstractLeastSquaresSolver:
    tol = 1e-12 if jnp.dtype(dtype) == jnp.float64 else 1e-6
    return optx.GaussNewton(rtol=tol, atol=tol)


_TWO_POSITIVE = (2, "two", "(a rotation needs two orientations to be seen)")


def _check_observations(
    times: ArrayLike, qs: ArrayLike, weights: ArrayLike | None, positive=_TWO_POSITIVE
):
    """Validate `(times, qs, weights)`; return (times, unit qs, weights). `positive`: how many
    observations concrete weights must leave (the count, in words, and why)."""
    qs = check_trailing(qs, 4, "qs")
    if qs.ndim != 2:
        raise ValueError(
            "`qs` must be one trajectory of shape (T, 4) (use `jax.vmap` for many bodies); "
            f"got shape {tuple(qs.shape)}."
        )
    num_obs = qs.shape[0]
    if num_obs < 3:
        raise ValueError(
            f"at least 3 observations are needed; got `qs` of shape {tuple(qs.shape)}."
        )
    times = as_float_array(times, "times")
    if times.shape != (num_obs,):
        raise ValueError(
            f"`times` must have shape ({num_obs},) to match `qs` {tuple(qs.shape)}; "
            f"got shape {tuple(times.shape)}."
        )
    if not is_tracer(times):
        concrete = np.asarray(times)
        if not np.all(np.isfinite(concrete)):
            first = int(np.argmin(np.isfinite(concrete)))
            raise ValueError(
                f"`times` must be finite; times[{first}] = {float(concrete[first])!r}."
            )
        with np.errstate(over="ignore"):
            span = concrete[-1] - concrete[0]
        if not np.isfinite(span):
            raise ValueError(
                f"`times` span {float(concrete[0])!r} … {float(concrete[-1])!r}, which overflows "
                f"{concrete.dtype}; shift them to a nearer origin."
            )
        steps = np.diff(concrete)
        if not np.all(steps > 0):
            first = int(np.argmin(steps > 0))
            raise ValueError(
                "`times` must be strictly increasing; "
                f"times[{first}] = {float(times[first])!r} >= times[{first + 1}] = "
                f"{float(times[first + 1])!r}."
            )
        # XLA flushes subnormal numbers to zero: a step below the smallest normal number (of the
        # times' dtype, or of the data's, into which the durations are cast) became a duration of
        # 0, and the fit NaN (times [0, 1e-310, 2e-310, ...]). float16 times are subtracted in
        # float32 (their steps of 1e-5 fit float32 data exactly), but durations cast to float16
        # data are float16: steps of 1e-5 gave a NaN fit with float16 data whatever the times.
        subtracted = jnp.promote_types(concrete.dtype, jnp.float32)
        tiny = max(float(jnp.finfo(subtracted).tiny), float(jnp.finfo(qs.dtype).tiny))
        if not np.all(steps >= tiny):
            first = int(np.argmin(steps >= tiny))
            raise ValueError(
                "`times` must increase by at least the smallest normal number "
                f"({tiny!r}; smaller steps are flushed to zero) between observations; "
                f"times[{first}] = {float(times[first])!r} and times[{first + 1}] = "
                f"{float(times[first + 1])!r}. Rescale the times."
            )
    dtype = qs.dtype
    if weights is None:
        weights = jnp.ones((num_obs,), dtype)
    else:
        weights = as_float_array(weights, "weights")
        if weights.shape != (num_obs,):
            raise ValueError(
                f"`weights` must have shape ({num_obs},) to match `qs` {tuple(qs.shape)}; "
                f"got shape {tuple(weights.shape)}."
            )
        if not is_tracer(weights) and not np.all(np.isfinite(np.asarray(weights))):
            raise ValueError(f"`weights` must be finite; got {np.asarray(weights)}.")
        if not is_tracer(weights) and np.any(np.asarray(weights) < 0):
            raise ValueError(f"`weights` must be non-negative; got minimum {np.min(weights)}.")
        needed, word, why = positive
        if not is_tracer(weights) and np.count_nonzero(np.asarray(weights)) < needed:
            raise ValueError(
                f"`weights` must give at least {word} observations a positive weight {why}; "
                f"got {np.count_nonzero(np.asarray(weights))}."
            )
        weights = weights.astype(dtype)
    if not is_tracer(qs):
        _check_normalisable(np.asarray(qs), "qs")
    # `normalize` brings rows of extreme magnitude (1e300, 1e-300) into range by an exact power of two
    # first (dividing by the largest component instead made rows above ~4.5e307 NaN: XLA turns x/m
    # into x·(1/m), and 1/m is then subnormal and flushed to zero).
    return times, normalize(qs), weights


def _check_normalisable(qs: np.ndarray, name: str) -> None:
    """Raise a `ValueError` naming the first row of `qs` `(T, 4)` that has no direction to normalise."""
    largest = np.max(np.abs(qs), axis=-1)
    finite = np.all(np.isfinite(qs), axis=-1)
    tiny = float(jnp.finfo(qs.dtype).tiny)  # jnp: also bfloat16
    for row in range(qs.shape[0]):
        if not finite[row]:
            problem = "is not finite"
        elif largest[row] == 0:
            problem = "is zero"
        elif largest[row] < tiny:
            problem = (
                f"is too small to normalise accurately (largest component {float(largest[row])!r} is "
                f"subnormal in {qs.dtype})"
            )
        else:
            continue
        raise ValueError(f"`{name}[{row}]` {problem}: {qs[row].tolist()}.")


def _check_count(value, name: str, minimum: int) -> int:
    """An integer ≥ `minimum` of any kind (Python, NumPy, a concrete JAX scalar), not a bool."""
    count = integer_value(value)
    if count is None or count < minimum:
        raise ValueError(f"`{name}` must be an int >= {minimum}; got {value!r}.")
    return count


def _relative_times(times: Array, dtype) -> Array:
    """t − t₀, subtracted in the dtype of `times` (float64 for float32 data, say), then cast."""
    return (times - times[0]).astype(dtype)


def _interval_rates(
    times: Array, qs: Array, weights: Array, frame: str
) -> tuple[Array, Array, Array, Array]:
    """Log-differences of neighbouring observations that have a positive weight.

    Returns `(rates, midpoints, durations, valid)`, each over T − 1 intervals in time order
    (midpoints in `times`' dtype, relative to t₀, durations in the data's): interval j ends at
    observation j + 1 and starts at the last positively weighted observation before it, and is valid
    if both have positive weights. Observations of weight 0 (outliers, say) are bridged, not used: a
    log-difference to one of them gave the starting guesses rates of up to π/Δt, from which the
    spline fits converged to a wrong minimum. Invalid intervals hold finite placeholders.
    """
    positive = weights > 0
    index = jnp.arange(qs.shape[0])
    last_positive = lax.cummax(jnp.where(positive, index, -1))[:-1]  # strictly before j + 1
    valid = positive[1:] & (last_positive >= 0)
    start = jnp.where(valid, last_positive, index[:-1])
    end = index[1:]
    tau = times - times[0]
    durations = (tau[end] - tau[start]).astype(qs.dtype)
    pairs = jnp.stack([qs[start], qs[end]])  # (2, T - 1, 4): one step per interval
    turns = angular_velocity(pairs, 1.0, frame=frame)[0]  # rotation vectors, angles in [0, π]
    midpoints = tau[start] + 0.5 * (tau[end] - tau[start])
    return _unwrap(turns, durations, valid), midpoints, durations, valid


def _unwrap(turns: Array, durations: Array, valid: Array) -> Array:
    """Rates θn̂/Δt from rotation vectors, near half a turn on the branch nearer the last valid rate.

    The shortest rotation between two observations is ambiguous at half a turn: for a body turning by
    π per interval, noise picked n̂π or −n̂π at random, the starting ω averaged them to ~0, and the
    fit converged with residuals of 2.9 rad (converged=True). A turn within `_NEAR_HALF_TURN` of π is
    therefore replaced by its other branch (θ − 2π)n̂ when that rate is nearer the previous one; all
    other turns (the documented domain |ω|Δt < π, away from its edge) are kept as they are.
    """
    angles = safe_norm(turns, axis=-1, keepdims=True)  # (a body at rest: no NaN in reverse mode)
    safe = jnp.where(angles > 0, angles, 1)
    rates = turns / durations[:, None]
    others = rates * (1 - 2 * jnp.pi / safe)
    ambiguous = valid & (angles[:, 0] > jnp.pi - _NEAR_HALF_TURN)

    def choose(last, inputs):
        rate, other, ok, near_pi = inputs
        nearer = jnp.sum((other - last) ** 2) < jnp.sum((rate - last) ** 2)
        chosen = jnp.where(near_pi & nearer, other, rate)
        return jnp.where(ok, chosen, last), chosen

    # The chain starts from the first valid interval's rate. If that turn is itself near π, noise may
    # have flipped it, and every near-π interval after it followed (a review: one observation off by
    # 0.01 rad gave residuals of 2.8 rad with converged=True). It is then taken on the branch whose
    # sign along the rates' dominant axis agrees with most intervals' (a discrete choice: no
    # derivative flows through it).
    index = jnp.argmax(valid)
    plain = lax.stop_gradient(jnp.where(valid[:, None], rates, 0))
    plain = plain.astype(jnp.promote_types(plain.dtype, jnp.float32))  # (no bfloat16 eigh)
    axis = jnp.linalg.eigh(plain.T @ plain)[1][:, -1]
    along = plain @ axis
    majority = jnp.sum(jnp.sign(along))
    flip = ambiguous[index] & (along[index] * majority < 0)
    first = jnp.where(flip, others[index], rates[index])
    return lax.scan(choose, first, (rates, others, valid, ambiguous))[1]


def _check_solver(solver):
    if solver is None or isinstance(
        solver, (optx.AbstractLeastSquaresSolver, optx.AbstractMinimiser)
    ):
        return solver
    raise ValueError(
        "`solver` must be None (the default Levenberg–Marquardt) or an optimistix least-squares solver "
        "or minimiser instance, e.g. optimistix.LevenbergMarquardt(rtol=1e-6, atol=1e-6), "
        "optimistix.GaussNewton(...), optimistix.Dogleg(...), optimistix.IndirectLevenbergMarquardt(...) "
        f"or optimistix.BFGS(...); got {solver!r}."
    )


def _solver_options(solver, dtype, max_steps, polish) -> dict:
    solver = _check_solver(solver)
    return dict(
        solver=_default_solver(dtype) if solver is None else solver,
        max_steps=_check_count(max_steps, "max_steps", 1),
        polish=_check_count(polish, "polish", 0),
    )


def _weighted_loss(residuals: Array, weights: Array) -> Array:
    """½ Σₖ wₖ |ρₖ|², linear in the weights (so differentiable at a weight of 0)."""
    return 0.5 * jnp.sum(weights * jnp.sum(residuals * residuals, axis=-1))


def _cast(tree, dtype):
    return jax.tree_util.tree_map(lambda leaf: leaf.astype(dtype), tree)


def _solver_dtype(data_dtype):
    """The dtype the solvers hold the parameters in: the data's promoted with JAX's default float."""
    return jnp.promote_types(data_dtype, jnp.asarray(1.0).dtype)


def _solve(residual_fn, y0, args, weights, solver, max_steps: int, polish: int):
    """Minimise ½ Σₖ wₖ |ρₖ(θ)|² (ρ = `residual_fn(θ, args)`, shape (T, 3)) from `y0`.

    Levenberg–Marquardt (or `solver`), then up to `polish` Gauss–Newton steps. Returns
    `(parameters, steps, converged)`. Near the optimum of a problem with noise the loss no
    longer resolves the remaining step (its round-off is ~ε·loss), so a damped method's acceptance
    test starts rejecting steps at ~1e-10 from the optimum and ends on the trust-region radius.
    Gauss–Newton does not test the loss: from the Levenberg–Marquardt solution it reaches the
    stationary point to round-off in one or two steps, on exact and noisy data alike (its result is
    used only if it meets its own tolerance).

    The solvers see the residuals √wₖ ρₖ. Their derivative with respect to the data, the weights and
    the times is the implicit function theorem's, applied to the stationarity condition
    ∇θ ½ Σₖ wₖ |ρₖ|² = 0 written with the weights linear: through √w, as optimistix's own adjoint
    would differentiate it, a weight of exactly 0 gave 0·∞ = NaN (d√w/dw = ∞) instead of the finite
    −H⁻¹ Jₖᵀρₖ.

    The parameters are held in the promotion of their dtype with JAX's default float (float64 for
    float32 data when x64 is on: optimistix creates its trust-region radius in the default dtype, which
    would promote half of the damped linear system) and cast back to the data's dtype inside the
    residual, so the model itself runs in the data's dtype; the residuals are promoted on the way out.
    """
    data_dtype = jax.tree_util.tree_leaves(y0)[0].dtype
    y0 = _cast(y0, _solver_dtype(data_dtype))
    inputs = (residual_fn, y0, args, weights, solver, max_steps, polish)
    # The rewrite's Jacobian in θ is the loss's Hessian: symmetric. It is singular when the data do
    # not determine the parameters (a batch lane with one positive weight, under vmap where the
    # ValueError cannot see it); an LU solve then raised inside lineax and aborted the whole batch's
    # derivative. The least-squares solve (well_posed=False) gives that lane its minimum-norm
    # derivative instead, and the others theirs.
    params, (num_steps, converged) = optx.internal.implicit_jvp(
        _solve_primal,
        _solve_rewrite,
        inputs,
        frozenset({lx.symmetric_tag}),
        lx.AutoLinearSolver(well_posed=False),
    )
    return _cast(params, data_dtype), num_steps, converged


def _solve_primal(inputs):
    """The solve itself (only its value is used: `_solve_rewrite` gives its derivative)."""
    residual_fn, y, args, weights, solver, max_steps, polish = inputs
    data_dtype = weights.dtype
    solver_dtype = jax.tree_util.tree_leaves(y)[0].dtype
    sqrt_weights = jnp.sqrt(weights)[:, None]

    def residuals(params, args):
        rho = residual_fn(_cast(params, data_dtype), args)
        return (sqrt_weights * rho).astype(solver_dtype)

    def run(solver, y, steps):
        solution = optx.least_squares(residuals, solver, y, args, max_steps=steps, throw=False)
        ok = solution.result == optx.RESULTS.successful
        return solution.value, solution.stats["num_steps"], ok

    y, num_steps, converged = run(solver, y, max_steps)
    if polish:
        polished, polish_steps, polish_ok = run(_polish_solver(data_dtype), y, polish)
        y = jax.tree_util.tree_map(lambda a, b: jnp.where(polish_ok, a, b), polished, y)
        num_steps = num_steps + polish_steps
        converged = converged | polish_ok
    return y, (num_steps, converged)


def _solve_rewrite(params, _, inputs):
    """The stationarity condition ∇θ ½ Σₖ wₖ |ρₖ(θ)|², zero at the solution."""
    residual_fn, _, args, weights, *_ = inputs
    data_dtype = weights.dtype
    solver_dtype = jax.tree_util.tree_leaves(params)[0].dtype

    def loss(params):
        rho = residual_fn(_cast(params, data_dtype), args).astype(solver_dtype)
        return _weighted_loss(rho, weights.astype(solver_dtype))

    return jax.grad(loss)(params)


# --------------------------------------------------------------------------------------------------
# Constant angular velocity


def _constant_model(params, tau, reference, frame):
    delta, omega = params
    q0 = _perturb(reference, delta, frame)
    return q0, step(q0, omega, tau, frame=frame)


def _constant_residuals(params, args, frame):
    tau, observed, reference = args
    _, model_qs = _constant_model(params, tau, reference, frame)
    return _orientation_residuals(model_qs, observed, frame)


# --------------------------------------------------------------------------------------------------
# Time-varying angular velocity: a curve through knot values


class AngularVelocityCurve(eqx.Module):
    r"""A time-varying angular velocity ω(t) through values at knots: piecewise linear or a cubic spline.

    Callable: `curve(t)` (or `curve(t, q)`, the signature `integrate` expects; `q` is ignored) returns
    ω at the times `t` (any shape), shape `t.shape + (3,)`. Outside the knots the first and last
    pieces are extended (linear, resp. cubic extrapolation).

    The spline is the interpolating cubic with not-a-knot end conditions (SciPy's `CubicSpline`
    default): on $[x_i, x_{i+1}]$, with $b = (t - x_i)/h_i$, $a = 1 - b$,
    $s(t) = a v_i + b v_{i+1} + \tfrac{h_i^2}{6}\big((a^3 - a) M_i + (b^3 - b) M_{i+1}\big)$,
    where the second derivatives $M$ make $s'$ continuous at the interior knots and $s'''$ continuous
    at the second and the second-to-last knot. The curve is linear in the values.

    **Fields:** `knots` `(K,)` (increasing times), `values` `(K, 3)` (ω at the knots, rad/s),
    `second_derivatives` `(K, 3)` (zero for the piecewise-linear kind), `kind`
    (`"piecewise_linear"` or `"spline"`, static).
    """

    knots: Array
    values: Array
    second_derivatives: Array
    kind: str = eqx.field(static=True)

    @classmethod
    def through(cls, knots: Array, values: Array, kind: str) -> AngularVelocityCurve:
        """The curve of `kind` through `values` `(K, C)` at `knots` `(K,)` (any number C of channels).

        K ≥ 2 for `"piecewise_linear"`, K ≥ 4 for `"spline"`; `knots` must be increasing (not checked).
        """
        kind = check_choice(kind, _MODELS[1:], "kind")
        knots = as_float_array(knots, "knots")
        values = as_float_array(values, "values")
        minimum = 4 if kind == "spline" else 2
        if knots.ndim != 1 or knots.shape[0] < minimum or values.shape[:1] != knots.shape:
            raise ValueError(
                f"`knots` must have shape (K,) with K >= {minimum} for kind={kind!r} and `values` "
                f"shape (K, C); got {tuple(knots.shape)} and {tuple(values.shape)}."
            )
        if kind == "spline":
            second = _not_a_knot_second_derivatives(knots, values)
        else:
            second = jnp.zeros_like(values)
        return cls(knots, values, second, kind)

    def __call__(self, t: ArrayLike, q: ArrayLike | None = None) -> Array:
        del q
        t = jnp.asarray(t)
        num_knots = self.knots.shape[0]
        index = jnp.clip(jnp.searchsorted(self.knots, t, side="right") - 1, 0, num_knots - 2)
        left = self.knots[index]
        width = self.knots[index + 1] - left
        b = ((t - left) / width).astype(self.values.dtype)[..., None]
        a = 1.0 - b
        out = a * self.values[index] + b * self.values[index + 1]
        if self.kind == "spline":
            curvature = (a * a * a - a) * self.second_derivatives[index] + (
                b * b * b - b
            ) * self.second_derivatives[index + 1]
            out = out + (width * width / 6.0).astype(self.values.dtype)[..., None] * curvature
        return out


def _not_a_knot_second_derivatives(knots: Array, values: Array) -> Array:
    """Second derivatives M `(K, C)` of the not-a-knot cubic spline through `values` at `knots`."""
    num_knots = knots.shape[0]
    dtype = values.dtype
    h = jnp.diff(knots).astype(dtype)
    inner = jnp.arange(1, num_knots - 1)
    lhs = jnp.zeros((num_knots, num_knots), dtype)
    lhs = lhs.at[inner, inner - 1].set(h[:-1] / 6.0)
    lhs = lhs.at[inner, inner].set((h[:-1] + h[1:]) / 3.0)
    lhs = lhs.at[inner, inner + 1].set(h[1:] / 6.0)
    # Not-a-knot: the third derivative (M[i+1] - M[i]) / h[i] is continuous at knots 1 and K - 2.
    lhs = lhs.at[0, 0:3].set(jnp.stack([-h[1], h[0] + h[1], -h[0]]))
    lhs = lhs.at[-1, -3:].set(jnp.stack([-h[-1], h[-2] + h[-1], -h[-2]]))
    slopes = jnp.diff(values, axis=0) / h[:, None]
    rhs = jnp.zeros_like(values).at[1:-1].set(slopes[1:] - slopes[:-1])
    return jnp.linalg.solve(lhs, rhs)


def _curve_model(params, times, reference, knots, frame, kind, substeps):
    """q0, the curve, and the orientations at `times`: `substeps` Magnus-4 steps per interval
    between neighbouring points of the merged grid of observation times and knots.

    Integrating from point to point (rather than on a fixed grid and interpolating) lands every
    step sequence on the observation times whatever their spacing; ending steps on the knots too,
    where ω's slope (piecewise linear) or third derivative (spline) jumps, keeps the method's fourth
    order — a step straddling a kink of the piecewise-linear curve made it first order. ω(t) does
    not depend on q, so the fourth-order Magnus method applies (docs/numerics.md §2).
    """
    delta, values = params
    curve = AngularVelocityCurve.through(knots, values, kind)
    q0 = _perturb(reference, delta, frame)
    num_obs = times.shape[0]
    # Knots outside the observed span give steps of length 0 (the identity) once clipped to it.
    inner = jnp.clip(knots.astype(times.dtype), times[0], times[-1])
    points = jnp.concatenate([times, inner])
    order = jnp.argsort(points, stable=True)  # (times first among equal values)
    grid = points[order]
    where = jnp.zeros(order.shape, order.dtype).at[order].set(jnp.arange(order.shape[0]))

    def interval(q, bounds):
        start, end = bounds
        h = (end - start) / substeps
        q = integrate(q, curve, h, substeps, frame=frame, method="magnus4", t0=start, save="final")
        return q, q

    _, later = lax.scan(interval, q0, (grid[:-1], grid[1:]))
    along = jnp.concatenate([q0[None], later], axis=0)
    return q0, curve, along[where[:num_obs]]


def _curve_residuals(params, args, frame, kind, substeps):
    times, observed, reference, knots = args
    _, _, model_qs = _curve_model(params, times, reference, knots, frame, kind, substeps)
    return _orientation_residuals(model_qs, observed, frame)


def _used_times(times: Array, weights: Array) -> np.ndarray | None:
    """The times of the observations of positive weight when the weights are concrete and some are
    0 (a weight of 0 removes an observation: only the rest determine the knots), else `None`."""
    if is_tracer(weights) or is_tracer(times):
        return None
    used = np.asarray(weights) > 0
    return None if used.all() else np.asarray(times)[used]


def _check_knots(knots, times: Array, model: str, num_obs: int, used=None) -> Array:
    """The knot times: evenly spaced over `times` for an int, or as given; checked to be determined
    by the observations (by `used`, the times of positive weight, when some weights are 0)."""
    minimum = 4 if model == "spline" else 2
    weighted = used is not None
    if weighted:
        num_obs = used.shape[0]
    determining = (
        None if is_tracer(times) else np.asarray(times if used is None else used, np.float64)
    )
    if knots is None:
        knots = max(minimum, min(20, num_obs // 4))
    if isinstance(knots, (bool, np.bool_)):
        raise ValueError(f"`knots` must be an int or knot times (K,); got {knots!r}.")
    if isinstance(knots, (int, np.integer)):
        if knots < minimum:
            raise ValueError(
                f"`knots` must be at least {minimum} for model={model!r}; got {knots}."
            )
        _check_determined(int(knots), model, num_obs, weighted)
        evenly = jnp.linspace(times[0], times[-1], int(knots), dtype=times.dtype)
        if determining is not None:  # (evenly spaced knots over a gap in the observations)
            _check_identifiable(
                np.asarray(evenly, np.float64), determining, model, given=False, weighted=weighted
            )
        return evenly
    knots = as_float_array(knots, "knots")
    if knots.ndim != 1 or knots.shape[0] < minimum:
        raise ValueError(
            f"`knots` must be an int or knot times of shape (K,) with K >= {minimum} for "
            f"model={model!r}; got shape {tuple(knots.shape)}."
        )
    if not is_tracer(knots):
        if not np.all(np.isfinite(np.asarray(knots))):
            raise ValueError(f"`knots` must be finite; got {np.asarray(knots)}.")
        if not np.all(np.diff(np.asarray(knots)) > 0):
            raise ValueError(f"`knots` must be strictly increasing; got {np.asarray(knots)}.")
    _check_determined(knots.shape[0], model, num_obs, weighted)
    if not is_tracer(knots) and determining is not None:
        _check_identifiable(np.asarray(knots, np.float64), determining, model, weighted=weighted)
    return knots


def _check_determined(num_knots: int, model: str, num_obs: int, weighted: bool = False) -> None:
    """K knots are 3K unknowns (plus 3 for q0); T observations give 3T equations: need K <= T - 1.

    Equivalently, the T - 1 relative rotations between neighbouring observations (3 degrees of
    freedom each) must determine the 3K knot values. More knots leave ω(t) undetermined: the solver
    reports convergence to one of infinitely many minima.
    """
    if num_knots > num_obs - 1:
        minimum = 4 if model == "spline" else 2
        if num_obs - 1 < minimum:
            hint = f"model={model!r} needs at least {minimum} knots, so at least {minimum + 1} observations"
        else:
            hint = f"use knots <= {num_obs - 1} or more observations"
        which = " of positive `weights`" if weighted else ""
        raise ValueError(
            f"`knots`: {num_knots} knots are too many for {num_obs} observations{which} with "
            f"model={model!r}: the {num_obs - 1} rotations between neighbouring observations "
            f"determine at most {num_obs - 1} knots (3 unknowns each); {hint}."
        )


def _check_identifiable(
    knots: np.ndarray, times: np.ndarray, model: str, given: bool = True, weighted: bool = False
) -> None:
    """The T − 1 observation intervals must determine every knot value (`given`: the knot times
    were passed; else they are the evenly spaced ones of an int `knots`, which a gap in the
    observations can leave undetermined too).

    To first order in the rotation, the rotation between observations j and j + 1 is
    ∫ ω dt = Σ_i c_i ∫ B_i dt over that interval (B_i the curve's basis functions, c_i the knot
    values), so the knot values are determined (locally) only if the (T − 1) × K matrix
    G_ji = ∫_(t_j)^(t_(j+1)) B_i dt has full column rank K. Counting (K ≤ T − 1, `_check_determined`)
    is necessary, not sufficient: G loses rank when knots bunch between neighbouring observations (a
    Schoenberg–Whitney-type condition), and the solver would then report convergence to one of
    infinitely many minima. The integrals are exact (two-point Gauss–Legendre on the pieces between
    knots and observation times, on each of which the basis is a cubic); the rank is that of G with
    unit columns, to a relative 1e-8 (100 ε in float32).
    """
    num_knots = knots.shape[0]
    edges = np.unique(np.concatenate([times, knots[(knots > times[0]) & (knots < times[-1])]]))
    lo, hi = edges[:-1], edges[1:]
    mid, half = 0.5 * (lo + hi), 0.5 * (hi - lo)
    nodes = np.concatenate([mid - half / np.sqrt(3.0), mid + half / np.sqrt(3.0)])
    basis = AngularVelocityCurve.through(jnp.asarray(knots), jnp.eye(num_knots), model)
    values = basis(jnp.asarray(nodes))  # in JAX's default float: float32 unless x64 is on
    tolerance = max(1e-8, 100.0 * float(jnp.finfo(values.dtype).eps))
    values = np.asarray(values, np.float64).reshape(2, -1, num_knots)
    pieces = half[:, None] * (values[0] + values[1])  # ∫ B_i over each piece
    interval = np.clip(np.searchsorted(times, lo, side="right") - 1, 0, times.shape[0] - 2)
    gram = np.zeros((times.shape[0] - 1, num_knots))
    np.add.at(gram, interval, pieces)
    scale = np.linalg.norm(gram, axis=0)
    singular = np.linalg.svd(gram / np.where(scale > 0, scale, 1.0), compute_uv=False)
    rank = int(np.sum(singular > tolerance * singular[0])) if singular[0] > 0 else 0
    if rank < num_knots:
        inside = np.searchsorted(knots, times[1:], side="left") - np.searchsorted(
            knots, times[:-1], side="right"
        )
        j = int(np.argmax(inside))
        outside = int(np.sum((knots < times[0]) | (knots > times[-1])))
        where = []
        if inside[j] >= 2:
            where.append(
                f"{int(inside[j])} knots fall strictly between the neighbouring observations at "
                f"t = {times[j]:.6g} and {times[j + 1]:.6g}"
            )
        if outside:
            where.append(f"{outside} knots lie outside the observed times")
        which = (
            "times of the observations of positive `weights`" if weighted else "observation times"
        )
        raise ValueError(
            f"`knots`: the {which} do not determine the {num_knots} knot values of "
            f"model={model!r} (rank {rank} of {num_knots}"
            + (f"; {' and '.join(where)}" if where else "")
            + (
                "). Spread the knots over the observed times or pass an int (evenly spaced knots)."
                if given
                else "), evenly spaced over the observed times: pass fewer knots, or knot times "
                "placed among the observations."
            )
        )


# --------------------------------------------------------------------------------------------------
# Public entry point


def fit_angular_velocity(
    times: ArrayLike,
    qs: ArrayLike,
    *,
    model: str = "constant",
    knots: int | ArrayLike | None = None,
    frame: str = "world",
    weights: ArrayLike | None = None,
    omega0: ArrayLike | None = None,
    substeps: int = 2,
    solver: optx.AbstractLeastSquaresSolver | None = None,
    max_steps: int = 256,
    polish: int = 8,
) -> AngularVelocityFit:
    r"""Fit an angular velocity to observed orientations by nonlinear least squares.

    The model is the orientation $q(t)$ with $q(t_0) = q_0$ driven by $\dot q = \tfrac12\tilde\omega q$
    (world frame) or $\tfrac12 q\tilde\omega$ (body frame); $q_0$ and ω are fitted together,
    minimising $\tfrac12\sum_k w_k |\rho(q(t_k), r_k)|^2$ with the sign-invariant residual
    $\rho = 2\operatorname{sgn}(w(e))\operatorname{vec}(e) \approx$ the error rotation vector in radians
    ($e$ the error rotation; see the module docstring). Solved by `optimistix` (Levenberg–Marquardt).

    - `model="constant"`: $q(t) = \exp(\omega(t - t_0)) \otimes q_0$ (world) or
      $q_0 \otimes \exp(\omega(t - t_0))$ (body), in closed form (`step`).
    - `model="piecewise_linear"` / `"spline"`: ω(t) is an `AngularVelocityCurve` through values at
      `knots` (linear, or the not-a-knot cubic spline). The model integrates from each observation time
      or knot to the next with `substeps` fourth-order Magnus steps (`integrate(..., method="magnus4")`):
      non-uniform times need no interpolated trajectory, and no step straddles a knot, where ω's
      slope or third derivative jumps. The model is not exact: its error falls as substeps⁻⁴.
      Measured on exact data (SciPy DOP853) from ω(t) with knot values ~2 rad/s, 6 knots: with 25
      observations over 6 s the default `substeps=2` leaves knot errors ~5e-3 rad/s and residuals
      ~2e-3 rad (substeps=4: 3e-4 and 1e-4; 8: 2e-5 and 7e-6); denser data need fewer substeps.
      When the fit's residuals are near the noise, refit with `substeps` doubled to check.

    **Starting point.** Found from the data unless `omega0` is given: the log-differences of
    neighbouring observations, $\omega_k = \log(r_{k+1} r_k^*)/Δt_k$ (`angular_velocity`, shortest
    rotation, so sign-invariant), averaged over the span (constant model) or fitted by linear least
    squares to the curve at the interval midpoints (time-varying models); $q_0$ starts at the first
    observation. Observations of weight 0 are skipped: the log-differences bridge them, and if the
    first observation has weight 0, $q_0$ starts at the first positively weighted one carried back
    to $t_0$ by the starting ω. This needs each interval to turn the body by less than half a turn
    (|ω|Δt < π); turns within 0.25 rad of π, whose direction noise can flip, are taken on the branch
    that continues the previous interval's rate, so a body turning by exactly π per interval is
    still fitted. The constant model also tolerates gaps: each interval's turn is taken on the
    branch θ + 2πk nearest to what the intervals' (duration-weighted) median rate predicts, so a
    minority of intervals may turn by more than π.
    Started at ω = 0 instead, Levenberg–Marquardt converges to a wrong local minimum as soon as the
    data span more than about half a turn.

    **Arguments:**

    - `times`: observation times, shape `(T,)`, strictly increasing, not necessarily uniform, T ≥ 3.
      Keep them in float64 (or relative to a recent origin) when they are large.
    - `qs`: observed orientations, shape `(T, 4)`; may mix q and −q; normalised on input.
    - `model`: `"constant"`, `"piecewise_linear"` or `"spline"`.
    - `knots`: time-varying models only: the number K of uniformly spaced knots on
      `[times[0], times[-1]]`, or the knot times `(K,)`; K ≥ 2 (piecewise linear) or ≥ 4 (spline),
      and K ≤ T − 1 (the T − 1 rotations between neighbouring observations determine 3 unknowns each).
      Explicit knot times must also be told apart by the observations: the (T − 1) × K matrix of the
      basis functions' integrals over the observation intervals must have rank K, which fails when
      knots bunch between two neighbouring observations, or when knots outside the observed times
      leave the observations unable to tell their values apart (for `"piecewise_linear"`: a knot
      beyond the first one past either end of the data; the first is determined through the curve's
      values inside). Checked when `knots` and `times` are concrete. Default: `max(minimum, min(20, T // 4))`.
    - `frame`: `"world"` or `"body"` (the frame ω is expressed in).
    - `weights`: optional non-negative per-observation weights `(T,)` (e.g. 1/σₖ²), at least two
      of them positive. A weight of 0 removes an observation (an outlier, say) from the fit and from
      the starting point; a small positive weight keeps it in the starting point's log-differences.
      For the time-varying models T above means the observations of positive weight: they alone
      determine the knots (counted, placed by default and checked against them when the weights are
      concrete; traced weights leaving fewer than K + 1 give `converged=False`).
    - `omega0`: optional starting guess: `(3,)`, or knot values `(K, 3)` for the time-varying models.
    - `substeps`: Magnus-4 steps per observation interval (time-varying models).
    - `solver`: an `optimistix` least-squares solver; default
      `optimistix.LevenbergMarquardt(rtol=1e-6, atol=1e-6)` (1e-4 in float32).
    - `max_steps`: the solver's step limit; reaching it gives `converged=False`, not an error.
      `converged=True` says only that the solver met its tolerances, not that the model fits: data
      outside the domain above (most intervals turning by more than π, say) can converge to a wrong
      minimum. Compare `loss` with what the noise gives, ½ Σ w_k · 3σ² for rotation-vector noise
      of σ per axis (the rms of a good fit's `residual_angles` is then about σ√3).
    - `polish`: at most this many `optimistix.GaussNewton` steps (tolerance 1e-12; 1e-6 in float32)
      after `solver`, taken if they converge: they reach the optimum to round-off, where the damped
      solver's loss-based acceptance test stalls ~1e-10 short of it on noisy data. 0 switches it off.

    **Returns:** an `AngularVelocityFit` (a PyTree) with `.omega` (array `(3,)` or an
    `AngularVelocityCurve`), `.q0`, `.residual_angles`, `.loss`, `.num_steps`, `.converged`.
    Outputs have the dtype of `qs` (float32 in, float32 out).

    **Errors:** a `ValueError` at trace time for fewer than 3 observations (5 for
    `model="spline"`, whose 4 knots need 4 relative rotations), mismatched shapes of
    `times`, `qs`, `weights`, `omega0`, bad `knots` (including more knots than the data determine,
    K > T − 1), `model`, `frame` or `solver`, and — when the data are concrete (not under
    `jit`/`vmap`) — non-finite or non-increasing times (or steps between them below the
    smallest normal number, which XLA flushes to zero), zero, non-finite or subnormal rows of `qs`,
    and explicit knot times the observations do not determine (see `knots`).

    **Batches:** `jax.vmap(fit_angular_velocity)(times, qs)` fits many independent bodies in one
    compiled call (`qs` of shape `(B, T, 4)`); every field of the result gains the leading axis B.

    **Gradients:** the fitted parameters are differentiable with respect to the data, the times and
    the weights, by the implicit function theorem applied to the stationarity condition
    $\sum_k w_k J_k^\top \rho_k = 0$ (`optimistix.internal.implicit_jvp`; forward and reverse mode).
    It is linear in the weights, so the derivative with respect to a weight of 0 is the finite
    $-H^{-1} J_k^\top \rho_k$ (through $\sqrt{w}$ it would be 0·∞). The loss's derivative with
    respect to $w_k$ is $\tfrac12|\rho_k|^2$.

    Example:
    ```python
    omega_true = jnp.array([0.3, -0.5, 0.8])
    times = jnp.linspace(0.0, 10.0, 200)
    qs = jaxquat.step(jaxquat.identity(), omega_true, times)  # exact observations, 1.6 turns
    fit = jaxquat.fit_angular_velocity(times, qs)
    assert jnp.allclose(fit.omega, omega_true, atol=1e-10)  # float64 (x64 on)
    ```
    """
    model = check_choice(model, _MODELS, "model")
    frame = check_frame(frame)
    times, observed, weights = _check_observations(times, qs, weights)
    num_obs = observed.shape[0]
    dtype = observed.dtype
    if model == "constant":
        if knots is not None:
            raise ValueError(
                "`knots` is only used by the time-varying models; got model='constant'."
            )
        knots = None
        value_shapes = [(3,)]
    else:
        knots = _check_knots(knots, times, model, num_obs, _used_times(times, weights))
        value_shapes = [(3,), (knots.shape[0], 3)]
    if omega0 is None:
        omega0 = _start(times, observed, weights, knots, model=model, frame=frame)
    else:
        omega0 = as_float_array(omega0, "omega0").astype(dtype)
        if omega0.shape not in value_shapes:
            expected = " or ".join(str(s) for s in value_shapes)
            raise ValueError(f"`omega0` must have shape {expected}; got {tuple(omega0.shape)}.")
        if not is_tracer(omega0) and not np.all(np.isfinite(np.asarray(omega0))):
            raise ValueError(f"`omega0` must be finite; got {np.asarray(omega0)}.")
        omega0 = jnp.broadcast_to(omega0, value_shapes[-1])
    return _fit(
        times,
        observed,
        weights,
        knots,
        omega0,
        model=model,
        frame=frame,
        substeps=_check_count(substeps, "substeps", 1),
        **_solver_options(solver, dtype, max_steps, polish),
    )


@eqx.filter_jit
def _start(times, observed, weights, knots, *, model, frame):
    """The starting ω (constant model) or knot values from log-differences of neighbouring observations.

    Jitted on its own, so that fits with and without a user's `omega0` share one compiled solver.
    """
    rates, midpoints, durations, valid = _interval_rates(times, observed, weights, frame)
    if model == "constant":  # the total rotation over the time it took
        durations = jnp.where(valid, durations, 0)
        # An interval over which the body turns by more than π (a gap in the data) shows the
        # shortest rotation instead: 3.5 rad seen as 2π − 3.5 the other way dragged the average of
        # 58 intervals at 10 rad/s to 9, from which the fit converged to 8.56 rad/s (85° rms,
        # converged=True). Each turn is therefore taken on the branch θ + 2πk nearest to the turn
        # that the intervals' weighted median rate predicts.
        # The median is weighted by duration (a short interval's rate carries noise σ/Δt), and also
        # taken over the intervals alone: gaps covering more than half the span by duration outvoted
        # 40 short intervals (ω 0.27 instead of 5, residuals of 3 rad, converged=True). Of the two
        # starts, the one whose rotation fits the observations better is kept.
        total = jnp.sum(durations)

        def through(median):
            turns = _nearest_branch(
                rates * durations[:, None], median[None, :] * durations[:, None]
            )
            # (At least two positive weights make the sum positive; a traced lane with fewer gets 0.)
            return jnp.sum(turns, axis=0) / jnp.where(total > 0, total, 1)

        tau = _relative_times(times, observed.dtype)

        def loss(omega):
            reference = _reference(times, observed, weights, omega, frame)
            args = (tau, observed, reference)
            residuals = _constant_residuals((jnp.zeros_like(omega), omega), args, frame)
            return _weighted_loss(residuals, weights)

        medians = jax.vmap(lambda w: _weighted_median(rates, w))(
            jnp.stack([durations, valid.astype(rates.dtype)])
        )
        starts = jax.vmap(through)(medians)  # by duration, by count
        losses = jax.vmap(loss)(starts)  # (one copy of the model to compile)
        return jnp.where(losses[1] < losses[0], starts[1], starts[0])
    # The curve is linear in its values: its basis functions are the curve through I_K. An
    # interval's rate carries noise σ/Δt, so intervals shorter than the median count in proportion
    # to their duration (longer ones, which may hide a turn past π, no more than the median's): one
    # interval of 1 ms among 25 over 6 s, with 0.01 rad of noise, pulled the start to a local
    # minimum of loss 6.4 instead of 0.003, converged=True, differently for times in ms (helper-53).
    basis = AngularVelocityCurve.through(knots, jnp.eye(knots.shape[0], dtype=rates.dtype), model)
    durations = jnp.where(valid, durations, 0)
    typical = _weighted_median(durations[:, None], valid.astype(rates.dtype))[0]
    rows = jnp.minimum(durations / jnp.where(typical > 0, typical, 1), 1)[:, None]
    return jnp.linalg.lstsq(rows * basis(times[0] + midpoints), rows * rates)[0]


def _weighted_median(values: Array, weights: Array) -> Array:
    """The weighted median of each column of `values` (n, d) with weights (n,) ≥ 0 (the lower one
    at a tie)."""
    order = jnp.argsort(values, axis=0)
    cumulative = jnp.cumsum(weights[order], axis=0)
    index = jnp.argmax(cumulative >= 0.5 * cumulative[-1:], axis=0)
    return jnp.take_along_axis(values, order, axis=0)[index, jnp.arange(values.shape[1])]


def _nearest_branch(turns: Array, predicted: Array) -> Array:
    """Each rotation vector θn̂ as (θ + 2πk)n̂, the same rotation, with the integer k that brings it
    nearest to `predicted` (a zero rotation is kept)."""
    angles = safe_norm(turns, axis=-1, keepdims=True)  # (zero turns: no NaN in reverse mode)
    axes = turns / jnp.where(angles > 0, angles, 1)
    along = jnp.sum(axes * predicted, axis=-1, keepdims=True)
    k = jnp.round((along - angles) / (2 * jnp.pi))
    return turns + (2 * jnp.pi) * k * axes


def _reference(times, observed, weights, omega, frame):
    """The chart's centre at t₀: the first positively weighted observation, carried back to t₀ at `omega`.

    Usually observation 0 itself. When that one has weight 0 (an outlier), centring the chart on it
    put the fit up to π away from its start, and the spline fits converged to a wrong minimum.
    """
    first = jnp.argmax(weights > 0)
    return step(observed[first], omega, -(times[first] - times[0]).astype(omega.dtype), frame=frame)


def _statistics(fitted, observed, weights, frame):
    """(residual angles, loss) of a fit."""
    residuals = _orientation_residuals(fitted, observed, frame)
    return angle_between(fitted, observed), _weighted_loss(residuals, weights)


@eqx.filter_jit
def _fit(
    times,
    observed,
    weights,
    knots,
    omega0,
    *,
    model,
    frame,
    substeps,
    solver,
    max_steps,
    polish,
):
    dtype = observed.dtype
    tau = _relative_times(times, dtype)
    delta0 = jnp.zeros((3,), dtype)
    if model == "constant":
        reference = _reference(times, observed, weights, omega0, frame)
        args = (tau, observed, reference)
        residual_fn = functools.partial(_constant_residuals, frame=frame)
        params, num_steps, converged = _solve(
            residual_fn, (delta0, omega0), args, weights, solver, max_steps, polish
        )
        q0, fitted = _constant_model(params, tau, reference, frame)
        omega = params[1]
    else:
        first = jnp.argmax(weights > 0)  # the curve's start at the midpoint of [t₀, t_first]
        start = AngularVelocityCurve.through(knots, omega0, model)(0.5 * (times[0] + times[first]))
        reference = _reference(times, observed, weights, start, frame)
        args = (times, observed, reference, knots)
        residual_fn = functools.partial(
            _curve_residuals, frame=frame, kind=model, substeps=substeps
        )
        params, num_steps, converged = _solve(
            residual_fn, (delta0, omega0), args, weights, solver, max_steps, polish
        )
        q0, omega, fitted = _curve_model(params, times, reference, knots, frame, model, substeps)
    residual_angles, loss = _statistics(fitted, observed, weights, frame)
    # Traced weights escape the ValueErrors for too few positive ones (two; for K knots, K + 1, as
    # K ≤ T − 1 needs): nothing was determined then, whatever the solver says.
    needed = 2 if knots is None else knots.shape[0] + 1
    converged = converged & (jnp.sum(weights > 0) >= needed)
    return AngularVelocityFit(
        omega=omega,
        q0=q0,
        t0=times[0],
        fitted=fitted,
        residual_angles=residual_angles,
        loss=loss,
        num_steps=num_steps,
        converged=converged,
        frame=frame,
        model=model,
    )


# --------------------------------------------------------------------------------------------------
# Torque-free rigid body


class RigidBodyFit(eqx.Module):
    """The result of `fit_rigid_body` (a PyTree: fits `jax.vmap` and `jax.jit`).

    **Fields:**

    - `inertia`: principal moments of inertia normalised to `inertia[0] = 1`, shape `(3,)`, in the body
      frame of the observations (torque-free motion only determines the ratios).
    - `omega0`: the body-frame angular velocity at `t0`, shape `(3,)` (rad/s).
    - `q0`: the fitted orientation (body → world) at `t0`, shape `(4,)`.
    - `t0`, `fitted`, `residual_angles`, `loss`, `num_steps`, `converged`: as in `AngularVelocityFit`.
    """

    inertia: Array
    omega0: Array
    q0: Array
    t0: Array
    fitted: Array
    residual_angles: Array
    loss: Array
    num_steps: Array
    converged: Array

    @property
    def inertia_ratios(self) -> Array:
        """(I₂/I₁, I₃/I₁), shape `(2,)`."""
        return self.inertia[..., 1:] / self.inertia[..., :1]


def _rigid_body_model(params, times, reference, method, substeps):
    """q0 and the orientations at `times` of the torque-free body with the parameters `params`."""
    delta, log_ratios, omega0 = params
    inertia = jnp.concatenate([jnp.ones((1,), log_ratios.dtype), jnp.exp(log_ratios)])
    q0 = _perturb(reference, delta, "body")

    def interval(state, bounds):
        start, end = bounds
        q, omega = simulate_rigid_body(
            *state,
            inertia,
            (end - start) / substeps,
            substeps,
            method=method,
            save="final",
            t0=start,
        )
        return (q, omega), q

    _, later = lax.scan(interval, (q0, omega0), (times[:-1], times[1:]))
    return q0, inertia, jnp.concatenate([q0[None], later], axis=0)


def _rigid_body_residuals(params, args, method, substeps):
    times, observed, reference = args
    _, _, model_qs = _rigid_body_model(params, times, reference, method, substeps)
    return _orientation_residuals(model_qs, observed, "body")


def _strided_rates(times: Array, qs: Array, weights: Array) -> tuple[Array, ...]:
    """Body rates over baselines of about 0.3 rad between positively weighted observations.

    Returns `(rates, midpoints, durations, starts, valid)`, each `(T - 1, ...)` with the valid
    entries first, in time order: a rate, its baseline's midpoint (relative to t₀) and duration,
    and the observation it starts from. Neighbouring observations of noisy data give rates with
    noise ~σ/Δt, which dense sampling makes as large as ω itself (σ = 1e-2 rad at Δt = 0.04 s); a
    baseline of s observations (s chosen from the median turn per interval, so that it stays far
    below π) divides that by s.
    """
    num = qs.shape[0]
    order = jnp.argsort(weights <= 0, stable=True)  # the observations used, first and in order
    count = jnp.sum(weights > 0)
    tau = (times - times[0])[order]
    qs = qs[order]
    index = jnp.arange(num - 1)
    turns = safe_norm(angular_velocity(qs, 1.0, frame="body"), axis=-1)  # angles
    typical = jnp.nanmedian(jnp.where(index + 1 < count, turns, jnp.nan))
    stride = jnp.clip(jnp.round(0.3 / typical), 1, jnp.maximum(count // 4, 1)).astype(index.dtype)
    stride = jnp.where(jnp.isfinite(typical) & (typical > 0), stride, 1)
    end = jnp.minimum(index + stride, num - 1)
    valid = index + stride < count
    durations = jnp.where(valid, tau[end] - tau[index], 1).astype(qs.dtype)
    pairs = jnp.stack([qs[index], qs[end]])
    rates = angular_velocity(pairs, durations[None], frame="body")[0]
    midpoints = (0.5 * (tau[index] + tau[end])).astype(qs.dtype)
    return rates, midpoints, durations, qs[index], valid


def _equation_error_inertia(rates: Array, midpoints: Array, valid: Array) -> tuple[Array, Array]:
    """Principal moments (I₁ = 1) that best satisfy Euler's equations I ω̇ = (I ω) × ω on sampled ω.

    The equations are used integrated over windows of an eighth of the valid samples (`valid` is a
    prefix): I ⊙ (ω(b) − ω(a)) = ∫ₐᵇ (I ω) × ω dt, trapezoidal. They are linear and homogeneous in
    I: stacking them gives A I = 0, solved by A's last right singular vector. Differentiating noisy
    rates instead (ω̇ from neighbouring samples) gave starts of I₃/I₁ = 65 or 2e15 for a body of 2.6
    at σ = 1e-3 rad, from which the fit did not converge.
    """
    num = rates.shape[0]
    window = jnp.maximum(jnp.sum(valid) // 8, 1)
    both = (valid[1:] & valid[:-1])[:, None]
    lengths = jnp.where(both, jnp.diff(midpoints)[:, None], 0)
    start = jnp.arange(num)
    end = jnp.minimum(start + window, num - 1)
    used = valid[end][:, None] & (start + window < num)[:, None]

    def euler_residual(inertia):
        torque_free = cross(inertia * rates, rates)
        increments = 0.5 * (torque_free[1:] + torque_free[:-1]) * lengths
        integral = jnp.concatenate([jnp.zeros_like(rates[:1]), jnp.cumsum(increments, axis=0)])
        change = inertia * (rates[end] - rates[start]) - (integral[end] - integral[start])
        return jnp.where(used, change, 0)

    ones = jnp.ones((3,), rates.dtype)
    system = jax.jacfwd(lambda inertia: euler_residual(inertia[None, :]).reshape(-1))(ones)
    _, singular, vt = jnp.linalg.svd(system, full_matrices=False)
    inertia = vt[-1] * jnp.sign(jnp.sum(vt[-1]))
    inertia = inertia / jnp.max(jnp.abs(inertia))
    # Data that leave I undetermined (a steady spin about a principal axis, a body at rest: no
    # clear null vector, or moments of mixed signs) start from a sphere. The floor on the smallest
    # moment keeps I₁ = 1 finite: the SVD gave 1 : 2e15 : 1e8 there, and the fit went NaN.
    positive = jnp.min(inertia) > 1e-3
    determined = (singular[-1] < 0.3 * singular[-2]) & positive
    # Also returned: the null vector itself whenever its moments are positive. An axisymmetric body
    # in free precession leaves the equations nearly degenerate (singular values 9.7, 2.1, 0.68 for
    # 1 : 1 : 2.5), and the sphere started the fit in a wrong minimum (`_rigid_body_start` chooses).
    candidate = jnp.where(positive, inertia, ones)
    inertia = jnp.where(determined, inertia, ones)
    return inertia / inertia[0], candidate / candidate[0]


_RIGID_BODY_POSITIVE = (
    3,
    "three",
    "for a rigid body (8 unknowns: q0, two inertia ratios and ω0; 3 equations per observation)",
)


def fit_rigid_body(
    times: ArrayLike,
    qs: ArrayLike,
    *,
    weights: ArrayLike | None = None,
    inertia0: ArrayLike | None = None,
    omega0: ArrayLike | None = None,
    method: str = "cf4",
    substeps: int = 4,
    solver: optx.AbstractLeastSquaresSolver | None = None,
    max_steps: int = 256,
    polish: int = 8,
) -> RigidBodyFit:
    r"""Fit the inertia ratios and initial angular velocity of a torque-free rigid body to orientations.

    The model is Euler's equations for principal moments $I = \mathrm{diag}(1, e^{a}, e^{b})$ (the body
    frame of the observations is taken to be the principal frame; the overall scale of I is not
    observable without torques), $I\dot\omega = (I\omega)\times\omega$, $\dot q = \tfrac12 q\tilde\omega$,
    integrated by `simulate_rigid_body` from each observation time to the next with `substeps` steps
    of `method`. Fitted: $q_0$, $(a, b)$ and the body-frame $\omega_0$ (8 parameters), by
    Levenberg–Marquardt on the sign-invariant residual of `fit_angular_velocity` (body frame).

    **Starting point** (unless given): body rates from log-differences of observations a baseline of
    about 0.3 rad apart (`angular_velocity(..., frame="body")`; a longer baseline than neighbouring
    observations divides the rates' noise ~σ/Δt). The inertia from the *equation error*: Euler's
    equations integrated over windows, $I \odot (\omega(b) - \omega(a)) = \int_a^b
    (I\omega)\times\omega\,dt$, are linear and homogeneous in I, which one SVD gives up to scale
    (a sphere when the data leave it undetermined). ω₀ from the conserved world-frame angular
    momentum $q\,(I\omega)\,q^*$ averaged over all the rates. $q_0$ from the first observation (or
    the first positively weighted one, carried back to $t_0$). Observations of weight 0 are skipped.
    From there the fit is *continued*: the first quarter of the span is fitted, then the first half,
    each from the last, then the whole (a long span has many local minima around a rough start).

    Measured on SciPy DOP853 data of nine kinds (30 to 2,000 observations over 3 to 60 s, σ = 1e-3 to
    1e-2 rad, outliers of weight 0 at the ends and inside; six noise draws each): all 54 fits
    converge with χ² consistent with its degrees of freedom. Differentiating the noisy rates and
    extrapolating ω₀ from the first two, as before, none of them did.

    **Arguments:**

    - `times` `(T,)`, `qs` `(T, 4)`, `weights` `(T,)`: as in `fit_angular_velocity`, with at least
      three observations of positive weight (8 unknowns, 3 equations each; traced weights leaving
      fewer give `converged=False`).
    - `inertia0`: optional starting principal moments `(3,)` (any scale). `omega0`: optional starting
      body-frame ω at `times[0]`, `(3,)`.
    - `method`, `substeps`: the integrator (see `simulate_rigid_body`) and its steps per interval.
      The default (cf4, 4 steps) is not exact: on exact data (I = 1 : 1.6 : 2.3, 100 observations
      over 10 s) it leaves 2e-9 in the ratios at |ω₀| = 1.2 rad/s and 7e-7 at 4.4 rad/s (the
      method's h⁴ error grows with the spin), and with 40 observations at σ = 1e-3 it moves the
      fit by ~15 % of its statistical spread. Raise `substeps` for sparse, precise data.
    - `solver`, `max_steps`, `polish`: as in `fit_angular_velocity` (`converged` likewise says only
      that the solver met its tolerances).

    **Returns:** a `RigidBodyFit`: `.inertia` (I₁ = 1), `.inertia_ratios`, `.omega0`, `.q0`,
    `.residual_angles`, `.loss`, `.num_steps`, `.converged`.

    Identifiability: a steady spin about a principal axis does not determine the ratios; an
    asymmetric body tumbling for at least a fraction of its nutation period does.
    """
    times, observed, weights = _check_observations(times, qs, weights, _RIGID_BODY_POSITIVE)
    dtype = observed.dtype
    starts = []
    for name, value in (("inertia0", inertia0), ("omega0", omega0)):
        if value is not None:
            value = as_float_array(value, name).astype(dtype)
            if value.shape != (3,):
                raise ValueError(f"`{name}` must have shape (3,); got {tuple(value.shape)}.")
            if not is_tracer(value) and not np.all(np.isfinite(np.asarray(value))):
                raise ValueError(f"`{name}` must be finite; got {np.asarray(value)}.")
        starts.append(value)
    inertia0, omega0 = starts
    if inertia0 is not None and not is_tracer(inertia0) and np.any(np.asarray(inertia0) <= 0):
        raise ValueError(f"`inertia0` must be positive; got {np.asarray(inertia0)}.")
    # Options before the starting point is computed (a typo cost its compilation first).
    method = check_choice(method, ("cf4", "midpoint", "euler", "rk4", "naive"), "method")
    substeps = _check_count(substeps, "substeps", 1)
    options = _solver_options(solver, dtype, max_steps, polish)
    if inertia0 is None or omega0 is None:
        inertia_start, omega_start = _rigid_body_start(times, observed, weights)
        inertia0 = inertia_start if inertia0 is None else inertia0
        omega0 = omega_start if omega0 is None else omega0
    return _fit_rigid_body(
        times,
        observed,
        weights,
        inertia0,
        omega0,
        method=method,
        substeps=substeps,
        **options,
    )


@eqx.filter_jit
def _rigid_body_start(times, observed, weights):
    """Starting (principal moments, body ω at t0) from log-differences and the equation error."""
    rates, midpoints, durations, starts, valid = _strided_rates(times, observed, weights)
    inertia, candidate = _equation_error_inertia(rates, midpoints, valid)
    # ω₀ from the conserved world-frame angular momentum L = q (I ω) q*, averaged over every
    # baseline (q at its midpoint), carried to the first used observation. Extrapolating the first
    # rates back to t₀ instead was off by 0.1–0.4 rad/s on noisy data (up to 17 rad/s after a gap
    # of 1 ms), and long fits then converged to a wrong minimum.
    middles = multiply(starts, from_rotvec(0.5 * rates * durations[:, None]))

    def with_omega(inertia):
        momenta = rotate_unchecked(inertia[None, :] * rates, middles)
        momentum = jnp.sum(jnp.where(valid[:, None], momenta, 0), axis=0) / jnp.sum(valid)
        return inertia, rotate_unchecked(momentum, conjugate(starts[0])) / inertia

    # When the equation error leaves I undetermined, its null vector (if positive) competes with
    # the sphere: the start whose motion fits the first quarter of the span better is kept (the
    # stages of `_continue` then take it on). A determined I is both candidates at once.
    inside = jnp.where(times <= times[0] + 0.25 * (times[-1] - times[0]), weights, 0)

    def quarter_loss(start):
        inertia, omega = start
        params = (jnp.zeros_like(omega), jnp.log(inertia[1:] / inertia[0]), omega)
        args = (times, observed, _reference(times, observed, weights, omega, "body"))
        residuals = _rigid_body_residuals(params, args, "cf4", 2)
        loss = _weighted_loss(residuals, inside)
        return jnp.where(jnp.isfinite(loss), loss, jnp.inf)

    # (Both candidates in one vmapped evaluation: one copy of the rigid-body model to compile.)
    candidates = jax.vmap(with_omega)(jnp.stack([inertia, candidate]))
    losses = jax.vmap(quarter_loss)(candidates)
    better = losses[1] < losses[0]
    return jax.tree_util.tree_map(lambda c: jnp.where(better, c[1], c[0]), candidates)


def _continue(residual_fn, params0, args, weights, times, solver, max_steps: int):
    """The start for the whole span: fits of its first quarter, then its first half, each from the last.

    A tumbling body's orientation depends ever more sensitively on ω₀ and I as time goes on, so a fit
    of a long span from a rough start has many local minima: 30 observations over 15 s (σ = 1e-3 rad)
    converged to χ²/dof ~ 2e5 for 3 of 6 noise draws, and to ~1 for all of them this way. The
    stages only choose the start (no derivative flows through them); a stage with fewer than 4
    positively weighted observations, or a non-finite result, is skipped.
    """
    params0, args, weights, times = lax.stop_gradient((params0, args, weights, times))
    data_dtype = weights.dtype
    span = times[-1] - times[0]

    def stage(y, fraction):
        inside = jnp.where(times <= times[0] + fraction * span, weights, 0)
        fitted, _ = _solve_primal((residual_fn, y, args, inside, solver, max_steps, 0))
        finite = jnp.all(jnp.stack([jnp.all(jnp.isfinite(leaf)) for leaf in fitted]))
        ok = (jnp.sum(inside > 0) >= 4) & finite
        return jax.tree_util.tree_map(lambda a, b: jnp.where(ok, a, b), fitted, y), None

    fractions = jnp.asarray([0.25, 0.5], times.dtype)
    y, _ = lax.scan(stage, _cast(params0, _solver_dtype(data_dtype)), fractions)
    return _cast(y, data_dtype)


@eqx.filter_jit
def _fit_rigid_body(
    times, observed, weights, inertia0, omega0, *, method, substeps, solver, max_steps, polish
):
    reference = _reference(times, observed, weights, omega0, "body")
    log_ratios0 = jnp.log(inertia0[1:] / inertia0[0])
    params0 = (jnp.zeros((3,), observed.dtype), log_ratios0, omega0)
    args = (times, observed, reference)
    residual_fn = functools.partial(_rigid_body_residuals, method=method, substeps=substeps)
    params0 = _continue(residual_fn, params0, args, weights, times, solver, max_steps)
    params, num_steps, converged = _solve(
        residual_fn, params0, args, weights, solver, max_steps, polish
    )
    # 8 unknowns (q0, two log ratios, ω0), 3 equations per observation: at least 3 observations of
    # positive weight (concrete weights are checked in `fit_rigid_body`).
    converged = converged & (jnp.sum(weights > 0) >= _RIGID_BODY_POSITIVE[0])
    q0, inertia, fitted = _rigid_body_model(params, times, reference, method, substeps)
    residual_angles, loss = _statistics(fitted, observed, weights, "body")
    return RigidBodyFit(
        inertia=inertia,
        omega0=params[2],
        q0=q0,
        t0=times[0],
        fitted=fitted,
        residual_angles=residual_angles,
        loss=loss,
        num_steps=num_steps,
        converged=converged,
    )
