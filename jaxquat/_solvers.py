r"""diffrax vector fields for orientation kinematics, and Lie-group solvers that stay on the unit sphere.

Two vector fields, both `f(t, q, args)` callables for `diffrax.ODETerm`:

- `kinematic_vector_field(omega)`: the plain rate $\dot q = \tfrac12 \tilde ω q$ (world) or
  $\tfrac12 q \tilde ω$ (body): *the* ODE, for every solver (jaxquat's and diffrax's own);
- `corrected_vector_field(omega, dt)`: the seed's $\dot q_{Δt} = \frac{\tan(|ω|Δt/2)}{|ω|Δt}\tilde ω q$, a
  different ODE made for exactly one scheme: `NormalizedEuler` with the constant step `dt`.

Solvers (`diffrax.AbstractSolver` subclasses): `NormalizedEuler` (ambient Euler, then renormalise) and
the Lie-group methods `LieEuler`, `ExpMidpoint`, `Magnus4`, `Magnus6`, `Magnus8`, `CF4` and the adaptive `RKMK45`. The Lie-group
solvers take any term whose vector field returns the ambient $\dot q ∈ ℝ^4$ and recover the world-frame
rotation increment of a stage themselves, $u = 2\,\mathrm{vec}(Δq ⊗ q^*)/|q|^2$ with $Δq$ the term's
`prod` of $\dot q$ and the step's control (docs/numerics.md §3). This works for world- and body-frame fields,
discards any radial part of $\dot q$, and handles a negative time direction. The same terms run under
stock diffrax solvers.

States: a quaternion array `q` of shape `(..., 4)`, or a tuple whose first element is the state's
quaternion, e.g. `(q, x)` with `x` any PyTree of arrays (angular velocity, position, ...). The Lie method
acts on `q`, the matching Runge–Kutta scheme on every other leaf. (The first-element rule also covers
the augmented state of `diffrax.BacksolveAdjoint`, so RK-type jaxquat solvers work under it.)

Derivatives: reverse mode (`jax.grad`, `jax.jacrev`) through `diffrax.diffeqsolve` with diffrax's
default `RecursiveCheckpointAdjoint`; forward mode (`jax.jacfwd`, `jax.jvp`) needs
`adjoint=diffrax.ForwardMode()` (the default adjoint is a `custom_vjp`, which JAX cannot push
tangents through). Both give the same derivatives. `diffrax.BacksolveAdjoint` (RK-type solvers)
differentiates the ODE, which keeps |q0|, and cannot see the first step normalising a non-unit q0:
it returns the gradient at q0/|q0| without the normalisation's Jacobian (wrong by 0.77 in a test
where |q0| = 1.3; at a unit q0 its tangent part is right but it keeps a radial part, 1.18 in one case,
which the other adjoints project out). Differentiate through `jaxquat.normalize(q0)`.
"""

from __future__ import annotations

import functools
import inspect
import math
from collections.abc import Callable
from typing import Any, ClassVar

import diffrax
import equinox as eqx
import jax.numpy as jnp
import jax.tree_util as jtu
import numpy as np
from jax import lax
from jaxtyping import Array, PyTree

from ._algebra import conjugate, from_vector, log, multiply
from ._integrate import (
    _GL4_INNER,
    _GL4_OUTER,
    _GL4_SPREAD,
    _STAGE_FRACTIONS,
    _check_finite_scalar,
    _depends_on,
    _depends_on_q,
    magnus6_exponent,
    magnus8_exponent,
)
from ._kinematics import corrected_rate, rate
from ._numerics import (
    broadcasts_to,
    check_callable,
    check_frame,
    check_trailing,
    cross,
    safe_norm,
    sum_squares,
)
from ._rotation import from_rotvec, rotate

__all__ = [
    "corrected_vector_field",
    "kinematic_vector_field",
    "NormalizedEuler",
    "LieEuler",
    "ExpMidpoint",
    "Magnus4",
    "Magnus6",
    "Magnus8",
    "CF4",
    "RKMK45",
]

_SQRT3 = math.sqrt(3.0)
# The fixed turns by which `_Magnus._probe` moves q0: 2 rad about (1, 2, 3)/√14 and about the
# perpendicular (1, 1, −1)/√3 (nothing special; two, because a rate along one turn's axis, or a q
# read only through the body image of that axis, does not change under that turn).
_PROBE_TURNS = tuple(
    (math.cos(1.0),) + tuple(math.sin(1.0) * c / math.sqrt(sum(a * a for a in axis)) for c in axis)
    for axis in ((1.0, 2.0, 3.0), (1.0, 1.0, -1.0))
)
_SQRT15 = math.sqrt(15.0)

_BACKSOLVE_HINT = (
    "`diffrax.BacksolveAdjoint` passes the augmented state (y, a_y, a_args, a_terms) to the solver; "
    "use the default `diffrax.RecursiveCheckpointAdjoint()` (exact discrete gradients), "
    "`diffrax.ForwardMode()`, or `diffrax.BacksolveAdjoint(solver=diffrax.Tsit5())`."
)


# ----------------------------------------------------------------------------------------------------
# Vector fields


def _takes_args(fn: Callable) -> bool:
    """True if `fn` can be called with three positional arguments `(t, q, args)`."""
    try:
        signature = inspect.signature(fn)
    except (TypeError, ValueError):
        return False
    try:
        signature.bind(None, None, None)
    except TypeError:
        return False
    return True


class _KinematicField(eqx.Module):
    """`f(t, q, args)` = the plain or the seed's corrected quaternion rate (a PyTree: ω, dt are leaves)."""

    omega: Any
    dt: Array | None
    frame: str = eqx.field(static=True)
    omega_takes_args: bool = eqx.field(static=True)

    def __call__(self, t, q, args):
        if not eqx.is_array_like(q):
            raise ValueError(
                "the jaxquat vector fields return q̇ for a state `q` of shape (..., 4); got a "
                f"{type(q).__name__}. For a tuple state (q, x) write "
                "`lambda t, y, args: (field(t, y[0], args), g(t, y, args))`."
            )
        q = check_trailing(q, 4, "q")
        if callable(self.omega):
            omega = self.omega(t, q, args) if self.omega_takes_args else self.omega(t, q)
        else:
            omega = self.omega
        omega = check_trailing(omega, 3, "omega").astype(q.dtype)
        batch = tuple(q.shape[:-1])
        if not broadcasts_to(omega.shape[:-1], batch):
            raise ValueError(
                f"`omega` must have shape (..., 3) with leading axes broadcasting to those of the "
                f"state `q` {batch}; got shape {tuple(omega.shape)} for q of shape {tuple(q.shape)}."
            )
        if self.dt is None:
            return rate(q, omega, frame=self.frame)
        return corrected_rate(q, omega, self.dt.astype(q.dtype), frame=self.frame)


def _make_field(omega, dt, frame) -> _KinematicField:
    frame = check_frame(frame)
    if callable(omega):
        takes_args = _takes_args(omega)
        if not takes_args:
            check_callable(omega, "omega", "omega(t, q) or omega(t, q, args)", 2)
    else:
        omega = check_trailing(omega, 3, "omega")
        takes_args = False
    return _KinematicField(omega, dt, frame, takes_args)


def kinematic_vector_field(omega, *, frame: str = "world") -> Callable[[Any, Array, Any], Array]:
    r"""The quaternion kinematics $\dot q = \tfrac12 \tilde ω q$ as a diffrax vector field `f(t, q, args)`.

    The seed's equation quatRateOfChange (world frame), or $\tfrac12 q\tilde ω$ with `frame="body"`.
    This is the exact ODE: use it with every Lie-group solver of jaxquat (`LieEuler`, `ExpMidpoint`,
    `Magnus4`, `CF4`, `RKMK45`) and with diffrax's own solvers.

    **Arguments:**

    - `omega`: the angular velocity in rad/s: an array of shape `(..., 3)` (constant; broadcast
      against `q`), or a callable `omega(t, q)` returning `(..., 3)` — a `jaxquat.sampled(omegas, dt)`
      object, any function, or an `equinox.Module` whose fields are the parameters. If the callable
      takes three positional arguments it is called as `omega(t, q, args)` with `diffeqsolve`'s `args`.
      Pass parameters as PyTree fields or through `args` (not closed over) so that every adjoint,
      including `diffrax.BacksolveAdjoint`, sees them.
    - `frame`: `"world"` (ω in world coordinates) or `"body"`.

    **Returns:** an `equinox.Module` `f` with `f(t, q, args)` = q̇, shape `(..., 4)`, in `q`'s dtype.

    Example:
    ```python
    term = diffrax.ODETerm(jaxquat.kinematic_vector_field(jnp.array([0.0, 0.0, 1.0])))
    sol = diffrax.diffeqsolve(term, jaxquat.LieEuler(), 0.0, 1.0, 0.1, jaxquat.identity())
    ```
    """
    return _make_field(omega, None, frame)


def corrected_vector_field(
    omega, dt, *, frame: str = "world"
) -> Callable[[Any, Array, Any], Array]:
    r"""The seed's corrected rate $\dot q_{Δt} = \frac{\tan(|ω|Δt/2)}{|ω|Δt}\,\tilde ω q$ as a vector field.

    Equation quatRateOfChangeCorrected of the seed notes (README, Sources). One Euler step of size
    exactly `dt` followed by renormalisation is the rotation $\exp(ωΔt) ⊗ q$ (docs/numerics.md §1), so
    `diffeqsolve(ODETerm(corrected_vector_field(ω, h)), NormalizedEuler(), t0, t1, dt0=h, ...)`
    reproduces the seed's scheme (= `jaxquat.integrate(..., method="euler")`): exact for constant or
    piecewise-constant (sampled) ω.

    !!! warning

        This field is *not* the kinematics: it is the plain rate scaled by
        $\frac{2\tan(θ/2)}{θ} = 1 + θ^2/12 + …$, $θ = |ω|Δt$. Any solver other than `NormalizedEuler` with
        step `dt` integrates that different ODE faithfully and so rotates too fast by
        $(κ − 1)|ω|T ≈ θ^2|ω|T/12$: with `diffrax.Tsit5` at |ω| = 1 rad/s, Δt = 0.1 s, T = 8 s the error
        is 6.7e-3 rad, where `kinematic_vector_field` gives 3e-11 (measured; jaxquat's Lie-group solvers
        likewise). Use `kinematic_vector_field` for everything else.

    **Arguments:**

    - `omega`: as for `kinematic_vector_field` (array `(..., 3)`, callable `omega(t, q)` or
      `omega(t, q, args)`, or `jaxquat.sampled(omegas, dt)`).
    - `dt`: the step the correction is made for (a scalar; must equal the solver's constant step:
      `NormalizedEuler` raises an `equinox.EquinoxRuntimeError` at run time on a step that differs,
      such as a last step clipped to a t1 that is not t0 plus a multiple of dt).
    - `frame`: `"world"` or `"body"`.

    **Returns:** an `equinox.Module` `f` with `f(t, q, args)` = q̇_Δt, shape `(..., 4)`.

    At ω = 0 the factor is its series (value ½, correct gradient); see `jaxquat.corrected_rate`.
    """
    dt = _check_finite_scalar(dt, "dt")
    return _make_field(omega, dt, frame)


# ----------------------------------------------------------------------------------------------------
# State handling and Lie-algebra helpers


def _is_array(x) -> bool:
    return eqx.is_array_like(x) and not isinstance(x, (tuple, list, dict))


def _state_split(y, solver_name: str):
    """Split a state into its quaternion (first leaf) and the other leaves; validate at trace time."""
    head = y
    while isinstance(head, tuple) and len(head) > 0:
        head = head[0]
    if not _is_array(head):
        raise ValueError(
            f"`y0` of {solver_name} must be a quaternion array `q` of shape (..., 4) or a tuple "
            f"`(q, x)` whose first element is `q`; got {type(y).__name__}. {_BACKSOLVE_HINT}"
        )
    leaves, treedef = jtu.tree_flatten(y)
    q = leaves[0]
    if jnp.ndim(q) == 0 or jnp.shape(q)[-1] != 4:
        raise ValueError(
            f"`y0` of {solver_name}: the quaternion (first element of the state) must have shape "
            f"(..., 4); got shape {tuple(jnp.shape(q))}. {_BACKSOLVE_HINT}"
        )
    return q, leaves[1:], treedef


def _join(treedef, q, xs):
    return jtu.tree_unflatten(treedef, [q] + list(xs))


def _leaves(tree, treedef):
    """The leaves of `tree` (which has the state's structure): (quaternion leaf, other leaves)."""
    leaves = treedef.flatten_up_to(tree)
    return leaves[0], leaves[1:]


def _lin(coeffs, arrays, base=None):
    """base + Σ c_j a_j over Python-float coefficients (zero terms skipped, dtype kept)."""
    out = base
    for c, a in zip(coeffs, arrays, strict=True):
        if c == 0.0:
            continue
        term = a if c == 1.0 else c * a
        out = term if out is None else out + term
    if out is None:
        out = jnp.zeros_like(arrays[0])
    return out


def _lin_leaves(coeffs, leaf_lists, base):
    """Leaf-wise `base + _lin` over lists of leaves (the non-quaternion part of the state)."""
    return [_lin(coeffs, [ks[i] for ks in leaf_lists], b) for i, b in enumerate(base)]


def _increment(dq: Array, q: Array) -> Array:
    r"""World-frame rotation vector $u = 2\,\mathrm{vec}(Δq ⊗ q^*)/|q|^2$ of an ambient increment Δq at q."""
    p = multiply(dq, conjugate(q))
    return 2.0 * p[..., 1:] / sum_squares(q, keepdims=True)


def _body_increment(dq: Array, q: Array) -> Array:
    r"""Body-frame rotation vector $2\,\mathrm{vec}(q^* ⊗ Δq)/|q|^2$."""
    p = multiply(conjugate(q), dq)
    return 2.0 * p[..., 1:] / sum_squares(q, keepdims=True)


def _dexpinv(u: Array, v: Array) -> Array:
    r"""$\mathrm{dexp}^{-1}_u(v) ≈ v − \tfrac12 u×v + (\tfrac1{12} + \tfrac{|u|^2}{720})\,u×(u×v)$ on so(3).

    The exact coefficient is $c(θ) = (1 − (θ/2)\cot(θ/2))/θ^2 = 1/12 + θ^2/720 + θ^4/30240 + …$; the series
    through $\mathrm{ad}_u^4$ keeps RKMK methods of order ≤ 5 at their order (Munthe-Kaas 1999), has no
    singularity at θ = 2π, and is exact whenever u ∥ v (constant ω) in exact arithmetic (round-off
    across u is amplified by about $θ^2/12 + θ^4/720$: see `RKMK45`).
    """
    uv = cross(u, v)
    coeff = 1.0 / 12.0 + sum_squares(u, keepdims=True) * (1.0 / 720.0)
    return v - 0.5 * uv + coeff * cross(u, uv)


def _unit(q: Array) -> Array:
    # Renormalising each step keeps ||q| − 1| at one rounding: without it the product's rounding
    # drifts |q| systematically on smooth problems (−7e-17 per CF4 step on coning, linear in time).
    return q / jnp.sqrt(sum_squares(q, keepdims=True))


def _exp_left(u: Array, q: Array) -> Array:
    """exp(u) ⊗ q for a rotation vector u, renormalised."""
    return _unit(multiply(from_rotvec(u), q))


def _exp_stage(u: Array, q: Array) -> Array:
    """exp(u) ⊗ q without renormalising (internal stages: |exp(u) ⊗ q| = |q| to a few ulp)."""
    return multiply(from_rotvec(u), q)


def _rotvec_between(q0: Array, q1: Array) -> Array:
    """The rotation vector U with exp(U) ⊗ q0 = q1 exactly (same sheet; |U| ≤ 2π, no sign fix)."""
    return 2.0 * log(multiply(q1, conjugate(q0)))[..., 1:]


def _nearest_turn(u: Array, guess: Array) -> Array:
    """The rotation vector u + 4πk·û nearest to `guess` (k an integer): the same quaternion,
    exp(u + 4πk û) = exp(u), on the branch a step's own increments point to. `_rotvec_between` gives
    |u| ≤ 2π, so a step turning further (|ω|h > 2π) needs the branch for its dense output to turn the
    whole way between the steps (a CF4 step of 7 rad was interpolated through 7 − 4π, 2 rad off)."""
    size = safe_norm(u, keepdims=True)
    guess_size = safe_norm(guess, keepdims=True)
    has_axis = size > 0
    axis = jnp.where(has_axis, u, guess) / jnp.where(
        has_axis, size, jnp.where(guess_size > 0, guess_size, 1.0)
    )
    turns = lax.stop_gradient(
        jnp.round((jnp.sum(guess * axis, -1, keepdims=True) - size) / (4 * math.pi))
    )
    return jnp.where(turns == 0, u, u + (4 * math.pi) * turns * axis)


def _step_rotvec(q0: Array, q1: Array, guess: Array, slack: float = 8.0) -> Array:
    """The rotation vector U with exp(U) ⊗ q0 = q1 (to `slack` ulp) nearest to `guess`.

    `_rotvec_between` takes U's axis from vec(q1 ⊗ q0*), whose length is |sin(|U|/2)|: for a step
    turning by nearly 2πk that vector is round-off, and its direction (U's axis) is noise. A CF4 step
    of exactly 2π (4π) about a fixed axis was interpolated about a random axis, 0.26 (1.3) rad off
    mid-step in float64; in float32 0.3 rad off for steps within 1e-8 of 2π. Here the part of
    vec(q1 ⊗ q0*) across `guess` is shrunk by `slack` ulp (the quaternion moves by at most that, so
    the dense output still ends at q1 to round-off) and a vanishing vector part takes `guess`'s axis.
    """
    d = multiply(q1, conjugate(q0))
    w, v = d[..., :1], d[..., 1:]
    guess_size = safe_norm(guess, keepdims=True)
    has_guess = guess_size > 0
    g_hat = jnp.where(has_guess, guess, 0.0) / jnp.where(has_guess, guess_size, 1.0)
    along = jnp.sum(v * g_hat, -1, keepdims=True) * g_hat
    across = v - along
    across_size = safe_norm(across, keepdims=True)
    tol = slack * jnp.finfo(d.dtype).eps * jnp.sqrt(sum_squares(d, keepdims=True))
    big = across_size > tol
    shrink = jnp.where(big, 1.0 - tol / jnp.where(big, across_size, 1.0), 0.0)
    # Only for a step of at least half a turn (the whole-turn case above). A small step's v is
    # resolved to absolute round-off, which is harmless in its value, but taking it apart along
    # ĝ = guess/|guess| put 1/|guess| into the derivative: the dense output's Jacobian in ω was
    # 5e-6 off at |ω|h = 1e-12, O(1) at 1e-18, 1e12 at 1e-30 in float64, and 6.6e-6 at 1e-3, 1e-2
    # at 1e-6, 15 at 1e-10 in float32 (helper-62). Such a step keeps v and its exact derivative
    # (ω = 0 included: no guess, derivative 2·I).
    v = jnp.where(guess_size > math.pi, along + shrink * across, v)
    # 2 log(w, v): atan2(|v|, w) v/|v| without normalising v (whose direction's derivative cancels
    # two terms of size 1/|v| near a full turn); w < 0 with v = 0 (exactly -1): `guess`'s axis.
    u = 2.0 * log(jnp.concatenate([w, v], axis=-1))[..., 1:]
    minus_one = (w < 0) & ~jnp.any(v != 0, axis=-1, keepdims=True)
    u = jnp.where(minus_one, (2 * math.pi) * g_hat, u)
    return _nearest_turn(u, guess)


def _eval_f(terms, t, treedef, q, xs, args):
    return terms.vf(t, _join(treedef, q, xs), args)


def _apply_control(terms, f, control, treedef):
    dq, dxs = _leaves(terms.prod(f, control), treedef)
    return dq, dxs


def _first_stage(terms, t0, y0, args, solver_state, made_jump):
    """The vector field at (t0, y0): the stored FSAL value unless a jump was made."""
    if isinstance(made_jump, bool):
        return terms.vf(t0, y0, args) if made_jump else solver_state
    return lax.cond(made_jump, lambda: terms.vf(t0, y0, args), lambda: solver_state)


# ----------------------------------------------------------------------------------------------------
# Dense output


def _rescale(t0, t, t1):
    width = t1 - t0
    safe = jnp.where(width == 0, jnp.ones_like(width), width)
    return jnp.where(width == 0, jnp.zeros_like(width), (t - t0) / safe)


def _polyeval(coeffs: Array, s: Array) -> Array:
    """Σ_{p=1..P} s^p coeffs[p-1] (no constant term; P = len(coeffs), Horner's rule)."""
    out = coeffs[-1]
    for c in coeffs[-2::-1]:
        out = c + s * out
    return s * out


class LiePolynomialInterpolation(diffrax.AbstractLocalInterpolation):
    r"""Dense output on the sphere: $q(s) = \exp(V(s)) ⊗ q_0$, $V$ a polynomial in
    $s = (t − t_0)/(t_1 − t_0)$ with $V(0) = 0$ (a world-frame rotation vector); other state leaves are
    polynomials in $s$ of the same degree.

    `RKMK45`: Tsitouras' fourth-order continuous extension applied in the Lie algebra,
    $V(s) = \sum_i b_i(s) K_i$ (quartic; the RKMK step is Tsit5 on the ODE of $V$, so Tsit5's dense
    output is its dense output). Cubic elsewhere: Lie-algebra Hermite interpolation when $V'(0)$,
    $V'(1) = \mathrm{dexp}^{-1}_{V(1)}(u_1)$ are known (`LieEuler`, `ExpMidpoint`, `CF4`), the geodesic
    $V(s) = sV(1)$ for `NormalizedEuler`, and the Magnus interpolant for `Magnus4/6/8`.
    $|q(s)| = 1$ for every $s$: $q_0$ is the step's initial quaternion normalised (jaxquat's solvers
    keep q on the unit sphere; a non-unit initial state is normalised by the first step).
    """

    t0: Any
    t1: Any
    y0: PyTree[Array]
    coeffs: PyTree[Array]

    def evaluate(self, t0, t1=None, left: bool = True) -> PyTree[Array]:
        del left
        if t1 is not None:
            return jtu.tree_map(lambda a, b: a - b, self.evaluate(t1), self.evaluate(t0))
        s = _rescale(self.t0, t0, self.t1)
        leaves, treedef = jtu.tree_flatten(self.y0)
        coeffs = treedef.flatten_up_to(self.coeffs)
        q0 = leaves[0]
        v = _polyeval(coeffs[0], s.astype(coeffs[0].dtype))
        q = multiply(from_rotvec(v), q0)
        xs = [
            x + _polyeval(c, s.astype(c.dtype)) for x, c in zip(leaves[1:], coeffs[1:], strict=True)
        ]
        return _join(treedef, q, xs)


# The name before `RKMK45`'s dense output became quartic (kept: it was exported).
LieCubicInterpolation = LiePolynomialInterpolation


def _hermite(y0_delta, k0, k1):
    """Coefficients (of s, s², s³) of the cubic with value 0 at 0, `y0_delta` at 1, slopes k0, k1."""
    return jnp.stack([k0, 3.0 * y0_delta - 2.0 * k0 - k1, k0 + k1 - 2.0 * y0_delta])


def _linear(delta):
    zero = jnp.zeros_like(delta)
    return jnp.stack([delta, zero, zero])


def _tsit5_dense_coefficients() -> tuple[tuple[float, ...], ...]:
    """Tsitouras' continuous extension b_i(s) = Σ_p β_ip s^p (p = 1 … 4) of Tsit5, as the rows
    (β_i1 … β_i4) for the seven stages: diffrax's `_Tsit5Interpolation` polynomials, expanded."""
    roots_and_scales = [
        (
            -1.0530884977290216,
            [0.0, 1.3299890189751412],
            [1.0, -1.4364028541716351, 0.7139816917074209],
        ),
        (0.1017, [0.0, 0.0], [1.0, -2.1966568338249754, 1.2949852507374631]),
        (2.490627285651252793, [0.0, 0.0], [1.0, -2.38535645472061657, 1.57803468208092486]),
        (-16.54810288924490272, [0.0, 0.0, 1.21712927295533244, 0.61620406037800089], None),
        (47.37952196281928122, [0.0, 0.0, 1.203071208372362603, 0.658047292653547382], None),
        (-34.87065786149660974, [0.0, 0.0, 1.2, 0.666666666666666667], None),
        (2.5, [0.0, 0.0, 1.0, 0.6], None),
    ]
    rows = []
    for scale, roots, quadratic in roots_and_scales:
        poly = np.poly1d([scale])
        for r in roots:
            poly = poly * np.poly1d([1.0, -r])
        if quadratic is not None:
            poly = poly * np.poly1d(quadratic)
        c = poly.coeffs[::-1]  # constant term first
        rows.append(tuple(float(x) for x in np.pad(c, (0, 5 - len(c)))[1:]))
    return tuple(rows)


def _dense_info(y0, treedef, qc, xcs):
    """The interpolation's fields; its base is the unit q0, so that the dense output ends on the
    step's unit q1 (a non-unit q0 is normalised by the first step)."""
    q0, x0, _ = _state_split(y0, "the solver")
    return dict(y0=_join(treedef, _unit(q0), x0), coeffs=_join(treedef, qc, xcs))


# ----------------------------------------------------------------------------------------------------
# Solvers


class _Tableau(eqx.Module):
    """An explicit Butcher tableau with Python-float entries (a ClassVar on each solver)."""

    a: tuple  # a[i] = coefficients of stage i (i ≥ 1) on stages 0..i-1
    b: tuple
    c: tuple
    b_error: tuple | None = None

    @property
    def fsal(self) -> bool:
        return len(self.a) > 0 and tuple(self.a[-1]) == tuple(self.b[:-1]) and self.c[-1] == 1.0


def _tsit5_tableau() -> _Tableau:
    tab = diffrax.Tsit5.tableau
    a = tuple(tuple(float(v) for v in row) for row in tab.a_lower)
    c = (0.0,) + tuple(float(v) for v in tab.c)
    return _Tableau(
        a=a,
        b=tuple(float(v) for v in tab.b_sol),
        c=c,
        b_error=tuple(float(v) for v in tab.b_error),
    )


class _RKMK(diffrax.AbstractSolver):
    """Runge–Kutta–Munthe-Kaas on an explicit tableau, FSAL across steps, Lie-algebra Hermite output."""

    term_structure: ClassVar = diffrax.AbstractTerm
    interpolation_cls: ClassVar[Callable[..., LiePolynomialInterpolation]] = (
        LiePolynomialInterpolation
    )
    tableau: ClassVar[_Tableau]
    # Trace every stage separately instead of looping over them (tableaux of more than two stages).
    unroll_stages: bool = eqx.field(default=False, static=True, kw_only=True)
    # Continuous extension: per stage, the coefficients of s, s², … of b_i(s); None: cubic Hermite.
    dense: ClassVar[tuple[tuple[float, ...], ...] | None] = None

    def init(self, terms, t0, t1, y0, args):
        _state_split(y0, type(self).__name__)
        return terms.vf(t0, y0, args)

    def func(self, terms, t0, y0, args):
        return terms.vf(t0, y0, args)

    def step(self, terms, t0, t1, y0, args, solver_state, made_jump):
        tab = self.tableau
        q0, x0, treedef = _state_split(y0, type(self).__name__)
        control = terms.contr(t0, t1)
        h = t1 - t0
        f = _first_stage(terms, t0, y0, args, solver_state, made_jump)
        dq, dxs = _apply_control(terms, f, control, treedef)
        # u0 is recovered against the q that f was evaluated at; the stages start from the unit q0.
        # A non-unit q0 (the first step only: every step ends on the unit sphere) otherwise reached
        # the last stage with |q| = |q0|, whose first-same-as-last value, recovered in the next step
        # against the unit q1, scaled its rotation by |q0| (RKMK45, |q0| = 1 + 1e-6: 1e-8 off).
        u0 = _increment(dq, q0)
        q0 = _unit(q0)
        n_stages = len(tab.c)
        a = np.zeros((n_stages, n_stages))
        for i, row in enumerate(tab.a, start=1):
            a[i, :i] = row
        times = [t0 + ci * h for ci in tab.c]

        def weigh(coeffs, stacked):
            """Σ_j c_j K_j over stacked stage increments (stage axis first; `coeffs` (..., stages))."""
            return jnp.tensordot(jnp.asarray(coeffs, stacked.dtype), stacked, axes=1)

        def stage(i, carry):
            big_k, small_k, *_ = carry
            row = a[i] if isinstance(i, int) else jnp.asarray(a)[i]
            big_u = weigh(row, big_k)
            q_stage = _exp_stage(big_u, q0)
            x_stage = [x + weigh(row, ks) for x, ks in zip(x0, small_k, strict=True)]
            t = times[i] if isinstance(i, int) else jnp.stack(times)[i]
            f = _eval_f(terms, t, treedef, q_stage, x_stage, args)
            dq, dxs = _apply_control(terms, f, control, treedef)
            big_k = big_k.at[i].set(_dexpinv(big_u, _increment(dq, q_stage)))
            small_k = [ks.at[i].set(dx) for ks, dx in zip(small_k, dxs, strict=True)]
            return big_k, small_k, big_u, q_stage, x_stage, f

        # The stage increments K_i (and the other leaves' k_i), stacked along a leading stage axis.
        # (Stacked from zeros_like, which keeps a sharding with explicit axes; jnp.zeros would not.)
        def stages(first):
            return jnp.stack([first] + [jnp.zeros_like(first)] * (n_stages - 1))

        big_k = stages(u0)
        small_k = [stages(jnp.asarray(d)) for d in dxs]
        carry = (big_k, small_k, jnp.zeros_like(u0), q0, list(x0), f)
        if n_stages > 2 and not self.unroll_stages:
            # One traced stage instead of n (as diffrax's own Runge–Kutta solvers do): measured for
            # RKMK45 in the `RKMK45` docstring.
            carry = lax.fori_loop(1, n_stages, stage, carry)
        else:
            for i in range(1, n_stages):
                carry = stage(i, carry)
        big_k, small_k, big_u, q_stage, x_stage, f = carry
        if tab.fsal:
            big_u1 = big_u
            q1, x1 = _unit(q_stage), x_stage
            f_end, k_end, dx_end = f, big_k[-1], [ks[-1] for ks in small_k]
        else:
            big_u1 = weigh(tab.b, big_k)
            q1 = _exp_left(big_u1, q0)
            x1 = [x + weigh(tab.b, ks) for x, ks in zip(x0, small_k, strict=True)]
            f_end = _eval_f(terms, t1, treedef, q1, x1, args)
            dq, dx_end = _apply_control(terms, f_end, control, treedef)
            k_end = _dexpinv(big_u1, _increment(dq, q1))
        y1 = _join(treedef, q1, x1)
        if tab.b_error is None:
            y_error = None
        else:
            err_x = [weigh(tab.b_error, ks) for ks in small_k]
            # ½(0, δU) ⊗ q1 ≈ exp(U) ⊗ q0 − exp(Û) ⊗ q0: its norm is the geodesic distance on the
            # unit sphere S³ between the two solutions (radians; half the rotation angle between them),
            # i.e. the same measure a stock solver applies to the quaternion's components.
            err_q = multiply(from_vector(0.5 * weigh(tab.b_error, big_k)), q1)
            y_error = _join(treedef, err_q, err_x)
        if self.dense is not None:
            # The tableau's continuous extension, V(s) = Σ b_i(s) K_i (the RKMK step is the tableau
            # applied to the ODE of V, so its dense output is V's).
            powers = np.asarray(self.dense).T  # powers[p-1] = (β_1p, …, β_np)
            qc = weigh(powers, big_k)
            xcs = [weigh(powers, ks) for ks in small_k]
        else:
            qc = _hermite(big_u1, u0, k_end)
            xcs = [
                _hermite(end - start, ks[0], k1)
                for start, end, ks, k1 in zip(x0, x1, small_k, dx_end, strict=True)
            ]
        dense_info = _dense_info(y0, treedef, qc, xcs)
        return y1, y_error, dense_info, f_end, diffrax.RESULTS.successful


class LieEuler(_RKMK):
    r"""The Lie–Euler method: $q_{n+1} = \exp(h\,ω(t_n, q_n)) ⊗ q_n$, order 1.

    The seed's corrected step with ω taken at the step start, written as the exponential map
    (docs/numerics.md §1): exact for constant and piecewise-constant (sampled) ω, so use it with
    `kinematic_vector_field` (the plain rate). The rotation vector is recovered from the term's
    $\dot q$ as $2\,\mathrm{vec}(h\dot q ⊗ q^*)$, so world- and body-frame fields both work. Other leaves of a
    tuple state `(q, x)` take an explicit Euler step. Dense output: Lie-algebra cubic Hermite
    (the end slope is the next step's first stage, first-same-as-last); for sampled ω that slope reads
    the next sample, so only the steps are exact, not the curve between them (see `sampled`).

    ??? cite "Reference"

        Iserles, Munthe-Kaas, Nørsett, Zanna, *Lie-group methods*, Acta Numerica 9 (2000) 215–365.
    """

    tableau: ClassVar[_Tableau] = _Tableau(a=(), b=(1.0,), c=(0.0,))

    def order(self, terms):
        return 1


class ExpMidpoint(_RKMK):
    r"""The exponential midpoint rule (RKMK on the explicit midpoint tableau), order 2.

    $u_1 = hω(t_n, q_n)$, $u_2 = hω(t_n + h/2, \exp(u_1/2) q_n)$,
    $q_{n+1} = \exp(\mathrm{dexp}^{-1}_{u_1/2}(u_2)) ⊗ q_n$. Two vector-field evaluations per step
    (first-same-as-last). The ω may depend on the state. Dense output: Lie-algebra cubic Hermite.

    ??? cite "Reference"

        H. Munthe-Kaas, *High order Runge–Kutta methods on manifolds*, Appl. Numer. Math. 29 (1999) 115–127.
    """

    tableau: ClassVar[_Tableau] = _Tableau(a=((0.5,),), b=(0.0, 1.0), c=(0.0, 0.5))

    def order(self, terms):
        return 2


class RKMK45(_RKMK, diffrax.AbstractAdaptiveSolver):
    r"""Adaptive Runge–Kutta–Munthe-Kaas method on Tsitouras' 5(4) pair: order 5, embedded order 4.

    With $u_i$ the stage rotation vectors recovered from the term's $\dot q$ and
    $K_i = \mathrm{dexp}^{-1}_{U_i}(u_i)$, $U_i = \sum_j a_{ij} K_j$, the stages are
    $Q_i = \exp(U_i) ⊗ q_n$ and $q_{n+1} = \exp(\sum_i b_i K_i) ⊗ q_n$: Tsit5 applied to the ODE of the
    rotation vector in the Lie algebra (Munthe-Kaas 1999; dexp⁻¹ by its series through $\mathrm{ad}^4$),
    so $|q| = 1$ to round-off (the step result is renormalised) and constant ω is integrated exactly
    in exact arithmetic. Other leaves of a tuple state `(q, x)` are integrated by Tsit5 itself.

    **Step size.** In floating point the dexp⁻¹ series amplifies round-off across ω by about
    $θ^2/12 + θ^4/720$ per stage, θ = |ω|h. For one step of constant ω, the worst of 20 random
    orientations and axes against the exponential (another 20 draws gave up to 1.4× these): 1.5e-14
    rad (float64) and 8.5e-6 rad (float32) up to θ = 5 rad; 3.3e-13 / 1.3e-4 at θ = 10; 6.4e-10 /
    1.2 rad at θ = 20 (CF4: ≤ 2e-6 in float32 at all of these). The series stands for dexp⁻¹ only
    for θ < 2π, so steps of more than a few radians are outside the method anyway. An adaptive
    controller does not keep them out for constant ω, whose embedded estimate barely sees this
    round-off (a review: steps of 24 rad accepted in float64 and of 8.9 rad in float32 at
    rtol = atol = 1e-6): bound `dtmax` by a few radians over |ω| for fast spin, or use `CF4` or
    the Magnus methods.

    The error estimate for the quaternion is $\tfrac12(0, δU) ⊗ q_{n+1}$, $δU = \sum_i (b_i − \hat b_i) K_i$:
    to leading order the 4-vector difference of the 5th- and 4th-order solutions, whose norm is their
    geodesic distance on the unit sphere $S^3$ in radians (half the rotation angle between them). So
    `diffrax.PIDController(rtol, atol)` means for the quaternion what it means for a stock solver on the
    same state (other leaves as usual). Measured at rtol = atol = 1e-8: coning 77 accepted steps (Tsit5
    95), torque-free rigid body 194 (Tsit5 195), attitude error ≈ 3e-8 … 7e-8 rad.
    Six vector-field evaluations per step (FSAL). Dense output (`SaveAt(ts=...)`, `sol.evaluate`):
    Tsitouras' continuous extension in the Lie algebra, $q(s) = \exp(\sum_i b_i(s) K_i) ⊗ q_n$, fourth
    order like Tsit5's own ($|q| = 1$ to round-off). At rtol = atol = 1e-10 on coning its error between
    steps is that at the step ends (a cubic Hermite interpolant was 130× worse there).

    **Stages in a loop.** The six stages after the first (which is the previous step's last) are
    traced once, inside a loop (as diffrax does for its own Runge–Kutta solvers). Measured on a 2-core
    CPU for the reverse-mode gradient of an adaptive 1,267-step solve of one body: compiled in 12.9 s
    instead of 30.3 s, run in 108 ms instead of 215 ms. Under `jax.vmap` over many bodies the loop costs
    run time instead: over 100 bodies the same gradient ran in 2.7 s instead of 1.7 s, and the forward
    solve of 1,000 bodies in 4.4 s instead of 2.1 s. Pass `RKMK45(unroll_stages=True)` there (the
    results agree to round-off).

    ??? cite "References"

        H. Munthe-Kaas, *High order Runge–Kutta methods on manifolds*, Appl. Numer. Math. 29 (1999) 115–127.
        Ch. Tsitouras, *Runge–Kutta pairs of order 5(4) satisfying only the first column simplifying
        assumption*, Comput. Math. Appl. 62 (2011) 770–775.
    """

    tableau: ClassVar[_Tableau] = _tsit5_tableau()
    dense: ClassVar[tuple[tuple[float, ...], ...]] = _tsit5_dense_coefficients()

    def order(self, terms):
        return 5


class CF4(diffrax.AbstractSolver):
    r"""The fourth-order commutator-free Lie-group method of Celledoni, Marthinsen and Owren (2003).

    With $F_i$ the stage angular velocities (recovered from the term's $\dot q$, world frame) and
    $u_i = hF_i$: $Q_2 = e^{u_1/2} q$, $Q_3 = e^{u_2/2} q$, $Q_4 = e^{(2u_3 − u_1)/2} Q_2$,
    $q_{n+1} = e^{(−u_1 + 2u_2 + 2u_3 + 3u_4)/12}\, e^{(3u_1 + 2u_2 + 2u_3 − u_4)/12}\, q_n$.
    Only exponentials (no dexp⁻¹, no singularity at $|u| = 2π$); the ω may depend on the state. Other
    leaves of a tuple state get classical RK4. Four evaluations per step (first-same-as-last).
    Dense output: Lie-algebra cubic Hermite in the rotation vector from q_n to q_{n+1}, whose axis
    is taken along the step's own estimate when that rotation is a whole number of turns (steps of
    exactly 2πk keep their axis). At such a step the interpolant's derivative in ω is wrong, though
    (the end quaternion does not depend on ω across the axis to first order, so it cannot carry
    that derivative): values from `SaveAt(ts=...)` or `evaluate`, a step's end included, had
    jacfwd and jacrev 70–110 % apart at exactly 2π per step, and right to 3e-10 at 1e-3 from it;
    the steps' own states (`SaveAt(t1=True)`, `steps=True`) differentiate exactly. A body-frame
    field (q̇ = ½ q ω̃) is stepped through its world-frame rate, exponentials on the left; `integrate(..., method="cf4", frame="body")` applies
    them on the right, in the body frame. Both are fourth order and agree in the world frame; in
    the body frame their error constants differ, by a factor that depends on the motion (2–5× on
    the coning motions tried, 32–128 steps).

    ??? cite "Reference"

        E. Celledoni, A. Marthinsen, B. Owren, *Commutator-free Lie group methods*, Future Generation
        Computer Systems 19 (2003) 341–352.
    """

    term_structure: ClassVar = diffrax.AbstractTerm
    interpolation_cls: ClassVar[Callable[..., LiePolynomialInterpolation]] = (
        LiePolynomialInterpolation
    )

    def order(self, terms):
        return 4

    def init(self, terms, t0, t1, y0, args):
        _state_split(y0, "CF4")
        return terms.vf(t0, y0, args)

    def func(self, terms, t0, y0, args):
        return terms.vf(t0, y0, args)

    def step(self, terms, t0, t1, y0, args, solver_state, made_jump):
        q0, x0, treedef = _state_split(y0, "CF4")
        control = terms.contr(t0, t1)
        t_half = t0 + 0.5 * (t1 - t0)

        def stage(t, q, xs):
            f = _eval_f(terms, t, treedef, q, xs, args)
            dq, dxs = _apply_control(terms, f, control, treedef)
            return _increment(dq, q), dxs

        f1 = _first_stage(terms, t0, y0, args, solver_state, made_jump)
        dq, k1 = _apply_control(terms, f1, control, treedef)
        u1 = _increment(dq, q0)
        q2 = _exp_stage(0.5 * u1, q0)
        u2, k2 = stage(t_half, q2, _lin_leaves((0.5,), [k1], x0))
        q3 = _exp_stage(0.5 * u2, q0)
        u3, k3 = stage(t_half, q3, _lin_leaves((0.5,), [k2], x0))
        q4 = _exp_stage(u3 - 0.5 * u1, q2)
        u4, k4 = stage(t1, q4, _lin_leaves((1.0,), [k3], x0))
        inner = _lin((0.25, 1.0 / 6.0, 1.0 / 6.0, -1.0 / 12.0), [u1, u2, u3, u4])
        outer = _lin((-1.0 / 12.0, 1.0 / 6.0, 1.0 / 6.0, 0.25), [u1, u2, u3, u4])
        q1 = _exp_left(outer, _exp_stage(inner, q0))
        x1 = _lin_leaves((1.0 / 6.0, 1.0 / 3.0, 1.0 / 3.0, 1.0 / 6.0), [k1, k2, k3, k4], x0)
        f_end = _eval_f(terms, t1, treedef, q1, x1, args)
        dq, dx_end = _apply_control(terms, f_end, control, treedef)
        big_u1 = _step_rotvec(q0, q1, inner + outer)
        k_end = _dexpinv(big_u1, _increment(dq, q1))
        qc = _hermite(big_u1, u1, k_end)
        xcs = [_hermite(b - a, s0, s1) for a, b, s0, s1 in zip(x0, x1, k1, dx_end, strict=True)]
        y1 = _join(treedef, q1, x1)
        return y1, None, _dense_info(y0, treedef, qc, xcs), f_end, diffrax.RESULTS.successful


def _kinematic_field_of(terms) -> _KinematicField | None:
    """jaxquat's own kinematic field inside `terms` (an `ODETerm`, possibly wrapped by diffrax, e.g.
    to integrate backwards), or `None` for any other term (whose ω the solver cannot see)."""
    for _ in range(8):
        if isinstance(terms, diffrax.ODETerm):
            field = terms.vector_field
            return field if isinstance(field, _KinematicField) else None
        terms = getattr(terms, "term", None)
    return None


class _Magnus(diffrax.AbstractSolver):
    """What `Magnus4`, `Magnus6` and `Magnus8` share: the frame, the state checks, and the stage rates
    uᵢ = 2 vec(h q̇ᵢ ⊗ q_n*) (world) or 2 vec(q_n* ⊗ h q̇ᵢ) (body) at the Gauss points, with q frozen."""

    frame: eqx.AbstractVar[str]

    term_structure: ClassVar = diffrax.AbstractTerm
    interpolation_cls: ClassVar[Callable[..., LiePolynomialInterpolation]] = (
        LiePolynomialInterpolation
    )

    def __check_init__(self):
        check_frame(self.frame)

    def init(self, terms, t0, t1, y0, args):
        q0, x0, treedef = self._split(y0)
        name = type(self).__name__
        if x0 and _depends_on(lambda *xs: terms.vf(t0, _join(treedef, q0, xs), args), *x0):
            # E.g. a rigid body (q, ω): ω evolves, and frozen at the step start it gives order 1.
            raise ValueError(
                f"the vector field depends on the state's other leaves `x` of `y0 = (q, x)`, but "
                f"{name} needs rates that are given functions of time (they are evaluated at the "
                "Gauss points with the state frozen: order 1 otherwise); use CF4 or RKMK45."
            )
        if x0 and _depends_on(
            lambda q: _leaves(terms.vf(t0, _join(treedef, q, x0), args), treedef)[1], q0
        ):
            # E.g. a position p' = rotate(v, q): Magnus evaluates it with q frozen, order 1.
            raise ValueError(
                f"the derivative of the state's other leaves `x` of `y0 = (q, x)` depends on q, but "
                f"{name} evaluates it at the Gauss points with q frozen at the step start (order 1 "
                "otherwise); use CF4 or RKMK45."
            )
        field = _kinematic_field_of(terms)
        if field is not None and field.frame != self.frame:
            raise ValueError(
                f"{name}(frame={self.frame!r}) was given a {field.frame}-frame kinematic field; pass "
                f"`frame={field.frame!r}` (Magnus composes ω in the solver's frame: a mismatch drops "
                "to order 2)."
            )
        if field is not None and callable(field.omega):
            omega = field.omega
            if field.omega_takes_args:
                omega = lambda t, q: field.omega(t, q, args)  # noqa: E731
            if _depends_on_q(omega, t0, q0):
                raise ValueError(
                    f"`omega` depends on q, but {type(self).__name__} needs a q-independent angular "
                    "velocity ω(t) (it is evaluated at the Gauss points with q frozen: order 2 "
                    "at best); use CF4 or RKMK45."
                )
        if field is None:
            return self._probe(terms, t0, t1, y0, args)
        return None

    def _probe(self, terms, t0, t1, y0, args):
        """For a term whose ω the solver cannot see (a plain `ODETerm`): a runtime check that the
        rate it gives at the first step's midpoint, read in the solver's frame, is the same at q0
        and at q0 turned by two fixed rotations (an ω(t) in that frame is; an ω that depends on q, or
        one given in the other frame, is not, and Magnus would silently drop to order 1 or 2).
        Returns a scalar zero carrying an `equinox.error_if`, which `step` adds to each new q so
        that the check cannot be compiled away."""
        q0, x0, treedef = self._split(y0)
        t = t0 + 0.5 * (t1 - t0)
        control = terms.contr(t0, t1)
        recover = _increment if self.frame == "world" else _body_increment
        turned = [multiply(jnp.asarray(turn, q0.dtype), q0) for turn in _PROBE_TURNS]
        rates = []
        for q in (q0, *turned):
            dq, _ = _apply_control(
                terms, terms.vf(t, _join(treedef, q, x0), args), control, treedef
            )
            rates.append(recover(dq, q))
        # 1024 ε (a right term differs by < 3 ε), but at most 1/8: in float16 and bfloat16 1024 ε ≥ 1,
        # and gap ≤ size always, so the check could never fail.
        tol = min(1024 * float(jnp.finfo(q0.dtype).eps), 0.125)
        bad = False
        for other_rates in rates[1:]:
            gap = jnp.max(jnp.abs(rates[0] - other_rates))
            size = jnp.max(jnp.abs(rates[0])) + jnp.max(jnp.abs(other_rates))
            bad = bad | (gap > tol * size)
        other = "body" if self.frame == "world" else "world"
        return eqx.error_if(
            jnp.zeros((), q0.dtype),
            bad,
            f"{type(self).__name__}(frame={self.frame!r}): the term's rate, read as an angular "
            "velocity in that frame, depends on q (probed at q0 and at q0 turned, at the first "
            "step's midpoint). Magnus evaluates it with q frozen at each step's start, so the "
            f"order would drop to 1 (ω depends on q: use CF4 or RKMK45) or 2 (ω is given in the "
            f"{other} frame: pass frame={other!r}).",
        )

    @staticmethod
    def _checked(q1, solver_state):
        """The new q, tied to `_probe`'s check (adding its zero) when there is one."""
        return q1 if solver_state is None else q1 + solver_state

    def func(self, terms, t0, y0, args):
        return terms.vf(t0, y0, args)

    def _split(self, y0):
        name = type(self).__name__
        if isinstance(y0, tuple) and (len(y0) != 2 or isinstance(y0[0], tuple)):
            raise ValueError(
                f"`y0` of {name} must be `q` or a tuple `(q, x)`; got a tuple of length "
                f"{len(y0)}. {name} assumes a vector field independent of the state. {_BACKSOLVE_HINT}"
            )
        return _state_split(y0, name)

    def _stages(self, terms, t0, t1, y0, args, fractions):
        q0, x0, treedef = self._split(y0)
        control = terms.contr(t0, t1)
        h = t1 - t0
        recover = _increment if self.frame == "world" else _body_increment
        us, ks = [], []
        for c in fractions:
            f = terms.vf(t0 + c * h, y0, args)
            dq, dxs = _apply_control(terms, f, control, treedef)
            us.append(recover(dq, q0))
            ks.append(dxs)
        return q0, x0, treedef, us, ks

    def _advance(self, q0, x0, treedef, y0, us, ks, phi, cubic, solver_state):
        """The step by the exponent Ω = `phi`, with dense output `cubic(*rates)` (coefficients of s,
        s², s³ of the integral of an interpolant of the rates) for q, made to end exactly at Ω, and
        for each other leaf, whose step is the cubic's value at s = 1 (Gauss quadrature)."""
        if self.frame == "world":
            q1 = _exp_left(phi, q0)
        else:
            q1 = _unit(multiply(q0, from_rotvec(phi)))
        qc = cubic(*us)
        qc = qc.at[2].add(phi - jnp.sum(qc, axis=0))  # end exactly at Ω
        if self.frame == "body":
            qc = rotate(qc, q0)  # q0 ⊗ exp(V) = exp(q0 V q0*) ⊗ q0
        x1, xcs = [], []
        for i, x in enumerate(x0):
            xc = cubic(*(k[i] for k in ks))
            x1.append(x + jnp.sum(xc, axis=0))
            xcs.append(xc)
        y1 = _join(treedef, self._checked(q1, solver_state), x1)
        dense = _dense_info(y0, treedef, qc, xcs)
        return y1, None, dense, solver_state, diffrax.RESULTS.successful


class Magnus4(_Magnus):
    r"""The fourth-order Magnus method with two Gauss points and one commutator.

    For an angular velocity that depends on time only: with $c_{1,2} = \tfrac12 ∓ \tfrac{\sqrt3}{6}$ and
    $u_i = hω(t_n + c_i h)$, world frame: $φ = \tfrac12(u_1 + u_2) + \tfrac{\sqrt3}{12}\,u_2 × u_1$,
    $q_{n+1} = \exp(φ) ⊗ q_n$; body frame: $φ_b = \tfrac12(u_1+u_2) + \tfrac{\sqrt3}{12}\,u_1 × u_2$,
    $q_{n+1} = q_n ⊗ \exp(φ_b)$ (docs/numerics.md §2).

    The rates are recovered from the term at the step's initial state, $u_i = 2\,\mathrm{vec}(h\dot q_i ⊗ q_n^*)$
    (world) or $2\,\mathrm{vec}(q_n^* ⊗ h\dot q_i)$ (body), so `frame` must be the frame in which ω is a
    given function of time: a world-frame Magnus step fed body-frame rates drops to order 2. Not for
    state-dependent ω (it would drop to order 1; use `CF4` or `RKMK45`). A jaxquat kinematic field of
    the other frame, or whose ω reads q, is a `ValueError`; for any other term (a plain `ODETerm`) the
    solver checks at run time (an `equinox` runtime error) that the rate it gives at the first step's
    midpoint, read as ω in `frame`, is the same at q0 and at q0 turned by two fixed rotations (to
    1024 ε relative, at most 1/8), which catches both mistakes (unless they happen to vanish at that
    time) at the cost of three more evaluations per solve; the error is raised also under
    `diffeqsolve(..., throw=False)`.
    Other leaves of a tuple state `(q, x)` are integrated by two-point Gauss quadrature (their
    derivative, too, must not depend on the state; a field that reads `x` is a `ValueError`). Not
    under `diffrax.BacksolveAdjoint` (the adjoint state depends on the state). Dense output: the Magnus
    expansion of the linear interpolant of ω through the two Gauss points (on the sphere).

    **Arguments:**

    - `frame`: `"world"` (default) or `"body"`, the frame of the term's angular velocity.

    ??? cite "References"

        A. Iserles, S. P. Nørsett, *On the solution of linear differential equations in Lie groups*,
        Phil. Trans. R. Soc. A 357 (1999) 983–1019. S. Blanes, F. Casas, J. A. Oteo, J. Ros,
        *The Magnus expansion and some of its applications*, Phys. Rep. 470 (2009) 151–238.
    """

    frame: str = eqx.field(static=True, default="world")

    def order(self, terms):
        return 4

    def step(self, terms, t0, t1, y0, args, solver_state, made_jump):
        del made_jump
        q0, x0, treedef, us, ks = self._stages(terms, t0, t1, y0, args, _STAGE_FRACTIONS["magnus4"])
        u1, u2 = us
        mean = 0.5 * (u1 + u2)
        slope = _SQRT3 * (u2 - u1)
        bracket = cross(mean, slope) * (1.0 / 12.0)
        if self.frame == "world":
            # (√3/12) u2×u1 = −(1/12) mean×slope
            phi = mean - bracket
            q1 = _exp_left(phi, q0)
            third = -bracket
        else:
            phi = mean + bracket
            q1 = _unit(multiply(q0, from_rotvec(phi)))
            third = bracket
        qc = jnp.stack([mean - 0.5 * slope, 0.5 * slope, third])
        if self.frame == "body":
            # q0 ⊗ exp(V) = exp(q0 V q0*) ⊗ q0: the interpolant in world coordinates.
            qc = rotate(qc, q0)
        x1, xcs = [], []
        for i, x in enumerate(x0):
            k_mean = 0.5 * (ks[0][i] + ks[1][i])
            k_slope = _SQRT3 * (ks[1][i] - ks[0][i])
            x1.append(x + k_mean)
            xcs.append(jnp.stack([k_mean - 0.5 * k_slope, 0.5 * k_slope, jnp.zeros_like(k_mean)]))
        y1 = _join(treedef, self._checked(q1, solver_state), x1)
        dense = _dense_info(y0, treedef, qc, xcs)
        return y1, None, dense, solver_state, diffrax.RESULTS.successful


class Magnus6(_Magnus):
    r"""The sixth-order Magnus method with three Gauss points and three commutators.

    For an angular velocity that depends on time only: with $c_{1,2,3} = \tfrac12 − \tfrac{\sqrt{15}}{10},
    \tfrac12, \tfrac12 + \tfrac{\sqrt{15}}{10}$ and $u_i = hω(t_n + c_i h)$, $α_1 = u_2$,
    $α_2 = \tfrac{\sqrt{15}}{3}(u_3 − u_1)$, $α_3 = \tfrac{10}{3}(u_3 − 2u_2 + u_1)$, $C_1 = [α_1, α_2]$,
    $C_2 = −\tfrac1{60}[α_1, 2α_3 + C_1]$ and
    $Ω = α_1 + \tfrac1{12}α_3 + \tfrac1{240}[−20α_1 − α_3 + C_1, α_2 + C_2]$; world frame
    $[a, b] = a × b$, $q_{n+1} = \exp(Ω) ⊗ q_n$; body frame $[a, b] = b × a$, $q_{n+1} = q_n ⊗ \exp(Ω)$.
    The same step as `jaxquat.integrate(..., method="magnus6")`.

    As for `Magnus4`, the rates are recovered from the term at the step's initial state, so `frame`
    must be the frame in which ω is a given function of time, ω must not depend on the state, other
    leaves of a tuple state `(q, x)` are integrated by three-point Gauss quadrature (their derivative
    must not depend on the state either), and it does not run under `diffrax.BacksolveAdjoint`. Dense
    output: the integral of the quadratic through the three Gauss-point rates plus a cubic correction
    that makes it end at Ω (on the sphere; order 4.0 between steps measured on the coning motion).

    **Arguments:**

    - `frame`: `"world"` (default) or `"body"`, the frame of the term's angular velocity.

    ??? cite "Reference"

        S. Blanes, F. Casas, J. A. Oteo, J. Ros, *The Magnus expansion and some of its applications*,
        Phys. Rep. 470 (2009) 151–238, §5.2.
    """

    frame: str = eqx.field(static=True, default="world")

    def order(self, terms):
        return 6

    def step(self, terms, t0, t1, y0, args, solver_state, made_jump):
        del made_jump
        q0, x0, treedef, us, ks = self._stages(terms, t0, t1, y0, args, _STAGE_FRACTIONS["magnus6"])
        phi = magnus6_exponent(*us, self.frame)
        cubic = functools.partial(_gauss_cubic, offset=_SQRT15 / 10.0)
        return self._advance(q0, x0, treedef, y0, us, ks, phi, cubic, solver_state)


class Magnus8(_Magnus):
    r"""The eighth-order Magnus method with four Gauss points and ten commutators (cross products).

    For an angular velocity that depends on time only: $u_i = hω(t_n + c_i h)$ at the four
    Gauss–Legendre nodes $c_i = \tfrac12 ∓ v_1, \tfrac12 ∓ v_2$, and Ω the order-8 Magnus exponent of
    Blanes, Casas & Ros (2000) formed from the moments of the $u_i$ (`jaxquat._integrate.magnus8_exponent`
    gives the formula); world frame $q_{n+1} = \exp(Ω) ⊗ q_n$, body frame $q_{n+1} = q_n ⊗ \exp(Ω)$.
    The same step as `jaxquat.integrate(..., method="magnus8")`; exact for a constant ω.

    As for `Magnus4` and `Magnus6`, the rates are recovered from the term at the step's initial state,
    so `frame` must be the frame in which ω is a given function of time, ω must not depend on the
    state, other leaves of a tuple state `(q, x)` are integrated by four-point Gauss quadrature (exact
    for polynomials of degree 7; their derivative must not depend on the state either), and it does not
    run under `diffrax.BacksolveAdjoint`. Dense output: the integral of the quadratic with the Gauss
    rates' first three moments, plus a cubic correction that makes it end at Ω (on the sphere; order 4.0
    between steps measured on the coning motion, as Magnus6's).

    **Arguments:**

    - `frame`: `"world"` (default) or `"body"`, the frame of the term's angular velocity.

    ??? cite "Reference"

        S. Blanes, F. Casas, J. Ros, *Improved high order integrators based on the Magnus expansion*,
        BIT Numer. Math. 40 (2000) 434–450.
    """

    frame: str = eqx.field(static=True, default="world")

    def order(self, terms):
        return 8

    def step(self, terms, t0, t1, y0, args, solver_state, made_jump):
        del made_jump
        q0, x0, treedef, us, ks = self._stages(terms, t0, t1, y0, args, _STAGE_FRACTIONS["magnus8"])
        phi = magnus8_exponent(*us, self.frame)
        return self._advance(q0, x0, treedef, y0, us, ks, phi, _gauss4_cubic, solver_state)


def _gauss4_cubic(k1, k2, k3, k4):
    """Coefficients (of s, s², s³) of ∫₀ˢ p, p the quadratic in τ = s − ½ with the same moments
    ∫τʲp (j = 0, 1, 2) over the step as the cubic through k₁ … k₄ at the four Gauss nodes. The
    moments are four-point Gauss–Legendre sums; at s = 1 it is the Gauss rule itself."""
    v1, v2, spread = _GL4_OUTER, _GL4_INNER, _GL4_SPREAD
    w1, w2 = 0.5 - spread, 0.5 + spread
    outer, inner = k1 + k4, k2 + k3
    m0 = 0.25 * (outer + inner) + (0.5 * spread) * (inner - outer)  # Σ (wᵢ/2) kᵢ
    m1 = (0.5 * v1 * w1) * (k4 - k1) + (0.5 * v2 * w2) * (k3 - k2)
    m2 = (0.5 * v1 * v1 * w1) * outer + (0.5 * v2 * v2 * w2) * inner
    # p = c₀ + c₁τ + c₂τ²: ∫p = c₀ + c₂/12, ∫τp = c₁/12, ∫τ²p = c₀/12 + c₂/80.
    c2 = 180.0 * (m2 - m0 / 12.0)
    c1 = 12.0 * m1
    c0 = m0 - c2 / 12.0
    return jnp.stack([c0 - 0.5 * c1 + 0.25 * c2, 0.5 * (c1 - c2), c2 / 3.0])


def _gauss_cubic(k1, k2, k3, offset):
    """Coefficients (of s, s², s³) of ∫₀ˢ p, p the quadratic through k₁, k₂, k₃ at s = ½ − d, ½, ½ + d
    (d = `offset`); at s = 1 it is the Gauss–Legendre rule (5k₁ + 8k₂ + 5k₃)/18."""
    b = (k3 - k1) / (2.0 * offset)
    a = ((k3 - k2) - (k2 - k1)) / (2.0 * offset * offset)
    return jnp.stack([k2 - 0.5 * b + 0.25 * a, 0.5 * (b - a), a / 3.0])


def _check_corrected_step(terms, t0, t1, q1):
    """`q1`, with a runtime error (`equinox.error_if`) when `terms` is (diffrax's wrapping of) an
    `ODETerm` of `corrected_vector_field(ω, dt)` and the step t1 − t0 is not dt up to the times'
    rounding (and diffrax's clipping of the last step: within 256 ε·(|t0| + |t1| + dt)): the correction is exact
    for steps of dt only. A last step clipped to t1 = 1.05 with dt = 0.1 turned the body by 0.074
    rad too little at |ω| = 10, silently (helper-54)."""
    term = terms
    while term is not None and not isinstance(getattr(term, "vector_field", None), _KinematicField):
        term = getattr(term, "term", None)
    if term is None or term.vector_field.dt is None:
        return q1
    h = jnp.abs(jnp.asarray(t1 - t0))
    dt = jnp.abs(jnp.asarray(term.vector_field.dt, h.dtype))
    slack = 256 * jnp.finfo(h.dtype).eps * (jnp.abs(t0) + jnp.abs(t1) + dt)
    return eqx.error_if(
        q1,
        jnp.abs(h - dt) > slack,
        "NormalizedEuler: a step t1 - t0 differs from the `dt` of its corrected_vector_field(omega, "
        "dt); the correction is exact only for steps of dt. Make t1 - t0 a multiple of dt0 = dt "
        "(no shorter last step, no uneven StepTo), or use LieEuler with kinematic_vector_field.",
    )


class NormalizedEuler(diffrax.AbstractSolver):
    r"""Euler's method followed by renormalisation of the quaternion: $q_{n+1} = (q_n + h\dot q)/|q_n + h\dot q|$.

    With `corrected_vector_field(ω, dt)` and the constant step `dt0 = dt` this is the seed's scheme
    exactly, $q_{n+1} = \exp(ω_n Δt) ⊗ q_n$ (docs/numerics.md §1, for $|ω|Δt < π$): exact for constant and
    piecewise-constant (sampled) ω, and equal to `jaxquat.integrate(..., method="euler")`. With
    `kinematic_vector_field` it is the naive normalised Euler baseline (it rotates by $2\arctan(θ/2)$
    instead of θ per step). Other leaves of a tuple state `(q, x)` take a plain Euler step.

    Dense output: the geodesic $q(s) = \exp(sU) ⊗ q_n$, $\exp(U) ⊗ q_n = q_{n+1}$ — exactly the
    constant-ω motion within a step of the seed's scheme while $|ω|Δt < π$; other leaves linear.
    Past π the steps are still the exact rotations (as $-\exp(ωΔt) ⊗ q_n$, docs/numerics.md §1), but
    the corrected rate, $\tan(|ω|Δt/2)$ along ω, no longer tells which way the body turned, and the
    geodesic turns the short way: backwards by $2π − |ω|Δt$ (3.1 rad off mid-step at
    $|ω|Δt = 3.5$). For dense output of such steps use `LieEuler` with `kinematic_vector_field`
    (exact for constant ω at any step).

    ??? cite "Reference"

        The seed notes' equation quatRateOfChangeCorrected (README, Sources).
    """

    term_structure: ClassVar = diffrax.AbstractTerm
    interpolation_cls: ClassVar[Callable[..., LiePolynomialInterpolation]] = (
        LiePolynomialInterpolation
    )

    def order(self, terms):
        return 1

    def init(self, terms, t0, t1, y0, args):
        _state_split(y0, "NormalizedEuler")
        return None

    def func(self, terms, t0, y0, args):
        return terms.vf(t0, y0, args)

    def step(self, terms, t0, t1, y0, args, solver_state, made_jump):
        del solver_state, made_jump
        q0, x0, treedef = _state_split(y0, "NormalizedEuler")
        control = terms.contr(t0, t1)
        dq, dxs = _apply_control(terms, terms.vf(t0, y0, args), control, treedef)
        p = q0 + dq
        q1 = _check_corrected_step(terms, t0, t1, p / jnp.sqrt(sum_squares(p, keepdims=True)))
        x1 = [x + d for x, d in zip(x0, dxs, strict=True)]
        qc = _linear(_rotvec_between(q0, q1))
        xcs = [_linear(d) for d in dxs]
        y1 = _join(treedef, q1, x1)
        return y1, None, _dense_info(y0, treedef, qc, xcs), None, diffrax.RESULTS.successful
