"""Rigid-body dynamics: point masses, inertia, Euler's equations, rigid and shape-changing bodies.

Conventions: `q` maps body coordinates to world (inertial) coordinates, v_world = q v_body q⁻¹.
Body-frame quantities carry the subscript b in the maths: ω_b, Π = q⁻¹ L q. An inertia is either a full
symmetric positive-definite `(..., 3, 3)` matrix or the principal moments `(..., 3)` (a diagonal
matrix); a trailing `(3, 3)` is always read as a matrix.

Time stepping is delegated to the Lie-group integrators of `_integrate.py` (the orientation moves by
exponentials, the vector part of the state by the matching Runge–Kutta scheme), so every integrator
`method` is available here and reverse mode stays bounded in memory over long runs.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import NamedTuple

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, ArrayLike

from ._algebra import conjugate
from ._integrate import (
    LIE_METHODS,
    _check_finite_scalar,
    _check_steps,
    _reads_time,
    check_times_advance,
    compensated_lie_step,
    lie_step,
    long_run_options,
    renormalized_when_due,
    scan_steps,
)
from ._kinematics import rate
from ._numerics import (
    as_float_array,
    at_least_float32,
    broadcast_batch,
    broadcasts_to,
    check_callable,
    check_choice,
    check_frame,
    check_matrix,
    check_trailing,
    cross,
    is_tracer,
    power_of_two_times,
    prescale,
    reusable_callable,
    sum_squares,
)
from ._rotation import from_matrix, rotate, rotate_unchecked

# Methods usable with a state-dependent angular velocity (the Magnus methods need ω(t) independent of the state).
_METHODS = ("euler", "midpoint", "cf4", "naive", "rk4")


# --------------------------------------------------------------------------------------------------
# Point masses


def _check_positive_masses(masses: Array) -> None:
    """Raise a `ValueError` for non-positive or non-finite masses (only when they are concrete; a NaN
    mass once gave an all-NaN centre of mass and inertia without a word), or subnormal ones: XLA on
    CPU flushes those to zero, and masses of 1e-320 gave a NaN centre of mass (helper-52)."""
    if not is_tracer(masses):
        values = np.asarray(masses)
        bad = values[~(np.isfinite(values) & (values > 0))]
        if bad.size:
            raise ValueError(f"`masses` must be positive and finite; got {bad.flat[0]}.")
        tiny = np.finfo(values.dtype).tiny if np.issubdtype(values.dtype, np.floating) else 0
        small = values[values < tiny]
        if small.size:
            raise ValueError(
                f"`masses` must be at least {values.dtype}'s smallest normal number {tiny:.3g} "
                f"(XLA flushes smaller ones to zero); got {small.flat[0]:.3g}. Scale the masses up."
            )


def _check_point_masses(masses: ArrayLike, positions: ArrayLike):
    """Validate `masses (..., n)` against `positions (..., n, 3)` and broadcast their batch axes."""
    masses = as_float_array(masses, "masses")
    positions = check_trailing(positions, 3, "positions")
    if positions.ndim < 2:
        raise ValueError(
            f"`positions` must have shape (..., n, 3); got shape {tuple(positions.shape)}."
        )
    if masses.ndim < 1 or masses.shape[-1] != positions.shape[-2]:
        raise ValueError(
            f"`masses` must have shape (..., n) with n = {positions.shape[-2]} to match `positions` "
            f"of shape {tuple(positions.shape)}; got shape {tuple(masses.shape)}."
        )
    _check_nonempty(positions.shape[-2])
    _check_positive_masses(masses)
    masses, positions = broadcast_batch((masses, 1, "masses"), (positions, 2, "positions"))
    return masses, positions


def _check_nonempty(n: int) -> None:
    """Raise a `ValueError` for an empty set of point masses (n = 0)."""
    if n == 0:
        raise ValueError(
            "at least one point mass is needed: `masses` (..., n) and `positions` (..., n, 3) have "
            "n = 0."
        )


def _moment(masses: Array, vectors: Array) -> Array:
    """Σᵢ mᵢ vᵢ over the point axis: `(..., n)`, `(..., n, k)` → `(..., k)`."""
    return jnp.sum(masses[..., None] * vectors, axis=-2)


def center_of_mass(masses: ArrayLike, positions: ArrayLike) -> Array:
    r"""The centre of mass $c = \sum_i m_i x_i / \sum_i m_i$ of a set of point masses.

    The seed's `center_of_mass` (DeformableBodies.jl), on arrays instead of `PointMass` lists.

    **Arguments:**

    - `masses`: positive masses, shape `(..., n)`, n ≥ 1.
    - `positions`: positions, shape `(..., n, 3)`; leading axes broadcast with those of `masses`.

    **Returns:** the centre of mass, shape `(..., 3)`.

    Masses are checked to be positive when they are concrete; under `jit` they are not checked.
    """
    masses, positions = _check_point_masses(masses, positions)
    # Masses at scale 1 (`prescale`; c does not depend on their scale): Σ mᵢxᵢ overflowed float32
    # for masses 1e20 at 1e20 and underflowed to 0 for 1e-20 at 1e-20 (helper-53).
    masses = prescale(masses, limit=0)[0]
    return _moment(masses, positions) / jnp.sum(masses, axis=-1, keepdims=True)


def _point_inertia(masses: Array, relative: Array) -> Array:
    """Σᵢ mᵢ (|rᵢ|² E − rᵢ rᵢᵀ) for positions `relative` to the reference point.

    Masses and positions are brought to scale 1 first (exact powers of two, `prescale`) and the sum
    scaled back: |rᵢ|² underflowed float32 from |r| ≈ 1e-19 (I = 0 for masses 1e20 at 1e-20) and
    overflowed from 1e19 (helper-53)."""
    unit, e = _point_inertia_scaled(masses, relative)
    return power_of_two_times(unit, e[..., None, None])


def _point_inertia_scaled(masses: Array, relative: Array) -> tuple[Array, Array]:
    """(J, e) with `_point_inertia(masses, relative)` = J·2ᵉ exactly and J at scale ~1: for callers
    that need I only up to its scale (I⁻¹ applied to a vector, the ratio of its moments), which I
    itself may not hold (a molecule in SI units, I ≈ 1e-46 kg m², underflows float32)."""
    masses, e_mass = prescale(masses, limit=0)
    relative, e_length = prescale(relative, axes=(-2, -1), limit=0)
    return _unit_point_inertia(masses, relative), e_mass + 2 * e_length


def _unit_point_inertia(masses: Array, relative: Array) -> Array:
    """Σ mᵢ(|rᵢ|² 1 − rᵢrᵢᵀ) of masses and positions already at scale 1 (`prescale`)."""
    eye = jnp.eye(3, dtype=relative.dtype)
    outer = relative[..., :, None] * relative[..., None, :]
    per_point = sum_squares(relative)[..., None, None] * jnp.broadcast_to(eye, outer.shape) - outer
    return jnp.sum(masses[..., None, None] * per_point, axis=-3)


def inertia_tensor(
    masses: ArrayLike, positions: ArrayLike, *, about: ArrayLike | None = None
) -> Array:
    r"""The inertia tensor $I = \sum_i m_i (|r_i|^2 E - r_i r_i^\top)$, $r_i = x_i - p$, of point masses.

    **Arguments:**

    - `masses`: positive masses, shape `(..., n)`.
    - `positions`: positions, shape `(..., n, 3)`.
    - `about`: the reference point p, shape `(..., 3)`; by default the centre of mass (the inertia the
      equations of motion use). The seed's `inertia_tensor` is the case `about=0` on centred positions.

    **Returns:** the symmetric `(..., 3, 3)` inertia tensor, in the coordinates of `positions`.
    """
    masses, positions = _check_point_masses(masses, positions)
    if about is None:
        about = center_of_mass(masses, positions)
    else:
        about = check_trailing(about, 3, "about")
    positions, about = broadcast_batch((positions, 2, "positions"), (about, 1, "about"))
    masses = jnp.broadcast_to(masses, positions.shape[:-1])
    return _point_inertia(masses, positions - about[..., None, :])


def angular_momentum(
    masses: ArrayLike,
    positions: ArrayLike,
    velocities: ArrayLike,
    *,
    about: ArrayLike | None = None,
) -> Array:
    r"""The angular momentum $L = \sum_i m_i (x_i - p) \times v_i$ of point masses.

    **Arguments:**

    - `masses`: positive masses, shape `(..., n)`.
    - `positions`: positions, shape `(..., n, 3)`; `velocities`: their velocities, same shape.
    - `about`: the reference point p, shape `(..., 3)`; by default the centre of mass, so that a rigid
      rotation $v_i = ω \times (x_i - c)$ gives $L = I ω$ with `I = inertia_tensor(masses, positions)`.
      With `about=jnp.zeros(3)` this is the seed's `angular_momentum` ($\sum_i m_i x_i \times v_i$).

    **Returns:** $L$, shape `(..., 3)`.
    """
    masses, positions = _check_point_masses(masses, positions)
    velocities = check_trailing(velocities, 3, "velocities")
    if velocities.shape[-2:] != positions.shape[-2:]:
        raise ValueError(
            f"`velocities` must have shape (..., {positions.shape[-2]}, 3) like `positions`; "
            f"got shape {tuple(velocities.shape)}."
        )
    if about is None:
        about = center_of_mass(masses, positions)
    else:
        about = check_trailing(about, 3, "about")
    positions, velocities, about = broadcast_batch(
        (positions, 2, "positions"), (velocities, 2, "velocities"), (about, 1, "about")
    )
    masses = jnp.broadcast_to(masses, positions.shape[:-1])
    return _moment(masses, cross(positions - about[..., None, :], velocities))


def principal_axes(inertia: ArrayLike) -> tuple[Array, Array]:
    r"""Principal moments and the rotation to the principal frame: $I = R\,\mathrm{diag}(I_1, I_2, I_3)\,R^\top$.

    **Arguments:**

    - `inertia`: symmetric positive semidefinite inertia tensors, shape `(..., 3, 3)` (checked when
      concrete). A zero moment is allowed: a rod's inertia (points on one line) has the line as the
      axis of moment ≈ 0, which may come out as a tiny negative number from rounding.

    **Returns:** `(moments, q)`: the principal moments in ascending order, shape `(..., 3)`, and the unit
    quaternion `q` of the rotation R (det R = +1) whose columns are the principal axes, shape `(..., 4)`.
    So `rotate(e_k, q)` is the k-th principal axis, and a body whose orientation is `q_world` with this
    inertia in body coordinates has orientation `multiply(q_world, q)` with the inertia `moments`.

    The axes are defined up to sign; q is the proper choice whose first two axes have their largest
    component positive, so q is continuous in the inertia (and its derivative that of the values
    nearby) wherever those components and the moments are distinct: a diagonal inertia with distinct
    moments in ascending order gives the identity, and small changes keep q near it. q jumps where
    an axis's two largest components swap, and between q and −q where w crosses 0 (a rotation near a
    half-turn; the same rotation). For equal moments the axes are not unique and the gradient through
    q is undefined (the eigenvector gradient divides by the gap; NaN for exactly equal moments, finite
    and meaningless where round-off has split them). The moments' gradient stays finite there, but
    only symmetric functions of the equal ones (their sum, say) have a gradient: that of one of them
    follows the basis `eigh` happened to pick.
    """
    inertia = check_matrix(inertia, "inertia")
    inertia = _check_inertia(inertia, "inertia", semidefinite=True)
    # At scale 1 (exactly, `prescale`): JAX's eigh derivative forms 1 + λⱼ − λᵢ, which rounds to
    # 0 for moments past 2²⁴ in float32 (NaN gradients for a space station's 1e8 kg m²; helper-53).
    unit, e = prescale(at_least_float32(inertia), axes=(-2, -1), limit=0)
    moments, axes = jnp.linalg.eigh(unit)  # (no half-precision eigh)
    moments = power_of_two_times(moments, e[..., None])
    # eigh's signs are LAPACK's whim: for a diagonal inertia an off-diagonal change of 1e-7 turned
    # q from the identity to a half-turn. Each of the first two axes is signed so that its largest
    # component is positive (continuous wherever that component is unique), the third completes a
    # right-handed frame.
    largest = jnp.argmax(jnp.abs(axes), axis=-2, keepdims=True)
    sign = jnp.where(jnp.take_along_axis(axes, largest, axis=-2) < 0, -1.0, 1.0)
    axes = axes * sign.astype(axes.dtype)
    axes = axes.at[..., :, 2].set(cross(axes[..., :, 0], axes[..., :, 1]))
    return moments.astype(inertia.dtype), from_matrix(axes).astype(inertia.dtype)


# --------------------------------------------------------------------------------------------------
# Inertia as an operator


def _is_matrix(inertia: Array) -> bool:
    return inertia.ndim >= 2 and inertia.shape[-2:] == (3, 3)


def _check_inertia(
    inertia: ArrayLike, name: str = "inertia", *, semidefinite: bool = False
) -> Array:
    """Check the shape (`(..., 3, 3)` or `(..., 3)`) and, when concrete, symmetry and positivity
    (moments > 0; with `semidefinite`, ≥ 0 up to the symmetry check's relative √ε, which admits the
    rounding residue of a zero moment: a rod or a single point)."""
    inertia = as_float_array(inertia, name)
    if not _is_matrix(inertia) and (inertia.ndim == 0 or inertia.shape[-1] != 3):
        raise ValueError(
            f"`{name}` must be a (..., 3, 3) matrix or principal moments (..., 3); got shape "
            f"{tuple(inertia.shape)}."
        )
    if is_tracer(inertia):
        return inertia
    values = np.asarray(inertia, dtype=np.float64)
    if not np.all(np.isfinite(values)):
        raise ValueError(f"`{name}` must be finite.")
    if _is_matrix(inertia):
        scale = np.max(np.abs(values), axis=(-2, -1), keepdims=True)
        tolerance = np.sqrt(float(jnp.finfo(inertia.dtype).eps)) * scale
        if np.any(np.abs(values - np.swapaxes(values, -1, -2)) > tolerance):
            hint = ""
            if values.shape == (3, 3):  # perhaps three bodies' principal moments
                hint = (
                    " (a (3, 3) array is one matrix; three bodies' principal moments go in as "
                    "diagonal matrices, `jax.vmap(jnp.diag)(moments)`)"
                )
            raise ValueError(f"`{name}` must be a symmetric matrix{hint}.")
        moments = np.linalg.eigvalsh(0.5 * (values + np.swapaxes(values, -1, -2)))
    else:
        moments = values
    if semidefinite:
        scale = np.max(np.abs(moments), axis=-1, keepdims=True)
        tolerance = np.sqrt(float(jnp.finfo(inertia.dtype).eps)) * scale
        if np.any(moments < -tolerance):
            raise ValueError(
                f"`{name}` must be positive semidefinite (principal moments ≥ 0); got moments "
                f"{moments.min()}."
            )
    elif np.any(moments <= 0):
        raise ValueError(
            f"`{name}` must be positive definite (principal moments > 0); got moments {moments.min()}."
        )
    return inertia


def _inertia_rank(inertia: Array) -> int:
    """The number of trailing element axes of an inertia: 2 (matrix) or 1 (principal moments)."""
    return 2 if _is_matrix(inertia) else 1


def _apply_inertia(
    inertia: Array, vector: Array, names: tuple[str, str] = ("inertia", "vector")
) -> Array:
    """I v for a `(..., 3, 3)` matrix or principal moments `(..., 3)`; `names` for error messages."""
    # Which it is must be read before broadcasting: moments (3,) against three vectors (3, 3) would
    # broadcast to (3, 3) and then look like a matrix.
    matrix = _is_matrix(inertia)
    inertia, vector = broadcast_batch(
        (inertia, 2 if matrix else 1, names[0]), (vector, 1, names[1])
    )
    if matrix:
        return jnp.sum(inertia * vector[..., None, :], axis=-1)
    return inertia * vector


def _unit_inertia(inertia: Array) -> tuple[Array, Array]:
    """(J, e) with I = J·2ᵉ and J's largest entry in [½, 1), exactly (`prescale`).

    Euler's equations do not depend on the inertia's scale, ω̇ = J⁻¹(τ·2⁻ᵉ + (Jω) × ω), but their
    intermediates did: a cofactor inverse (∝ I², over a determinant ∝ I³) left float32's range
    from I ≈ 7e12 (I⁻¹ = 0: the body stopped turning) or below 1e-13 (NaN: a milligram at a tenth
    of a millimetre; helper-52), and (Iω) × ω underflowed for a float32 nanoparticle (I ≈ 1e-32,
    |ω| ≈ 1e-3: ω̇ 93 % off; helper-53). Bit for bit the unscaled result where that is in range.
    """
    return prescale(inertia, axes=(-2, -1) if _is_matrix(inertia) else (-1,), limit=0)


def _unit_inverse(unit: Array) -> Array:
    """J⁻¹ for a `_unit_inertia` J: by cofactors (rows' cross products over the determinant) for a
    matrix, reciprocals for moments."""
    if not _is_matrix(unit):
        return 1.0 / unit
    row0, row1, row2 = unit[..., 0, :], unit[..., 1, :], unit[..., 2, :]
    cofactors = jnp.stack([cross(row1, row2), cross(row2, row0), cross(row0, row1)], axis=-1)
    det = jnp.sum(row0 * cross(row1, row2), axis=-1)
    return cofactors / det[..., None, None]


def _scaled_torque(torque: Array | None, e: Array) -> Array | None:
    """τ·2⁻ᵉ, the torque for `_euler_rhs` with a `_unit_inertia` J = I·2⁻ᵉ (e of the inertia's
    batch shape, which broadcasts against the torque's)."""
    if torque is None:
        return None
    e = -e[..., None]
    return power_of_two_times(torque, e.reshape((1,) * (torque.ndim - e.ndim) + e.shape))


def _euler_rhs(omega: Array, inertia: Array, inverse: Array, torque: Array | None) -> Array:
    """ω̇ = I⁻¹(τ + (Iω) × ω) with a precomputed I⁻¹ (called with `_unit_inertia`'s J, J⁻¹ and τ·2⁻ᵉ).

    For principal moments the gyroscopic term is written (I₂ − I₃) ω₂ ω₃ and cyclic, so it is exactly
    0 about the axis of an axisymmetric body (I₂ = I₃): in the cross product form I₂ω₂ω₃ − I₃ω₃ω₂,
    the compiler's fused multiply-adds leave a rounding residue that 1/I₁ amplifies (float32, a
    slender body with I₁ = 1e-8: ω̇₁ = −1.1 instead of 0).
    """
    if _is_matrix(inertia):
        moment = cross(_apply_inertia(inertia, omega, ("inertia", "omega")), omega)
    else:
        inertia, omega = broadcast_batch((inertia, 1, "inertia"), (omega, 1, "omega"))
        i1, i2, i3 = inertia[..., 0], inertia[..., 1], inertia[..., 2]
        w1, w2, w3 = omega[..., 0], omega[..., 1], omega[..., 2]
        moment = jnp.stack([(i2 - i3) * w2 * w3, (i3 - i1) * w3 * w1, (i1 - i2) * w1 * w2], axis=-1)
    if torque is not None:
        moment = moment + torque
    return _apply_inertia(inverse, moment, ("inertia", "omega"))


def euler_equations(
    omega_body: ArrayLike, inertia: ArrayLike, torque: ArrayLike | None = None
) -> Array:
    r"""Euler's equations: the body-frame angular acceleration $\dot ω = I^{-1}(τ + (Iω) \times ω)$.

    For principal moments this is $I_1 \dot ω_1 = (I_2 - I_3) ω_2 ω_3 + τ_1$ and cyclic.

    **Arguments:**

    - `omega_body`: body-frame angular velocity ω, shape `(..., 3)`.
    - `inertia`: body-frame inertia, a symmetric positive-definite `(..., 3, 3)` matrix or the principal
      moments `(..., 3)`.
    - `torque`: optional body-frame torque τ, shape `(..., 3)`.

    **Returns:** $\dot ω$ in the body frame, shape `(..., 3)`.

    The inertia's symmetry and positivity are checked when it is concrete; under `jit` they are not.
    """
    omega_body = check_trailing(omega_body, 3, "omega_body")
    inertia = _check_inertia(inertia)
    named = [(omega_body, 1, "omega_body"), (inertia, _inertia_rank(inertia), "inertia")]
    if torque is not None:
        torque = check_trailing(torque, 3, "torque")
        named.append((torque, 1, "torque"))
    # ω and τ take the common batch shape (naming the arguments if they do not broadcast), so that
    # any broadcasting combination also works under `jax_numpy_rank_promotion='raise'`. The inertia
    # keeps its own: broadcast, principal moments (3,) against three bodies would read as a matrix.
    omega_body, _, *rest = broadcast_batch(*named)
    torque = rest[0] if rest else None
    unit, e = _unit_inertia(inertia)
    return _euler_rhs(omega_body, unit, _unit_inverse(unit), _scaled_torque(torque, e))


def kinetic_energy(omega_body: ArrayLike, inertia: ArrayLike) -> Array:
    r"""The rotational kinetic energy $T = \tfrac12\, ω \cdot I ω$.

    **Arguments:**

    - `omega_body`: angular velocity, shape `(..., 3)` (body frame with a body-frame inertia; any frame
      works when ω and I are in the same frame).
    - `inertia`: a symmetric positive-semidefinite `(..., 3, 3)` matrix or principal moments
      `(..., 3)`: T needs I, not its inverse, so a rod's or a single point mass's inertia (one zero
      moment, perhaps −1e-16 after rounding) is accepted, as `principal_axes` accepts it.

    **Returns:** T, shape `(...)`.
    """
    omega_body = check_trailing(omega_body, 3, "omega_body")
    inertia = _check_inertia(inertia, semidefinite=True)
    momentum = _apply_inertia(inertia, omega_body, ("inertia", "omega_body"))
    omega_body, momentum = broadcast_batch((omega_body, 1, "omega_body"), (momentum, 1, "inertia"))
    return 0.5 * jnp.sum(omega_body * momentum, axis=-1)


# --------------------------------------------------------------------------------------------------
# Rigid bodies


def _rigid_body_field(inertia: Array, torque, frame: str):
    """The field (t, q, ω_b) → (ω_b, ω̇_b) for a body-frame Lie step; `torque` in `frame`."""
    unit, e = _unit_inertia(inertia)
    inverse = _unit_inverse(unit)

    def field(t, q, omega_body):
        if torque is None:
            tau = None
        elif frame == "body":
            tau = _call_torque(torque, t, q, omega_body)
        else:
            omega = rotate_unchecked(omega_body, q)
            tau = rotate_unchecked(_call_torque(torque, t, q, omega), conjugate(q))
        return omega_body, _euler_rhs(omega_body, unit, inverse, _scaled_torque(tau, e))

    return field


def _call_torque(torque: Callable, t, q: Array, omega: Array) -> Array:
    """`torque(t, q, omega)`, checked at trace time to be `(..., 3)` broadcasting to ω's shape (it must
    not add batch axes), and broadcast to it."""
    tau = as_float_array(torque(t, q, omega), "torque(t, q, omega)")
    shape = tuple(tau.shape)
    if not (len(shape) > 0 and shape[-1] == 3 and broadcasts_to(shape, omega.shape)):
        raise ValueError(
            f"`torque(t, q, omega)` must return shape (..., 3) broadcasting to the angular velocity's "
            f"shape {tuple(omega.shape)}; got shape {shape}."
        )
    return jnp.broadcast_to(tau, omega.shape)


def _times(t0, dt, steps, dtype):
    """t0 + k Δt for integer step indices k (no accumulated round-off)."""
    return t0 + jnp.asarray(steps).astype(dtype) * dt


def body_step(method: str, field: Callable, t, q: Array, x, c, dt, index, renormalize_every):
    """One body-frame step of the coupled (q, x) system, `(q, x, c) -> (q, x, c)`: `lie_step`, or,
    when the compensations `c = (c_q, c_x)` are given (not None), q and x advanced by Kahan-compensated
    increments (`compensated_lie_step`); then, for a Lie method, q/|q| after every
    `renormalize_every`-th global step `index` (None: never), which resets c_q."""
    if c is None:
        q, x = lie_step(method, field, t, q, x, dt, frame="body")
        c_q = c_x = None
    else:
        q, x, (c_q, c_x) = compensated_lie_step(method, field, t, q, x, c, dt, frame="body")
    if renormalize_every is not None and method in LIE_METHODS:
        q, c_q = renormalized_when_due(index, q, c_q, renormalize_every)
    return q, x, None if c is None else (c_q, c_x)


def compensations(q: Array, x) -> tuple[Array, object]:
    """Zero Kahan compensations `(c_q, c_x)` for a state (q, x) (`body_step`)."""
    return jnp.zeros_like(q), jax.tree_util.tree_map(jnp.zeros_like, x)


class _LongRun(NamedTuple):
    """The static options of a simulation's fixed-step run (hashable: a compiled run's key)."""

    method: str
    num_steps: int
    save: str
    save_every: int
    compensated: bool
    renormalize_every: int | None


def _long_run_scan(run: _LongRun, field, t0, dt, dtype, carry0, output=lambda carry: carry):
    """`scan_steps` of `body_step` from `carry0 = (q0, x0)`; the final carry and the saved ones are
    `output((q, x))` (the compensations, when there are, are not returned)."""
    every = run.renormalize_every
    if every is not None and every > run.num_steps:
        every = None  # a run shorter than the interval never renormalises: no conditional at all
    c0 = compensations(*carry0) if run.compensated else None

    def step_fn(k, carry):
        q, x, c = carry
        return body_step(run.method, field, _times(t0, dt, k, dtype), q, x, c, dt, k, every)

    final, saved = scan_steps(
        step_fn,
        (*carry0, c0),
        run.num_steps,
        save=run.save,
        save_every=run.save_every,
        output=lambda carry: output(carry[:2]),
    )
    return final[:2], saved


# The advice of `check_times_advance` for a run whose times take the state's dtype.
_WIDEN_STATE = " or use a float64 state (jax_enable_x64 and a float64 q0), whose times are float64"


def simulate_rigid_body(
    q0: ArrayLike,
    omega0: ArrayLike,
    inertia: ArrayLike,
    dt: ArrayLike,
    num_steps: int,
    *,
    torque: Callable | None = None,
    frame: str = "body",
    method: str = "cf4",
    save: str = "all",
    save_every: int = 1,
    t0: ArrayLike = 0.0,
    compensated: bool | None = None,
    renormalize_every: int | None = 1000,
) -> tuple[Array, Array]:
    r"""Integrate the attitude and angular velocity of a rigid body under Euler's equations.

    $$\dot q = \tfrac12\, q\, \tilde ω_b, \qquad I \dot ω_b = τ_b + (I ω_b) \times ω_b,$$

    with a fixed step on the Lie group: the orientation moves by exponentials (it stays unit to
    round-off), ω by the Runge–Kutta scheme of the same method. With `method="cf4"` (default) the
    scheme is fourth order. For a torque-free body the kinetic energy and the world angular momentum
    are not conserved exactly (classical Runge–Kutta for ω is not a symplectic or energy-preserving
    method): their errors drift, linearly in time and like Δt⁵ (for I = (1, 2, 3) and
    ω₀ = (1.1, 0, 0.8) rad/s the relative energy error after 1,000 s is −4.3e-7 at Δt = 0.05 s and
    32× less at Δt = 0.025 s; round-off, ~1e-13, over 10⁵ steps of 1e-3 s). For very long horizons
    use a smaller step, or diffrax with `rigid_body_vector_field` and a tolerance.

    **Arguments:**

    - `q0`: initial orientation (body → world), shape `(..., 4)`.
    - `omega0`: initial angular velocity, shape `(..., 3)`, in the frame `frame`.
    - `inertia`: body-frame inertia: a symmetric positive-definite `(..., 3, 3)` matrix or principal
      moments `(..., 3)` (checked when concrete; not under `jit`). Euler's equations hold for any
      positive moments, so moments that no body of masses has are accepted: a real body's satisfy
      I₁ + I₂ ≥ I₃ (their difference is 2Σmz²), and (1, 1, 5) is most likely a typo.
    - `dt`: the time step (a scalar); `num_steps`: the number of steps (a Python int ≥ 0).
    - `torque`: optional callable `torque(t, q, omega) -> (..., 3)` giving the torque in the frame
      `frame` from the time, the orientation and the angular velocity (in that frame). It is evaluated
      at the method's stages and may close over parameters to differentiate. Its result must
      broadcast to the shape of `omega` (checked at trace time).
    - `frame`: `"body"` (default; `omega0`, `omegas` and the torque are body-frame) or `"world"`.
    - `method`: `"cf4"`, `"midpoint"`, `"euler"`, `"rk4"` or `"naive"` (see `jaxquat.integrate`).
    - `save`: `"all"` (every `save_every`-th state, including the initial one) or `"final"`;
      `save_every` ≥ 1 must divide `num_steps`.
    - `t0`: the initial time (a scalar, passed to `torque`). Times take q0's dtype: with a torque
      that reads t, a `ValueError` when its step times t0 + k·dt need not increase (see
      `jaxquat.integrate`).
    - `compensated`, `renormalize_every`: the long-run mode of `integrate`, for the Lie methods
      (`"cf4"`, `"midpoint"`, `"euler"`): q and ω advanced in Kahan-compensated increments (default:
      on for float32 and float16 states), and q/|q| every `renormalize_every` steps (`None`: never).
      As in `integrate`, a non-unit `q0` keeps its norm until the first renormalisation, which
      scales the state to |q| = 1. In float32, 10⁵ steps of 1e-3 s of a sphere spinning at 1.4 rad/s
      end 1e-7 to 3e-6 rad from the closed form with them (depending on the axis: about float32's
      rounding of ωΔt, times the 140 rad turned), and 1.7e-3 rad (cf4; |q| − 1 = −4.8e-4) or 7e-6 to
      2.6e-5 rad (midpoint, euler) without. An asymmetric body (I = (1, 2, 3), ω₀ = (1.1, 0, 0.8)
      rad/s) ends 9.9e-6 rad from the float64 run after those 10⁵ steps, 3.3e-4 rad without.

    **Returns:** `(qs, omegas)`: time-major orientations `(num_saved, ..., 4)` and angular velocities
    `(num_saved, ..., 3)` in the frame `frame` (without the time axis for `save="final"`).

    Differentiable in `q0`, `omega0`, `inertia`, `dt`, `t0` and the torque's parameters; reverse mode
    uses checkpointing, so memory stays bounded over long runs.

    Without a torque, or with an `equinox.Module` torque (arrays as fields), the run is compiled once
    per shapes, dtypes, options and Module type and static fields: new values of the arrays, those
    inside the Module included, reuse it (a repeated call outside `jit` takes milliseconds instead
    of the 0.4–0.5 s of tracing and compiling). Any other callable (a function, a bound method, a
    `functools.partial`) is traced and compiled again at each call, since it may read state that
    changes between calls (`integrate` instead keys such a callable by its identity, as `jax.jit`
    does). A Module holding NumPy values (arrays or scalars) is traced again too.

    **Reference:** L. D. Landau & E. M. Lifshitz, *Mechanics*, §§35–37; E. Celledoni, A. Marthinsen &
    B. Owren, *Commutator-free Lie group methods*, FGCS 19 (2003).
    """
    frame = check_frame(frame)
    method = check_choice(method, _METHODS, "method")
    check_choice(save, ("all", "final"), "save")
    num_steps, save_every = _check_steps(num_steps, save, save_every)
    q0 = check_trailing(q0, 4, "q0")
    omega0 = check_trailing(omega0, 3, "omega0")
    inertia = _check_inertia(inertia)
    if torque is not None:
        check_callable(torque, "torque", "torque(t, q, omega)", 3)
    dtype = q0.dtype  # the orientation's dtype governs, as in `integrate`
    q0, omega0, inertia = q0.astype(dtype), omega0.astype(dtype), inertia.astype(dtype)
    # The inertia keeps its own shape (it broadcasts in the arithmetic): broadcast to a batch of
    # three bodies, shared moments (3,) would become (3, 3) and be read as a matrix.
    q0, omega0, _ = broadcast_batch(
        (q0, 1, "q0"), (omega0, 1, "omega0"), (inertia, _inertia_rank(inertia), "inertia")
    )
    t0_given, dt_given = t0, dt
    dt = _check_finite_scalar(dt, "dt").astype(dtype)
    t0 = _check_finite_scalar(t0, "t0").astype(dtype)
    if torque is not None:
        reads, what = _reads_time(torque, q0, omega0), "`torque(t, q, omega)`"
        check_times_advance(t0_given, dt_given, num_steps, dtype, what, reads, _WIDEN_STATE, method)

    compensated, renormalize_every = long_run_options(method, dtype, compensated, renormalize_every)
    run = _LongRun(method, num_steps, save, save_every, compensated, renormalize_every)
    simulate = _rigid_body_run_compiled if reusable_callable(torque) else _rigid_body_run
    return simulate(q0, omega0, inertia, dt, t0, torque, frame, run)


def _rigid_body_run(q0, omega0, inertia, dt, t0, torque, frame: str, run: _LongRun):
    omega_body0 = omega0 if frame == "body" else rotate(omega0, conjugate(q0))
    field = _rigid_body_field(inertia, torque, frame)
    final, saved = _long_run_scan(run, field, t0, dt, q0.dtype, (q0, omega_body0))
    qs, omegas = final if run.save == "final" else saved
    if frame == "world":
        omegas = rotate(omegas, qs)
    return qs, omegas


# Each call outside `jit` traced and compiled the whole run again: 0.4-0.5 s for 100-1,000 steps.
_rigid_body_run_compiled = eqx.filter_jit(_rigid_body_run)


class _RigidBodyVectorField(eqx.Module):
    inertia: Array
    torque: Callable | None = eqx.field(static=True)
    frame: str = eqx.field(static=True)

    def __call__(self, t, y, args):
        if not isinstance(y, (tuple, list)) or len(y) != 2:
            raise ValueError(
                "the state `y` must be a pair (q, omega) of arrays of shapes (..., 4) and (..., 3); "
                f"got {type(y).__name__}"
                + (f" of length {len(y)}." if isinstance(y, (tuple, list)) else ".")
            )
        q = check_trailing(y[0], 4, "y[0] (q)")
        omega = check_trailing(y[1], 3, "y[1] (omega)")
        broadcast_batch((q, 1, "y[0] (q)"), (omega, 1, "y[1] (omega)"))  # a clear error, or nothing
        omega_body = omega if self.frame == "body" else rotate_unchecked(omega, conjugate(q))
        field = _rigid_body_field(self.inertia, self.torque, self.frame)
        _, omega_dot_body = field(t, q, omega_body)
        if self.frame == "body":
            return rate(q, omega, frame="body"), omega_dot_body
        # d/dt (R ω_b) = R ω̇_b + ω × ω = R ω̇_b.
        return rate(q, omega, frame="world"), rotate_unchecked(omega_dot_body, q)


def rigid_body_vector_field(
    inertia: ArrayLike, *, torque: Callable | None = None, frame: str = "body"
) -> Callable:
    r"""The rigid body as a diffrax vector field `f(t, (q, ω), args) -> (q̇, ω̇)` on tuple states.

    Body frame: $\dot q = \tfrac12 q \tilde ω$, $\dot ω = I^{-1}(τ + Iω \times ω)$; world frame:
    $\dot q = \tfrac12 \tilde ω q$, $\dot ω = R\,\dot ω_b$. The same system `simulate_rigid_body`
    integrates, for `diffrax.ODETerm` with jaxquat's Lie-group solvers (`CF4`, `RKMK45`, …), which move
    q on the sphere and ω by their Runge–Kutta tableau.

    **Arguments:**

    - `inertia`: body-frame inertia, `(..., 3, 3)` or principal moments `(..., 3)`.
    - `torque`: optional callable `torque(t, q, omega)` in the frame `frame`; its result must
      broadcast to the shape of ω (checked at trace time).
    - `frame`: `"body"` (default) or `"world"`: the frame of ω and of the torque.

    **Returns:** a callable PyTree (an `equinox.Module`; the inertia is a differentiable leaf).

    **Errors:** a `ValueError` for a bad `inertia`, `frame` or `torque` here, and at trace time of
    a call for a state that is not a pair `(q (..., 4), ω (..., 3))` with broadcastable batch axes
    (naming `y[0] (q)` or `y[1] (omega)`) or a torque of the wrong shape.
    """
    frame = check_frame(frame)
    inertia = _check_inertia(inertia)
    if torque is not None:
        check_callable(torque, "torque", "torque(t, q, omega)", 3)
    return _RigidBodyVectorField(inertia, torque, frame)


# --------------------------------------------------------------------------------------------------
# Shape-changing bodies


def _centred(masses: Array, x: Array) -> Array:
    """Positions relative to their centre of mass."""
    return x - center_of_mass(masses, x)[..., None, :]


def _shape_state(masses: Array, positions: Callable, t: Array) -> tuple[Array, Array, Array, Array]:
    """(J, e, K, e_K): the inertia about the centre of mass J·2ᵉ (`_point_inertia_scaled`) and the
    internal angular momentum of the shape at time t, L_int = K·2^(e_K).

    The shape velocities are the exact time derivative of `positions` (forward-mode autodiff).
    L_int is summed from masses, positions and velocities at scale 1 (as I is): at its own scale it
    underflowed float32 to 0 for molecules over seconds (1e-46; the body did not turn) and
    overflowed for stars at 1 au (1e52; NaN).
    """
    x, v = jax.jvp(positions, (t,), (jnp.ones_like(t),))
    relative, e_length = prescale(_centred(masses, x), axes=(-2, -1), limit=0)
    masses, e_mass = prescale(masses, limit=0)
    v, e_speed = prescale(v, axes=(-2, -1), limit=0)
    unit = _unit_point_inertia(masses, relative)
    internal = _moment(masses, cross(relative, v))
    return unit, e_mass + 2 * e_length, internal, e_mass + e_length + e_speed


def _check_not_collinear(masses: Array, positions: Callable, t0: Array) -> None:
    """A `ValueError` when the shape at t0 is one point or a line (checked when concrete): its inertia
    about the centre of mass is then singular, and the spin about that line is not determined."""
    if is_tracer(masses) or is_tracer(t0):
        return
    x0 = positions(t0)
    if is_tracer(x0):
        return
    x0 = jnp.asarray(x0)
    if not (np.all(np.isfinite(np.asarray(x0))) and np.all(np.isfinite(np.asarray(masses)))):
        return  # NaN in, NaN out
    # The inertia up to its scale (a power of two): I itself may underflow (a float32 molecule in
    # SI units has I ≈ 1e-46 and came out 0, "a single point"), the moments' ratio does not.
    moments = np.linalg.eigvalsh(
        np.asarray(_point_inertia_scaled(masses, _centred(masses, x0))[0], np.float64)
    )
    if moments[0] <= 8.0 * float(jnp.finfo(t0.dtype).eps) * moments[-1]:
        what = "a single point" if moments[-1] <= 0 else "on one line"
        raise ValueError(
            f"`positions(t0)`: the point masses are {what} at t0, so the inertia about the centre "
            f"of mass is singular (principal moments {moments.tolist()}): its rotation is "
            "undetermined; the body needs at least three points not on one line."
        )


def _inertia_exponent(masses: Array, positions: Callable, t: Array) -> Array:
    """The e of I(t) = J·2ᵉ with J's largest entry in [½, 1) (integer-valued, no derivative)."""
    unit, e = _point_inertia_scaled(masses, _centred(masses, positions(t)))
    return e + _unit_inertia(unit)[1]


def _deformable_field(masses: Array, positions: Callable, e0: Array):
    """(t, q, P) → (ω_b, Ṗ) for the scaled body-frame momentum P = Π·2^(−e0), with
    ω_b = I(t)⁻¹(Π − L_int(t)) and Π̇ = Π × ω_b.

    Π and I are carried at the scale of ω (`e0` the exponent of I(t0), `_inertia_exponent`): at their
    own scale a float32 molecule in SI units (I ≈ 1e-46, Π ≈ 1e-34) underflowed I and overflowed I⁻¹
    (q was NaN), and the Kahan compensation of Π (≈ 1e-41) was subnormal (1e-4 rad off).
    """

    def field(t, q, momentum):
        unit, e, internal, e_internal = _shape_state(masses, positions, t)
        unit, e_unit = _unit_inertia(unit)
        # ω_b = J⁻¹(P − L_int·2^(−e0))·2^(e0 − e) with I = J·2ᵉ: neither I nor I⁻¹ nor L_int at its
        # own scale.
        relative = momentum - power_of_two_times(internal, (e_internal - e0)[..., None])
        omega_body = _apply_inertia(
            _unit_inverse(unit), power_of_two_times(relative, (e0 - e - e_unit)[..., None])
        )
        return omega_body, cross(momentum, omega_body)

    return field


def simulate_deformable_body(
    masses: ArrayLike,
    positions: Callable,
    q0: ArrayLike,
    dt: ArrayLike,
    num_steps: int,
    *,
    angular_momentum: ArrayLike | None = None,
    method: str = "cf4",
    save: str = "all",
    save_every: int = 1,
    t0: ArrayLike = 0.0,
    compensated: bool | None = None,
    renormalize_every: int | None = 1000,
) -> tuple[Array, Array]:
    r"""The orientation of a shape-changing body (a falling cat) from conservation of angular momentum.

    The body is a set of point masses whose body-frame positions $x_i(t)$ are prescribed; the
    orientation q(t) (body → world) follows from the conserved world angular momentum L. With the
    body-frame momentum $Π = q^{-1} L q$, the inertia $I(t)$ about the centre of mass and the internal
    momentum $L_{\mathrm{int}}(t) = \sum_i m_i (x_i - c) \times \dot x_i$:

    $$ω_b = I(t)^{-1}(Π - L_{\mathrm{int}}), \qquad \dot Π = Π \times ω_b, \qquad
      \dot q = \tfrac12\, q\, \tilde ω_b.$$

    The shape velocities $\dot x_i$ are the exact derivatives of `positions` (by `jax.jvp`, not finite
    differences). With L = 0 a cyclic change of shape can still give a net rotation (a geometric phase).

    **Arguments:**

    - `masses`: positive masses, shape `(n,)`, n ≥ 3 (positivity checked when concrete).
    - `positions`: a callable `positions(t) -> (n, 3)` giving the body-frame shape; it must be
      differentiable in t and traceable by JAX. Its centre of mass may move; it is removed. The
      points must not all lie on one line (nor coincide): I(t) is then singular and the spin about
      that line undetermined — a `ValueError` when that holds at t0 and the inputs are concrete.
      A shape that reaches a line *later* is not detected: the spin about the line (L over a moment
      that goes to 0) has no bounded integral, and the result is NaN only when a step or stage time
      lands on that instant exactly; otherwise it is a finite unit quaternion that does not
      converge as dt → 0 (it changes completely with dt). Keep the smallest principal moment of
      `inertia_tensor(masses, positions(t))` away from 0 over the run (check it on a grid of t).
    - `q0`: initial orientation, shape `(4,)`.
    - `dt`, `num_steps`: the time step (a scalar) and the number of steps (a Python int ≥ 0).
    - `angular_momentum`: the conserved world-frame angular momentum about the centre of mass,
      shape `(3,)`; zero by default.
    - `method`, `save`, `save_every`, `t0`, `compensated`, `renormalize_every`: as for
      `simulate_rigid_body` (a `ValueError` when `positions` reads t and its step times
      t0 + k·dt in q0's dtype need not increase).

    **Returns:** `(qs, world_positions)`: orientations `(num_saved, 4)` and the inertial-frame positions
    $q (x_i - c) q^{-1}$ `(num_saved, n, 3)` with the centre of mass at the origin (without the time axis
    for `save="final"`). Use `jax.vmap` for many bodies.

    With `positions` an `equinox.Module`, the run is compiled once and reused as in
    `simulate_rigid_body` (new masses, `q0`, `dt`, `t0`, angular momentum or Module arrays); a plain
    function is traced and compiled again at each call (2 s for 200 steps of a three-point shape).

    **Reference:** the model of the Julia package DeformableBodies.jl (I. Leal, 2020), there solved with
    finite-difference velocities and a general-purpose ODE solver.
    """
    method = check_choice(method, _METHODS, "method")
    check_choice(save, ("all", "final"), "save")
    num_steps, save_every = _check_steps(num_steps, save, save_every)
    check_callable(positions, "positions", "positions(t)", 1)
    masses = as_float_array(masses, "masses")
    q0 = check_trailing(q0, 4, "q0")
    if q0.shape != (4,):
        raise ValueError(
            f"`q0` must have shape (4,) (use jax.vmap for many bodies); got {tuple(q0.shape)}."
        )
    if masses.ndim != 1:
        raise ValueError(f"`masses` must have shape (n,); got shape {tuple(masses.shape)}.")
    _check_nonempty(masses.shape[0])
    dtype = q0.dtype  # the orientation's dtype governs, as in `integrate`
    t0_given, dt_given = t0, dt
    t0 = _check_finite_scalar(t0, "t0").astype(dtype)
    dt = _check_finite_scalar(dt, "dt").astype(dtype)
    try:  # a nested list is an array too (as in the integration below)
        shape = jax.eval_shape(lambda t: jnp.asarray(positions(t)), t0).shape
    except (TypeError, ValueError) as e:  # None: "None is not a valid value for jnp.array"
        raise ValueError(
            f"`positions(t)` must return an array of shape (n, 3); calling it at t0 gave: {e}"
        ) from None
    if shape != (masses.shape[0], 3):
        raise ValueError(
            f"`positions(t)` must return shape (n, 3) = ({masses.shape[0]}, 3) to match `masses`; "
            f"got shape {shape}."
        )
    reads = _reads_time(positions)
    check_times_advance(
        t0_given, dt_given, num_steps, dtype, "`positions(t)`", reads, _WIDEN_STATE, method
    )
    _check_positive_masses(masses)
    _check_not_collinear(masses, positions, t0)
    masses, q0 = masses.astype(dtype), q0.astype(dtype)
    compensated, renormalize_every = long_run_options(method, dtype, compensated, renormalize_every)
    if angular_momentum is None:
        momentum_world = jnp.zeros((3,), dtype)
    else:
        momentum_world = check_trailing(angular_momentum, 3, "angular_momentum").astype(dtype)
        if momentum_world.shape != (3,):
            raise ValueError(
                f"`angular_momentum` must have shape (3,); got shape {tuple(momentum_world.shape)}."
            )
    run = _LongRun(method, num_steps, save, save_every, compensated, renormalize_every)
    simulate = _deformable_run_compiled if reusable_callable(positions) else _deformable_run
    return simulate(masses, positions, q0, momentum_world, dt, t0, run)


def _deformable_run(masses, positions, q0, momentum_world, dt, t0, run: _LongRun):
    dtype = q0.dtype

    def body_positions(t):
        return jnp.asarray(positions(t)).astype(dtype)

    e0 = _inertia_exponent(masses, body_positions, t0)
    field = _deformable_field(masses, body_positions, e0)

    carry0 = (q0, power_of_two_times(rotate(momentum_world, conjugate(q0)), -e0))
    final, qs = _long_run_scan(run, field, t0, dt, dtype, carry0, output=lambda carry: carry[0])

    def world_positions(t, q):
        return rotate(_centred(masses, body_positions(t)), q)

    if run.save == "final":
        return final[0], world_positions(_times(t0, dt, run.num_steps, dtype), final[0])
    times = _times(t0, dt, run.save_every * jnp.arange(qs.shape[0]), dtype)
    return qs, jax.vmap(world_positions)(times, qs)


_deformable_run_compiled = eqx.filter_jit(_deformable_run)  # (a `reusable_callable` `positions`)
