"""Rigid-body dynamics and shape-changing bodies, tested against closed-form mechanics.

The torque-free asymmetric top is compared with an independent reference written here in NumPy/SciPy
(Jacobi elliptic functions for ω, Landau & Lifshitz §37 for the attitude), which is itself checked to
satisfy Euler's equations and the kinematics by finite differences before it is used.
"""

import functools

import diffrax
import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest
from helpers import (
    SEED_MASSES,
    SEED_POSITIONS,
    SEED_ROTATED,
    assert_quat_close,
    central_jacobian,
    count_lowerings,
    quat_distance,
    random_unit,
)
from jax.test_util import check_grads
from scipy import special
from scipy.spatial.transform import Rotation

import jaxquat as jq

# --------------------------------------------------------------------------------------------------
# Independent NumPy reference: quaternions and the torque-free asymmetric top


def np_multiply(p, q):
    pw, px, py, pz = np.moveaxis(np.asarray(p, float), -1, 0)
    qw, qx, qy, qz = np.moveaxis(np.asarray(q, float), -1, 0)
    return np.stack(
        [
            pw * qw - px * qx - py * qy - pz * qz,
            pw * qx + px * qw + py * qz - pz * qy,
            pw * qy - px * qz + py * qw + pz * qx,
            pw * qz + px * qy - py * qx + pz * qw,
        ],
        axis=-1,
    )


def np_conjugate(q):
    return np.asarray(q, float) * np.array([1.0, -1.0, -1.0, -1.0])


def np_rotate(v, q):
    v = np.asarray(v, float)
    pure = np.concatenate([np.zeros(v.shape[:-1] + (1,)), v], axis=-1)
    return np_multiply(np_multiply(q, pure), np_conjugate(q))[..., 1:]


def np_axis_quaternion(axis, angle):
    """Rotation by `angle` about the coordinate axis `axis` (0, 1, 2)."""
    angle = np.asarray(angle, float)
    q = np.zeros(angle.shape + (4,))
    q[..., 0] = np.cos(angle / 2)
    q[..., 1 + axis] = np.sin(angle / 2)
    return q


# A proper relabelling of body axes, x' = P x with P = [[0,0,1],[0,-1,0],[1,0,0]] (axes 1 and 3 swapped,
# axis 2 reversed: det P = +1), the rotation by π about (1, 0, 1)/√2.
_RELABEL = np.array([[0.0, 0.0, 1.0], [0.0, -1.0, 0.0], [1.0, 0.0, 0.0]])
_RELABEL_Q = np.array([0.0, 1.0, 0.0, 1.0]) / np.sqrt(2.0)


def torque_free_reference(moments, omega0, q0, times):
    """Closed-form motion of a torque-free asymmetric top with principal moments I₁ < I₂ < I₃.

    Landau & Lifshitz, Mechanics §37. For M² > 2EI₂ (else the axes are relabelled 1 ↔ 3 by the proper
    rotation P above, so the same formulas apply in the primed frame):
      ω₁ = A₁ cn u, ω₂ = σ₂ A₂ sn u, ω₃ = σ₃ A₃ dn u, u = λt + u₀,
      A₁² = (2EI₃ − M²)/(I₁(I₃ − I₁)), A₂² = (2EI₃ − M²)/(I₂(I₃ − I₂)), A₃² = (M² − 2EI₁)/(I₃(I₃ − I₁)),
      λ² = (I₃ − I₂)(M² − 2EI₁)/(I₁I₂I₃), m = k² = (I₂ − I₁)(2EI₃ − M²)/((I₃ − I₂)(M² − 2EI₁)),
    with σ₃ = sgn ω₃(0) and σ₂ = σ₃ sgn(I₃ − I₂) (substituting into Euler's equations fixes σ₂σ₃).
    Attitude: with Z along the conserved momentum M, the ZXZ Euler angles (φ, θ, ψ) of the body satisfy
      cos θ = I₃ω₃/M, tan ψ = I₁ω₁/(I₂ω₂), φ̇ = M(2E − I₃ω₃²)/(M² − I₃²ω₃²),
    and body → world is R = R_align R_z(φ) R_x(θ) R_z(ψ), R_align fixed by q(0) = q0. φ is the integral
    of φ̇ (composite 20-point Gauss–Legendre, exponentially accurate for this analytic integrand).

    Returns (qs, omegas, info) at `times` (ω in body coordinates), info with λ, m, K(m).
    """
    moments = np.asarray(moments, float)
    omega0 = np.asarray(omega0, float)
    times = np.asarray(times, float)
    assert moments[0] < moments[1] < moments[2]
    two_energy = np.sum(moments * omega0**2)
    momentum_sq = np.sum((moments * omega0) ** 2)
    momentum = np.sqrt(momentum_sq)
    relabel = momentum_sq < two_energy * moments[1]
    if relabel:
        moments, omega0, q_relabel = moments[::-1], _RELABEL @ omega0, _RELABEL_Q
    else:
        q_relabel = np.array([1.0, 0.0, 0.0, 0.0])
    i1, i2, i3 = moments
    a1 = np.sqrt((two_energy * i3 - momentum_sq) / (i1 * (i3 - i1)))
    a2 = np.sqrt((two_energy * i3 - momentum_sq) / (i2 * (i3 - i2)))
    a3 = np.sqrt((momentum_sq - two_energy * i1) / (i3 * (i3 - i1)))
    lam = np.sqrt((i3 - i2) * (momentum_sq - two_energy * i1) / (i1 * i2 * i3))
    m = (i2 - i1) * (two_energy * i3 - momentum_sq) / ((i3 - i2) * (momentum_sq - two_energy * i1))
    sigma3 = np.sign(omega0[2])
    sigma2 = np.sign(i3 - i2) * sigma3
    u0 = special.ellipkinc(np.arctan2(omega0[1] / (sigma2 * a2), omega0[0] / a1), m)

    def omega(t):
        sn, cn, dn, _ = special.ellipj(lam * t + u0, m)
        return np.stack([a1 * cn, sigma2 * a2 * sn, sigma3 * a3 * dn], axis=-1)

    def theta_psi(t):
        body_momentum = moments * omega(t)
        theta = np.arccos(np.clip(body_momentum[..., 2] / momentum, -1.0, 1.0))
        return theta, np.arctan2(body_momentum[..., 0], body_momentum[..., 1])

    def phi_rate(t):
        w3 = omega(t)[..., 2]
        return momentum * (two_energy - i3 * w3**2) / (momentum_sq - (i3 * w3) ** 2)

    nodes, weights = np.polynomial.legendre.leggauss(20)
    edges = np.concatenate([[0.0], times])
    increments = []
    for a, b in zip(edges[:-1], edges[1:], strict=True):
        cuts = np.linspace(a, b, int(np.ceil(abs(b - a) / 0.05)) + 1)
        mid, half = 0.5 * (cuts[1:] + cuts[:-1]), 0.5 * (cuts[1:] - cuts[:-1])
        increments.append(
            np.sum(half[:, None] * weights * phi_rate(mid[:, None] + half[:, None] * nodes))
        )
    phi = np.cumsum(increments)

    def attitude(phi, theta, psi):
        q = np_multiply(np_axis_quaternion(2, phi), np_axis_quaternion(0, theta))
        return np_multiply(np_multiply(q, np_axis_quaternion(2, psi)), q_relabel)

    q_align = np_multiply(q0, np_conjugate(attitude(0.0, *theta_psi(np.array(0.0)))))
    qs = np_multiply(q_align, attitude(phi, *theta_psi(times)))
    omegas = omega(times)
    if relabel:
        omegas = omegas @ _RELABEL  # Pᵀ ω' with P symmetric
    return qs, omegas, {"lam": lam, "m": m, "K": special.ellipk(m)}


def np_euler_rhs(moments, w):
    i1, i2, i3 = moments
    return np.stack(
        [
            (i2 - i3) * w[..., 1] * w[..., 2] / i1,
            (i3 - i1) * w[..., 2] * w[..., 0] / i2,
            (i1 - i2) * w[..., 0] * w[..., 1] / i3,
        ],
        axis=-1,
    )


# One compiled simulator shared by the tests (jit caches on the static arguments and the shapes, so
# runs that differ only in values reuse the compilation).
simulate = jax.jit(
    jq.simulate_rigid_body,
    static_argnames=("num_steps", "torque", "frame", "method", "save", "save_every"),
)

MOMENTS = np.array([1.0, 2.0, 3.0])
Q0 = np.array([0.5, 0.5, -0.5, 0.5])
# One initial rate on each side of the separatrix M² = 2EI₂, and one with negative components.
OMEGA0S = [np.array([0.3, 1.0, 0.8]), np.array([1.0, 0.5, 0.2]), np.array([-0.4, 0.7, -1.0])]


@pytest.mark.parametrize("omega0", OMEGA0S)
def test_reference_satisfies_the_equations_of_motion(omega0):
    times = np.linspace(0.0, 20.0, 41)
    h = 1e-4
    qs, ws, _ = torque_free_reference(MOMENTS, omega0, Q0, times)
    q_plus, w_plus, _ = torque_free_reference(MOMENTS, omega0, Q0, times + h)
    q_minus, w_minus, _ = torque_free_reference(MOMENTS, omega0, Q0, times - h)
    # Sign-align the neighbours (ψ wraps by 2π, which flips the quaternion's sign).
    q_plus *= np.sign(np.sum(q_plus * qs, axis=-1))[:, None]
    q_minus *= np.sign(np.sum(q_minus * qs, axis=-1))[:, None]
    scale = np.max(np.abs(ws))
    np.testing.assert_allclose(
        (w_plus - w_minus) / (2 * h), np_euler_rhs(MOMENTS, ws), atol=1e-8 * scale
    )
    pure = np.concatenate([np.zeros((len(times), 1)), ws], axis=-1)
    np.testing.assert_allclose(
        (q_plus - q_minus) / (2 * h), 0.5 * np_multiply(qs, pure), atol=1e-8 * scale
    )
    np.testing.assert_allclose(ws[0], omega0, atol=1e-14)
    assert_quat_close(qs[0], Q0, atol=1e-14)
    np.testing.assert_allclose(np.linalg.norm(qs, axis=-1), 1.0, atol=1e-14)
    world_momentum = np_rotate(MOMENTS * ws, qs)
    np.testing.assert_allclose(
        world_momentum, np.broadcast_to(world_momentum[0], world_momentum.shape), atol=1e-12
    )


# --------------------------------------------------------------------------------------------------
# Acceptance 1: the torque-free asymmetric body


@pytest.mark.parametrize("omega0", OMEGA0S)
def test_torque_free_body_matches_closed_form(omega0):
    dt, num_steps, every = 1e-3, 20_000, 500
    qs, omegas = simulate(Q0, omega0, MOMENTS, dt, num_steps, save_every=every)
    times = dt * every * np.arange(qs.shape[0])
    q_ref, omega_ref, _ = torque_free_reference(MOMENTS, omega0, Q0, times)
    assert times[-1] == pytest.approx(20.0)
    # README: attitude within ~5e-13 over 20 s (the Δt⁴ truncation error; it was "1e-13", which a
    # reviewer's 1.6e-13 and 2.1e-13 for two of these bodies broke).
    assert quat_distance(qs, q_ref) < 5e-13
    np.testing.assert_allclose(omegas, omega_ref, rtol=0, atol=5e-13)


def test_torque_free_body_with_full_inertia_matrix(getkey):
    # The same body described in rotated body axes: I = R diag(I) Rᵀ, ω₀' = R ω₀, q' = q R⁻¹.
    rotation = random_unit(getkey())
    matrix = np.asarray(jq.to_matrix(rotation))
    inertia = matrix @ np.diag(MOMENTS) @ matrix.T
    inertia = 0.5 * (inertia + inertia.T)
    omega0 = OMEGA0S[0]
    q0_rotated = jq.multiply(Q0, jq.conjugate(rotation))
    qs, omegas = jq.simulate_rigid_body(
        q0_rotated, matrix @ omega0, inertia, 1e-3, 5_000, save_every=500
    )
    q_ref, omega_ref, _ = torque_free_reference(MOMENTS, omega0, Q0, 0.5 * np.arange(qs.shape[0]))
    assert quat_distance(jq.multiply(qs, rotation), q_ref) < 1e-9
    np.testing.assert_allclose(omegas, omega_ref @ matrix.T, atol=1e-9)
    # The principal axes recover the diagonal description.
    moments, q_principal = jq.principal_axes(inertia)
    np.testing.assert_allclose(moments, MOMENTS, rtol=1e-12)
    rebuilt = (
        np.asarray(jq.to_matrix(q_principal))
        @ np.diag(moments)
        @ np.asarray(jq.to_matrix(q_principal)).T
    )
    np.testing.assert_allclose(rebuilt, inertia, atol=1e-12)


def test_world_frame_matches_body_frame():
    omega0 = OMEGA0S[1]
    q_body, w_body = simulate(Q0, omega0, MOMENTS, 1e-3, 2_000, save_every=100)
    w_world0 = jq.rotate(omega0, Q0)
    q_world, w_world = jq.simulate_rigid_body(
        Q0, w_world0, MOMENTS, 1e-3, 2_000, save_every=100, frame="world"
    )
    assert quat_distance(q_body, q_world) < 1e-13
    np.testing.assert_allclose(w_world, jq.rotate(w_body, q_body), atol=1e-13)


def test_conservation_over_1e5_steps():
    omega0 = jnp.array([0.3, 1.0, 0.8])
    inertia = jnp.asarray(MOMENTS)
    qs, omegas = jq.simulate_rigid_body(Q0, omega0, inertia, 1e-3, 100_000, save_every=1_000)
    energy = jq.kinetic_energy(omegas, inertia[None])
    world_momentum = jq.rotate(inertia[None] * omegas, qs)
    assert qs.shape == (101, 4)
    # README: kept to ~1e-13 over 10⁵ steps (it said ~1e-14; a reviewer measured |ΔL| = 8.5e-14).
    np.testing.assert_allclose(energy, energy[0], rtol=1e-13)
    drift = np.linalg.norm(world_momentum - world_momentum[:1], axis=-1)
    assert np.max(drift) < 1e-13 * np.linalg.norm(world_momentum[0])
    np.testing.assert_allclose(np.linalg.norm(qs, axis=-1), 1.0, atol=1e-12)


def test_energy_drift_is_linear_in_time_and_fifth_order_in_the_step():
    """cf4 integrates ω by classical Runge–Kutta, which does not conserve energy: the docstring (once
    "without drift", which a review measured to be wrong) says the error drifts linearly in time and
    like Δt⁵. Relative energy error at t = 100 and 200 s for Δt = 0.1 and 0.05 s."""
    inertia, omega0 = jnp.array([1.0, 2.0, 3.0]), jnp.array([1.1, 0.0, 0.8])
    energy0 = jq.kinetic_energy(omega0, inertia)
    errors = []
    for dt in (0.1, 0.05):
        num_steps = int(round(200 / dt))
        _, omegas = jq.simulate_rigid_body(
            Q0, omega0, inertia, dt, num_steps, save_every=num_steps // 2
        )
        errors.append(np.asarray(jq.kinetic_energy(omegas[1:], inertia[None]) / energy0 - 1.0))
    for error in errors:
        assert np.all(error < 0), error
        assert 1.8 < error[1] / error[0] < 2.2, error  # linear in time
    order = np.log2(errors[0][1] / errors[1][1])
    assert 4.7 < order < 5.3, order


def test_fourth_order_convergence():
    # Steps T/200, T/400, T/800 (T = 7.3, not a period): one compiled run of 800 steps per step size,
    # read at step 200, 400 and 800 respectively.
    omega0 = OMEGA0S[0]
    q_ref, w_ref, _ = torque_free_reference(MOMENTS, omega0, Q0, [7.3])
    errors = []
    for num_steps in (200, 400, 800):
        qs, ws = simulate(Q0, omega0, MOMENTS, 7.3 / num_steps, 800, save_every=200)
        k = num_steps // 200
        errors.append(quat_distance(qs[k], q_ref[0]) + np.max(np.abs(ws[k] - w_ref[0])))
    orders = np.log2(np.array(errors[:-1]) / np.array(errors[1:]))
    assert np.all(orders > 3.7), (errors, orders)


# --------------------------------------------------------------------------------------------------
# Acceptance 2: the tennis-racket flip


def test_intermediate_axis_flip_period():
    omega0 = np.array([0.01, 1.0, 0.01])  # M² > 2EI₂: ω₂ ∝ sn, which changes sign every 2K(m)/λ
    _, _, info = torque_free_reference(MOMENTS, omega0, Q0, [0.0])
    expected = 2 * info["K"] / info["lam"]
    assert info["m"] > 0.999 and expected > 15.0
    dt, num_steps = 2e-3, 35_000
    _, omegas = simulate(Q0, omega0, MOMENTS, dt, num_steps)
    w2 = np.asarray(omegas[:, 1])
    crossings = []
    for k in np.nonzero(np.sign(w2[1:]) != np.sign(w2[:-1]))[0]:
        # Root of the cubic through four samples around the sign change (error O(dt⁴)).
        window = np.arange(k - 1, k + 3)
        poly = np.polynomial.Polynomial.fit(window * dt, w2[window], 3)
        roots = poly.roots()
        roots = roots[np.isreal(roots)].real
        crossings.append(roots[np.argmin(np.abs(roots - (k + 0.5) * dt))])
    periods = np.diff(crossings)
    assert len(periods) >= 2
    np.testing.assert_allclose(periods, expected, rtol=1e-6)


# --------------------------------------------------------------------------------------------------
# Acceptance 3: torques


@jax.jit
def _spin_up(torque_vector):
    """A body at rest under a constant body-frame torque, 300 steps of 0.01 s."""

    def torque(t, q, omega):
        return jnp.broadcast_to(torque_vector, omega.shape)

    return jq.simulate_rigid_body(
        Q0, jnp.zeros(3), MOMENTS, 0.01, 300, torque=torque, save_every=30
    )


@pytest.mark.parametrize("axis", [0, 1, 2])
def test_constant_torque_gives_uniform_angular_acceleration(axis):
    inertia = MOMENTS
    tau = 0.7
    qs, omegas = _spin_up(jnp.asarray(np.eye(3)[axis] * tau))
    t = 0.3 * np.arange(qs.shape[0])
    alpha = tau / inertia[axis]
    np.testing.assert_allclose(omegas, np.outer(alpha * t, np.eye(3)[axis]), atol=1e-13)
    expected = np_multiply(Q0, np_axis_quaternion(axis, 0.5 * alpha * t**2))
    assert quat_distance(qs, expected) < 1e-13


def _gravity_torque(mgl):
    """World-frame torque of gravity −mg Ẑ on a top whose centre of mass is at l ẑ_body."""

    def torque(t, q, omega):
        axis = jq.rotate(jnp.array([0.0, 0.0, 1.0]), q)
        return mgl * jnp.stack([-axis[..., 1], axis[..., 0], jnp.zeros_like(axis[..., 2])], axis=-1)

    return torque


def test_heavy_symmetric_top_steady_precession_and_fast_top_rate():
    # Steady precession (Goldstein §5.7): θ fixed, φ̇ = Ω, ψ̇ = s with I₁Ω² cos θ − I₃ω₃Ω + mgl = 0.
    # The slow root tends to the textbook fast-top rate mgl/(I₃ω₃), with relative correction
    # ≈ I₁ mgl cos θ/(I₃ω₃)².
    i1, i3, mgl, theta = 1.0, 0.5, 1.0, 0.6
    inertia = np.array([i1, i1, i3])
    q0 = np_axis_quaternion(0, theta)
    gravity = _gravity_torque(mgl)
    deviations = []
    for omega3 in (20.0, 40.0):
        b = i3 * omega3
        rate = (b - np.sqrt(b**2 - 4 * i1 * np.cos(theta) * mgl)) / (2 * i1 * np.cos(theta))
        omega0 = np.array([0.0, rate * np.sin(theta), omega3])
        dt, num_steps = 1e-3, 5_000
        # World-frame run (ω and torque in world coordinates).
        qs, _ = simulate(
            q0,
            jq.rotate(omega0, q0),
            inertia,
            dt,
            num_steps,
            torque=gravity,
            frame="world",
            save_every=500,
        )
        t = dt * 500 * np.arange(qs.shape[0])
        spin = omega3 - rate * np.cos(theta)
        expected = np_multiply(
            np_multiply(
                np_axis_quaternion(2, rate * t), np_axis_quaternion(0, np.full_like(t, theta))
            ),
            np_axis_quaternion(2, spin * t),
        )
        assert quat_distance(qs, expected) < 1e-8
        # Precession rate measured from the trajectory's symmetry axis.
        axis = np.asarray(jq.rotate(jnp.array([0.0, 0.0, 1.0]), qs))
        azimuth = np.unwrap(np.arctan2(axis[:, 0], -axis[:, 1]))
        measured = np.polyfit(t, azimuth, 1)[0]
        textbook = mgl / (i3 * omega3)
        deviations.append(measured / textbook - 1.0)
        np.testing.assert_allclose(
            measured / textbook - 1.0, i1 * mgl * np.cos(theta) / (i3 * omega3) ** 2, rtol=0.02
        )
    assert deviations[1] < deviations[0] / 3.5


def test_released_fast_top_precesses_at_textbook_rate():
    # A fast top released with pure spin nutates; its mean precession rate is mgl/(I₃ω₃) to O(1/ω₃²).
    i1, i3, mgl, theta = 1.0, 0.5, 1.0, 0.6
    q0 = np_axis_quaternion(0, theta)
    omega3 = 60.0
    dt, num_steps = 1e-3, 20_000
    qs, _ = jq.simulate_rigid_body(
        q0,
        np.array([0.0, 0.0, omega3]),
        np.array([i1, i1, i3]),
        dt,
        num_steps,
        torque=_body_gravity(mgl),
        save_every=10,
    )
    t = dt * 10 * np.arange(qs.shape[0])
    axis = np.asarray(jq.rotate(jnp.array([0.0, 0.0, 1.0]), qs))
    azimuth = np.unwrap(np.arctan2(axis[:, 0], -axis[:, 1]))
    measured = np.polyfit(t, azimuth, 1)[0]
    np.testing.assert_allclose(measured, mgl / (i3 * omega3), rtol=3e-3)


def _body_gravity(mgl):
    """Body-frame gravity torque on the top: l ẑ × (−mg ĝ_body), ĝ_body = q⁻¹ Ẑ q."""

    def torque(t, q, omega):
        up = jq.rotate(jnp.array([0.0, 0.0, 1.0]), jq.conjugate(q))
        return -mgl * jnp.stack([-up[..., 1], up[..., 0], jnp.zeros_like(up[..., 2])], axis=-1)

    return torque


# --------------------------------------------------------------------------------------------------
# Point masses (seed 001 parity), rotation of point sets, principal axes, Euler's equations

# The seed's five-point body and its printed results: SEED_* in helpers.py.


def test_seed_point_mass_example():
    com = jq.center_of_mass(SEED_MASSES, SEED_POSITIONS)
    np.testing.assert_allclose(
        com, [0.40704043526795597, 0.4993749112573767, 0.3619966261272671], rtol=1e-14
    )
    rotated = jq.rotate(SEED_POSITIONS, jnp.array([1.0, 2.0, 3.0, 4.0]), com)
    np.testing.assert_allclose(rotated, SEED_ROTATED, atol=1e-14)
    np.testing.assert_allclose(jq.center_of_mass(SEED_MASSES, rotated), com, atol=1e-14)


def test_rotate_point_sets(getkey):
    points = jax.random.normal(getkey(), (5, 3))
    q = random_unit(getkey())
    expected = np.stack([np_rotate(p, q) for p in np.asarray(points)])
    np.testing.assert_allclose(jq.rotate(points, q), expected, atol=1e-14)
    batch_points = jax.random.normal(getkey(), (4, 5, 3))
    qs = random_unit(getkey(), (4,))
    expected = np.stack(
        [
            [np_rotate(p, qb) for p in pts]
            for pts, qb in zip(np.asarray(batch_points), np.asarray(qs), strict=True)
        ]
    )
    np.testing.assert_allclose(jq.rotate(batch_points, qs[:, None]), expected, atol=1e-14)
    centres = jax.random.normal(getkey(), (4, 3))
    about = jq.rotate(batch_points, qs[:, None], centres[:, None])
    expected_about = np.stack(
        [
            [np_rotate(p - c, qb) + c for p in pts]
            for pts, qb, c in zip(
                np.asarray(batch_points), np.asarray(qs), np.asarray(centres), strict=True
            )
        ]
    )
    np.testing.assert_allclose(about, expected_about, atol=1e-14)


def test_inertia_and_angular_momentum_of_point_masses(getkey):
    masses = jax.random.uniform(getkey(), (6,), minval=0.5, maxval=2.0)
    positions = jax.random.normal(getkey(), (6, 3))
    c = np.asarray(jq.center_of_mass(masses, positions))
    m = np.asarray(masses)
    r = np.asarray(positions) - c
    expected = sum(
        mi * (ri @ ri * np.eye(3) - np.outer(ri, ri)) for mi, ri in zip(m, r, strict=True)
    )
    inertia = jq.inertia_tensor(masses, positions)
    np.testing.assert_allclose(inertia, expected, atol=1e-13)
    # Parallel-axis theorem for another reference point.
    p = np.array([0.3, -1.0, 2.0])
    d = c - p
    np.testing.assert_allclose(
        jq.inertia_tensor(masses, positions, about=p),
        expected + m.sum() * (d @ d * np.eye(3) - np.outer(d, d)),
        atol=1e-12,
    )
    # A rigid rotation about the centre of mass (plus a drift) has L = I ω and T = ½ ω·Iω.
    omega = np.array([0.4, -1.1, 0.7])
    drift = np.array([1.0, 2.0, -0.5])
    velocities = np.cross(omega, r) + drift
    momentum = jq.angular_momentum(masses, positions, velocities)
    np.testing.assert_allclose(momentum, expected @ omega, atol=1e-12)
    energy = 0.5 * np.sum(m * np.sum(np.cross(omega, r) ** 2, axis=-1))
    np.testing.assert_allclose(jq.kinetic_energy(omega, inertia), energy, rtol=1e-13)
    # The seed's definition (about the origin): Σ m x × v.
    np.testing.assert_allclose(
        jq.angular_momentum(masses, positions, velocities, about=jnp.zeros(3)),
        np.sum(m[:, None] * np.cross(np.asarray(positions), velocities), axis=0),
        atol=1e-12,
    )
    # Batched point sets.
    batch = jq.inertia_tensor(jnp.stack([masses, masses]), jnp.stack([positions, positions + 1.0]))
    np.testing.assert_allclose(batch, np.stack([expected, expected]), atol=1e-12)


def test_principal_axes(getkey):
    rotation = random_unit(getkey(), (3,))
    moments = jnp.array([[1.0, 2.0, 3.0], [0.5, 0.7, 1.1], [2.0, 2.5, 4.0]])
    matrices = jq.to_matrix(rotation)
    inertia = jnp.einsum("bij,bj,bkj->bik", matrices, moments, matrices)
    found, q = jq.principal_axes(inertia)
    np.testing.assert_allclose(found, moments, rtol=1e-12)
    np.testing.assert_allclose(jq.norm(q), 1.0, atol=1e-14)
    axes = np.asarray(jq.to_matrix(q))
    np.testing.assert_allclose(np.linalg.det(axes), 1.0, atol=1e-12)
    for k in range(3):
        column = axes[..., :, k]
        np.testing.assert_allclose(
            np.einsum("bij,bj->bi", inertia, column), moments[:, k : k + 1] * column, atol=1e-12
        )


@pytest.mark.parametrize("moments", [(1.0, 1.7, 2.4), (2.4, 1.7, 1.0)])
def test_principal_axes_quaternion_is_continuous_at_a_diagonal_inertia(moments):
    """eigh's arbitrary signs made q jump: diag(1, 1.7, 2.4) gave the identity, and 1e-7 added to one
    off-diagonal entry a half-turn about y, with a derivative that matched neither. Now q moves by
    O(perturbation) and jacfwd = jacrev = central differences at the diagonal itself."""

    def q_of(a):
        return jq.principal_axes(0.5 * (a + a.T))[1]

    diagonal = jnp.diag(jnp.asarray(moments))
    q = q_of(diagonal)
    for i, j in ((0, 1), (0, 2), (1, 2)):
        for delta in (1e-7, -1e-5):
            nearby = q_of(diagonal.at[i, j].add(delta))
            assert float(jnp.max(jnp.abs(nearby - q))) < 10 * abs(delta)
    forward = jax.jacfwd(q_of)(diagonal)
    np.testing.assert_allclose(jax.jacrev(q_of)(diagonal), forward, atol=1e-14)
    h = 1e-6
    for i, j in ((0, 1), (0, 2), (1, 2), (2, 2)):
        step = jnp.zeros((3, 3)).at[i, j].set(h)
        central = (q_of(diagonal + step) - q_of(diagonal - step)) / (2 * h)
        np.testing.assert_allclose(forward[:, i, j], central, atol=1e-8)


def test_principal_axes_of_a_rod():
    """Points on one line have a singular (semidefinite) inertia whose principal axes exist: the line,
    moment 0, and any two perpendicular axes. Its rounding residue (a moment of -2e-16) was refused as
    "not positive definite"; a truly negative moment still is."""
    direction = np.array([1.0, 2.0, 2.0]) / 3.0
    offsets = np.array([-1.5, 0.25, 2.0])
    masses = np.array([1.0, 2.0, 0.5])
    inertia = jq.inertia_tensor(masses, offsets[:, None] * direction[None, :])
    moments, q = jq.principal_axes(inertia)
    transverse = np.sum(masses * offsets**2)  # about the origin, which lies on the line
    np.testing.assert_allclose(moments, [0.0, transverse, transverse], atol=1e-13)
    axis = np.asarray(jq.rotate(np.array([1.0, 0.0, 0.0]), q))
    np.testing.assert_allclose(abs(axis @ direction), 1.0, atol=1e-14)
    with pytest.raises(ValueError, match="positive semidefinite.*got moments -1.0"):
        jq.principal_axes(jnp.diag(jnp.array([-1.0, 2.0, 3.0])))
    # The dynamics still require a positive definite inertia.
    with pytest.raises(ValueError, match="positive definite"):
        jq.euler_equations(jnp.ones(3), inertia)
    # The kinetic energy needs I, not I⁻¹: ½ Σ m |ω × x|², whichever sign the zero moment's rounding
    # took (it was refused as "not positive definite" about half the time), also as moments.
    omega = np.array([0.3, 0.4, -0.5])
    points = offsets[:, None] * direction[None, :]
    energy = 0.5 * np.sum(masses * np.sum(np.cross(omega, points) ** 2, axis=-1))
    rng = np.random.default_rng(2)
    for turn in Rotation.random(12, random_state=rng).as_matrix():
        turned = turn @ np.asarray(inertia) @ turn.T
        np.testing.assert_allclose(jq.kinetic_energy(turn @ omega, turned), energy, rtol=1e-13)
    np.testing.assert_allclose(
        jq.kinetic_energy(jnp.ones(3), jnp.array([0.0, 1.0, 1.0])), 1.0, rtol=1e-15
    )
    with pytest.raises(ValueError, match="positive semidefinite"):
        jq.kinetic_energy(jnp.ones(3), jnp.array([-1e-3, 1.0, 1.0]))


def test_euler_equations_component_form(getkey):
    omega = jax.random.normal(getkey(), (7, 3))
    torque = jax.random.normal(getkey(), (7, 3))
    moments = jnp.array([1.3, 2.1, 2.9])
    expected = np_euler_rhs(np.asarray(moments), np.asarray(omega)) + np.asarray(
        torque
    ) / np.asarray(moments)
    np.testing.assert_allclose(
        jq.euler_equations(omega, moments[None], torque), expected, atol=1e-13
    )
    np.testing.assert_allclose(
        jq.euler_equations(omega, jnp.diag(moments)[None], torque), expected, atol=1e-13
    )
    np.testing.assert_allclose(
        jq.euler_equations(omega, moments[None]),
        np_euler_rhs(np.asarray(moments), np.asarray(omega)),
        atol=1e-13,
    )
    # A full inertia: I ω̇ = τ + Iω × ω.
    a = np.asarray(jax.random.normal(getkey(), (3, 3)))
    inertia = a @ a.T + np.eye(3)
    w = np.asarray(omega[0])
    np.testing.assert_allclose(
        inertia @ np.asarray(jq.euler_equations(w, inertia, torque[0])),
        np.asarray(torque[0]) + np.cross(inertia @ w, w),
        atol=1e-12,
    )


@pytest.mark.parametrize(
    ("omega_shape", "inertia_shape", "torque_shape"),
    [
        ((3,), (3,), (5, 3)),  # the torque has more batch axes than ω and the inertia
        ((5, 3), (3,), (3,)),  # the torque has fewer
        ((3,), (5, 1, 3), (3,)),  # principal moments with batch axes of their own
        ((5, 3), (2, 1, 3, 3), (5, 3)),  # a batch of full inertias
        ((3,), (2, 1, 3, 3), (5, 3)),
        ((3, 3), (3,), (3,)),  # three bodies: the moments must not become a (3, 3) matrix
        ((3,), (3,), (3, 3)),
    ],
)
def test_euler_equations_broadcasts_every_argument(
    getkey, omega_shape, inertia_shape, torque_shape
):
    # The suite runs with `jax_numpy_rank_promotion='raise'`, under which these raised before.
    omega = np.asarray(jax.random.normal(getkey(), omega_shape))
    torque = np.asarray(jax.random.normal(getkey(), torque_shape))
    if inertia_shape[-2:] == (3, 3):
        a = np.asarray(jax.random.normal(getkey(), inertia_shape))
        inertia = a @ np.swapaxes(a, -1, -2) + np.eye(3)
        matrix = inertia
    else:
        inertia = np.asarray(1.0 + jax.random.uniform(getkey(), inertia_shape))
        matrix = inertia[..., None, :] * np.eye(3)
    momentum = np.einsum("...ij,...j->...i", matrix, omega)
    rhs = torque + np.cross(momentum, omega)
    expected = np.linalg.solve(matrix, rhs[..., None])[..., 0]
    got = jq.euler_equations(omega, inertia, torque)
    assert got.shape == expected.shape
    np.testing.assert_allclose(got, expected, rtol=1e-12, atol=1e-13)


def test_float32_in_float32_out():
    q0 = jnp.asarray(Q0, jnp.float32)
    omega0 = jnp.asarray(OMEGA0S[0], jnp.float32)
    inertia = jnp.asarray(MOMENTS, jnp.float32)
    assert jq.euler_equations(omega0, inertia).dtype == jnp.float32
    assert jq.euler_equations(omega0, jnp.diag(inertia)).dtype == jnp.float32
    assert jq.kinetic_energy(omega0, inertia).dtype == jnp.float32
    assert (
        jq.inertia_tensor(jnp.ones(3, jnp.float32), jnp.eye(3, dtype=jnp.float32)).dtype
        == jnp.float32
    )
    qs, omegas = jq.simulate_rigid_body(q0, omega0, inertia, 1e-2, 200, save_every=200)
    assert qs.dtype == omegas.dtype == jnp.float32
    q_ref, w_ref, _ = torque_free_reference(MOMENTS, OMEGA0S[0], Q0, [2.0])
    assert quat_distance(qs[-1], q_ref[0]) < 1e-5
    np.testing.assert_allclose(omegas[-1], w_ref[0], atol=1e-5)


@pytest.mark.parametrize("scale", [1e13, 1e-14, 1e30, 1e-30])
def test_float32_inertia_matrix_at_any_scale(scale):
    """ω̇ = I⁻¹((Iω) × ω) does not change when I is scaled, nor does a deformable body's motion when
    its masses and L are: the cofactor inverse overflowed to I⁻¹ = 0 from I ≈ 7e12 (the body stood
    still) and gave NaN below 1e-13 in float32 (helper-52)."""
    omega = np.array([1.0, 0.5, 0.2])
    inertia = np.array([[2.0, 0.1, 0.0], [0.1, 3.0, 0.0], [0.0, 0.0, 4.0]])
    expected = np.linalg.solve(inertia, np.cross(inertia @ omega, omega))  # float64, unscaled
    f32 = functools.partial(jnp.asarray, dtype=jnp.float32)
    np.testing.assert_allclose(
        jq.euler_equations(f32(omega), f32(scale * inertia)), expected, rtol=2e-6
    )
    qs, _ = jq.simulate_rigid_body(
        f32(Q0), f32(omega), f32(scale * inertia), 0.05, 40, save_every=40
    )
    reference, _ = jq.simulate_rigid_body(Q0, omega, inertia, 0.05, 40, save_every=40)
    assert quat_distance(qs[-1], reference[-1]) < 1e-5
    points = np.array([[1.0, 0, 0], [0, 1, 0], [0, 0, 1], [-1, -1, 0.3]])
    masses, momentum = np.array([1.0, 2, 3, 4]), np.array([1.0, 0.5, -0.3])
    body = functools.partial(
        jq.simulate_deformable_body,
        positions=lambda t: f32(points),
        dt=0.05,
        num_steps=40,
        save="final",
    )
    q_scaled = body(f32(scale * masses), q0=f32(Q0), angular_momentum=f32(scale * momentum))[0]
    q_unit = body(masses, q0=Q0, angular_momentum=momentum)[0]
    assert quat_distance(q_scaled, q_unit) < 1e-5


def test_inertia_matrix_gradient_matches_finite_differences():
    # The inverse is taken of I / max|I| with the scale held constant under differentiation.
    omega = jnp.array([1.0, 0.5, 0.2])
    inertia = jnp.array([[2.0, 0.1, -0.2], [0.1, 3.0, 0.05], [-0.2, 0.05, 4.0]])
    for scale in (1.0, 1e-20, 1e20):
        check_grads(
            lambda i: jq.euler_equations(omega, (i + i.T) / 2),
            (scale * inertia,),
            order=1,
            modes=("fwd", "rev"),
            eps=1e-6 * scale,
        )


# --------------------------------------------------------------------------------------------------
# Acceptance 6: errors


def test_invalid_inputs_raise():
    with pytest.raises(ValueError, match="inertia"):
        jq.euler_equations(jnp.ones(3), jnp.array([1.0, -2.0, 3.0]))
    with pytest.raises(ValueError, match="inertia"):
        jq.euler_equations(jnp.ones(3), jnp.array([1.0, 0.0, 3.0]))
    with pytest.raises(ValueError, match="symmetric"):
        jq.simulate_rigid_body(
            Q0, jnp.ones(3), jnp.array([[1.0, 0.5, 0.0], [0.0, 2.0, 0.0], [0.0, 0.0, 3.0]]), 0.1, 2
        )
    with pytest.raises(ValueError, match="positive definite"):
        jq.simulate_rigid_body(Q0, jnp.ones(3), jnp.diag(jnp.array([1.0, 2.0, -3.0])), 0.1, 2)
    with pytest.raises(ValueError, match="inertia"):
        jq.kinetic_energy(jnp.ones(3), jnp.ones(4))
    with pytest.raises(ValueError, match="masses"):
        jq.center_of_mass(jnp.ones(4), jnp.ones((5, 3)))
    with pytest.raises(ValueError, match="masses"):
        jq.inertia_tensor(jnp.array([1.0, -1.0]), jnp.ones((2, 3)))
    with pytest.raises(ValueError, match=r"`positions\(t\)` must return an array"):
        jq.simulate_deformable_body(jnp.ones(3), lambda t: None, Q0, 0.1, 2)
    for bad in (np.nan, np.inf):  # once an all-NaN result without a word
        masses = jnp.array([1.0, bad, 2.0])
        points = jnp.array([[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]])
        with pytest.raises(ValueError, match="`masses` must be positive and finite"):
            jq.center_of_mass(masses, points)
        with pytest.raises(ValueError, match="`masses` must be positive and finite"):
            jq.inertia_tensor(masses, points)
        with pytest.raises(ValueError, match="`masses` must be positive and finite"):
            jq.simulate_deformable_body(masses, lambda t, p=points: p * (1.0 + t), Q0, 0.1, 2)
    # Subnormal masses: XLA flushes them to zero (a NaN centre of mass; NumPy's LinAlgError from
    # the deformable body's collinearity check).
    points = jnp.array([[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]])
    for masses in (jnp.full(3, 1e-320), jnp.array([1.0, 1e-40, 1.0], jnp.float32)):
        match = "`masses` must be at least float(64|32)'s smallest normal number.*got 1e-(320|40)"
        with pytest.raises(ValueError, match=match):
            jq.center_of_mass(masses, points.astype(masses.dtype))
        with pytest.raises(ValueError, match=match):
            jq.simulate_deformable_body(masses, lambda t, p=points: p * (1.0 + t), Q0, 0.1, 2)
    np.testing.assert_allclose(jq.center_of_mass(jnp.full(3, 3e-308), points), [1 / 3] * 3)
    with pytest.raises(ValueError, match="positions"):
        jq.inertia_tensor(jnp.ones(2), jnp.ones((2, 2)))
    with pytest.raises(ValueError, match="velocities"):
        jq.angular_momentum(jnp.ones(2), jnp.ones((2, 3)), jnp.ones((3, 3)))
    with pytest.raises(ValueError, match="masses"):
        jq.simulate_deformable_body(jnp.ones(4), lambda t: jnp.ones((5, 3)) * t, Q0, 0.1, 2)
    with pytest.raises(ValueError, match="omega0"):
        jq.simulate_rigid_body(Q0, jnp.ones(4), MOMENTS, 0.1, 2)
    with pytest.raises(ValueError, match="frame"):
        jq.simulate_rigid_body(Q0, jnp.ones(3), MOMENTS, 0.1, 2, frame="inertial")
    with pytest.raises(ValueError, match="method"):
        jq.simulate_rigid_body(Q0, jnp.ones(3), MOMENTS, 0.1, 2, method="magnus4")
    with pytest.raises(ValueError, match="torque"):
        jq.simulate_rigid_body(Q0, jnp.ones(3), MOMENTS, 0.1, 2, torque=jnp.ones(3))
    # Values are not checked under jit (documented): a traced inertia passes the shape check only.
    jax.jit(jq.euler_equations)(jnp.ones(3), jnp.array([1.0, -2.0, 3.0]))


# --------------------------------------------------------------------------------------------------
# Acceptance 5: gradients and vmap

_UP = np.array([0.0, 0.0, 1.0])


_ROTATION = np.asarray(jq.to_matrix(jnp.array([0.9, 0.1, -0.3, 0.2])))
_SYMMETRIC_DIRECTION = np.array([[0.3, 0.1, -0.2], [0.1, -0.4, 0.05], [-0.2, 0.05, 0.2]])
_WEIGHTS = np.array([0.3, -0.5, 0.7, 0.2])


@jax.jit
def _final_orientation_loss(packed):
    """⟨c, q(T)⟩ as a function of (principal moments, s, ω₀, torque parameters), packed in one vector.

    The inertia is the full matrix R diag(moments) Rᵀ + s D (D symmetric), so the derivative w.r.t. s is
    one along a symmetric direction of the inertia tensor; the torque depends on time, attitude and rate.
    """
    moments, s, omega0, params = packed[:3], packed[3], packed[4:7], packed[7:]
    rotation = jnp.asarray(_ROTATION)
    inertia = rotation @ jnp.diag(moments) @ rotation.T + s * jnp.asarray(_SYMMETRIC_DIRECTION)

    def torque(t, q, omega):
        up = jq.rotate(jnp.asarray(_UP), jq.conjugate(q))
        return params[:3] * jnp.cos(t) + params[3] * jnp.cross(up, omega)

    q, _ = jq.simulate_rigid_body(Q0, omega0, inertia, 0.02, 100, torque=torque, save="final")
    return jnp.sum(jnp.asarray(_WEIGHTS) * q)


def test_gradients_agree_with_finite_differences():
    packed = np.array([1.0, 2.0, 3.0, 0.0, 0.3, 1.0, 0.8, 0.2, -0.1, 0.3, 0.5])
    gradient = np.asarray(jax.grad(_final_orientation_loss)(jnp.asarray(packed)))
    differences = central_jacobian(
        lambda p: _final_orientation_loss(jnp.asarray(p)), packed, eps=1e-6
    )
    assert np.min(np.abs(differences)) > 1e-4  # every parameter matters
    np.testing.assert_allclose(gradient, differences, rtol=1e-6)


def test_vmap_over_ten_thousand_bodies(getkey):
    n = 10_000
    moments = jnp.sort(jax.random.uniform(getkey(), (n, 3), minval=0.5, maxval=3.0), axis=-1)
    omega0 = jnp.array([0.3, 1.0, 0.8])

    def final(inertia):
        return jq.simulate_rigid_body(Q0, omega0, inertia, 0.01, 100, save="final")

    qs, omegas = jax.jit(jax.vmap(final))(moments)
    assert qs.shape == (n, 4) and omegas.shape == (n, 3)
    batched_q, batched_w = jq.simulate_rigid_body(Q0, omega0, moments, 0.01, 100, save="final")
    assert quat_distance(qs, batched_q) < 1e-13
    np.testing.assert_allclose(omegas, batched_w, atol=1e-13)
    # Each body conserves its own energy and world momentum.
    energy0 = jq.kinetic_energy(omega0, moments)
    np.testing.assert_allclose(jq.kinetic_energy(omegas, moments), energy0, rtol=1e-9)
    momentum0 = jq.rotate(moments * omega0[None], Q0)
    np.testing.assert_allclose(jq.rotate(moments * omegas, qs), momentum0, atol=1e-9)
    for k in (0, 4321):
        q_ref, w_ref, _ = torque_free_reference(
            np.asarray(moments[k]), np.asarray(omega0), Q0, [1.0]
        )
        assert quat_distance(qs[k], q_ref[0]) < 1e-8
        np.testing.assert_allclose(omegas[k], w_ref[0], atol=1e-8)


# --------------------------------------------------------------------------------------------------
# Acceptance 4: shape-changing bodies

CAT_MASSES = np.array([3.0, 2.0, 1.0, 1.0, 0.2, 2.0, 1.0, 1.0, 1.3])  # DeformableBodies.jl's cat
CAT_REST = np.array(
    [
        [0.0, 0.0, 0.0],
        [0.0, -1.0, 0.0],
        [0.5, -1.0, 1.0],
        [-0.5, -1.0, 1.0],
        [0.0, -1.5, -0.5],
        [0.0, 1.0, 0.0],
        [0.5, 1.0, 1.0],
        [-0.5, 1.0, 1.0],
        [0.0, 1.2, -0.2],
    ]
)


def _shape_cycle(period=1.0):
    """A smooth 3-D cycle of shapes with period `period` (limbs swinging out of phase)."""
    rest = jnp.asarray(CAT_REST)
    phases = jnp.linspace(0.0, 2.0, rest.shape[0]) * jnp.pi
    amplitude = 0.3 * jnp.asarray([[1.0, 0.5, 0.0]] * rest.shape[0])

    def positions(t):
        s = 2 * jnp.pi * t / period
        swing = jnp.stack(
            [jnp.sin(s + phases), jnp.cos(s + 1.3 * phases), jnp.sin(2 * s + phases)], axis=-1
        )
        return rest + amplitude * swing + jnp.array([[0.0, 0.0, 0.2]]) * jnp.sin(s)

    return positions


def test_constant_shape_reduces_to_rigid_body():
    masses = jnp.asarray(CAT_MASSES)
    rest = jnp.asarray(CAT_REST)
    momentum = jnp.array([0.5, -1.0, 2.0])
    qs, world = jq.simulate_deformable_body(
        masses, lambda t: rest, Q0, 1e-2, 300, angular_momentum=momentum
    )
    inertia = jq.inertia_tensor(masses, rest)
    omega0 = jnp.linalg.solve(inertia, jq.rotate(momentum, jq.conjugate(Q0)))
    q_rigid, _ = jq.simulate_rigid_body(Q0, omega0, inertia, 1e-2, 300)
    assert quat_distance(qs, q_rigid) < 1e-10
    centred = rest - jq.center_of_mass(masses, rest)[None]
    np.testing.assert_allclose(world, jq.rotate(centred[None], q_rigid[:, None]), atol=1e-10)


def test_rigidly_rotating_shape_stays_still_in_the_inertial_frame():
    masses = jnp.asarray(CAT_MASSES)
    rest = jnp.asarray(CAT_REST)
    centre = jq.center_of_mass(masses, rest)
    axis = jnp.array([0.3, -0.5, 0.8])

    def positions(t):
        # The shape turns rigidly about its centre of mass while the centre drifts (drift is removed).
        turn = jq.from_axis_angle(axis, 1.7 * t + 0.4 * t**2)
        return jq.rotate(rest, turn, centre) + jnp.stack([t, -2 * t, 0.5])[None]

    qs, world = jq.simulate_deformable_body(masses, positions, Q0, 1e-2, 300, save_every=10)
    expected = jq.rotate(rest - centre[None], Q0)
    np.testing.assert_allclose(world, jnp.broadcast_to(expected, world.shape), atol=1e-10)


def _central_derivative(values, h):
    """Sixth-order central difference along axis 0 (interior points)."""
    c = (1 / 60, -3 / 20, 3 / 4)
    n = values.shape[0]
    return (
        c[0] * (values[6:] - values[: n - 6])
        + c[1] * (values[5 : n - 1] - values[1 : n - 5])
        + c[2] * (values[4 : n - 2] - values[2 : n - 4])
    ) / h


def test_world_angular_momentum_is_conserved():
    masses = np.asarray(CAT_MASSES)
    momentum = np.array([0.3, -0.2, 0.5])
    dt, num_steps = 1e-3, 2_000
    _, world = jq.simulate_deformable_body(
        masses, _shape_cycle(), Q0, dt, num_steps, angular_momentum=jnp.asarray(momentum)
    )
    world = np.asarray(world)
    velocities = _central_derivative(world, dt)
    # Independent of the model's internals: L = Σ m x × ẋ from the inertial-frame positions.
    measured = np.sum(masses[:, None] * np.cross(world[3:-3], velocities), axis=-2)
    np.testing.assert_allclose(np.sum(masses[:, None] * world, axis=-2), 0.0, atol=1e-12)
    assert np.max(np.linalg.norm(measured - momentum, axis=-1)) < 1e-10 * np.linalg.norm(momentum)


# A planar body: two hinge masses at (±1, 0, 0) and an arm on each hinge (lengths 1.5 and 1), the arm
# angles going round a loop in shape space.
PLANAR_MASSES = np.array([1.0, 1.0, 0.7, 0.5])
HINGES = np.array([[1.0, 0.0], [-1.0, 0.0]])
ARM_LENGTHS = np.array([1.5, 1.0])


def _arm_angles(t, xp=np):
    """Arm angles a, b and their rates (`xp`: numpy for the reference, jax.numpy for the model)."""
    s = 2 * np.pi * t
    return (
        1.0 + 1.5 * xp.sin(s),
        2.0 + 1.5 * xp.cos(s),
        3.0 * np.pi * xp.cos(s),
        -3.0 * np.pi * xp.sin(s),
    )


def _planar_positions(t):
    a, b, _, _ = _arm_angles(t, jnp)
    arms = [
        hinge + length * jnp.stack([jnp.cos(g), jnp.sin(g)])
        for hinge, length, g in zip(HINGES, ARM_LENGTHS, (a, b), strict=True)
    ]
    xy = jnp.concatenate([jnp.asarray(HINGES), jnp.stack(arms)], axis=0)
    return jnp.concatenate([xy, jnp.zeros((4, 1))], axis=1)


def test_planar_zero_momentum_cycle_matches_quadrature():
    # In-plane shape changes with L = 0 rotate the body about z only, at ω = −L_int,z/I_zz, so the net
    # rotation after one cycle is −∮ L_int,z/I_zz dt, computed here from the analytic shape and its
    # analytic velocities by Gauss–Legendre quadrature.
    def rate(t):
        a, b, da, db = _arm_angles(t)
        zero = np.zeros_like(t)
        points = [np.stack([h[0] + zero, h[1] + zero]) for h in HINGES]
        velocities = [np.stack([zero, zero]) for _ in HINGES]
        for hinge, length, g, dg in zip(HINGES, ARM_LENGTHS, (a, b), (da, db), strict=True):
            points.append(np.stack([hinge[0] + length * np.cos(g), hinge[1] + length * np.sin(g)]))
            velocities.append(length * dg * np.stack([-np.sin(g), np.cos(g)]))
        points, velocities = np.stack(points), np.stack(velocities)
        centre = np.tensordot(PLANAR_MASSES, points, axes=1) / PLANAR_MASSES.sum()
        relative = points - centre
        internal = np.tensordot(
            PLANAR_MASSES,
            relative[:, 0] * velocities[:, 1] - relative[:, 1] * velocities[:, 0],
            axes=1,
        )
        izz = np.tensordot(PLANAR_MASSES, relative[:, 0] ** 2 + relative[:, 1] ** 2, axes=1)
        return -internal / izz

    nodes, weights = np.polynomial.legendre.leggauss(40)
    cuts = np.linspace(0.0, 1.0, 21)
    mid, half = 0.5 * (cuts[1:] + cuts[:-1]), 0.5 * (cuts[1:] - cuts[:-1])
    angle = np.sum(half[:, None] * weights * rate(mid[:, None] + half[:, None] * nodes))
    assert abs(angle) > 0.3
    q_final, _ = jq.simulate_deformable_body(
        PLANAR_MASSES, _planar_positions, Q0, 1.0 / 500, 500, save="final"
    )
    assert quat_distance(q_final, np_multiply(Q0, np_axis_quaternion(2, angle))) < 1e-10


@jax.jit
def _cycle_run(dt):
    """400 steps of the 3-D shape cycle (period 1) with step dt, saved every 50 steps."""
    masses = jnp.asarray(CAT_MASSES)
    qs, _ = jq.simulate_deformable_body(masses, _shape_cycle(), Q0, dt, 400, save_every=50)
    return qs


def test_three_dimensional_zero_momentum_cycle_converges():
    # The state after one period with N = 50, 100, 200, 400 steps: one compiled run of 400 steps per
    # step size, read at step N.
    finals = [np.asarray(_cycle_run(1.0 / n)[n // 50]) for n in (50, 100, 200, 400)]
    net = np_multiply(np_conjugate(Q0), finals[-1])
    net_angle = 2 * np.arctan2(np.linalg.norm(net[1:]), abs(net[0]))
    assert net_angle > 0.05
    errors = [quat_distance(q, finals[-1]) for q in finals[:-1]]
    # Fourth order: each halving of the step divides the error by ~16.
    assert errors[1] < errors[0] / 10 and errors[2] < errors[1] / 10
    assert errors[2] < 1e-6


# --------------------------------------------------------------------------------------------------
# The same system as a diffrax vector field


@pytest.mark.parametrize(
    "frame, solver",
    [("body", "CF4"), ("body", "RKMK45"), ("world", "CF4")],
)
def test_rigid_body_vector_field_with_lie_group_solvers(frame, solver):
    omega0 = OMEGA0S[0]
    q_ref, w_ref, _ = torque_free_reference(MOMENTS, omega0, Q0, [3.0])
    field = jq.rigid_body_vector_field(jnp.asarray(MOMENTS), frame=frame)
    w0 = omega0 if frame == "body" else np.asarray(jq.rotate(omega0, Q0))
    y0 = (jnp.asarray(Q0), jnp.asarray(w0))
    # Its right-hand side is the kinematics plus Euler's equations.
    q_dot, w_dot = field(0.0, y0, None)
    if frame == "body":
        np.testing.assert_allclose(q_dot, 0.5 * np_multiply(Q0, np.r_[0.0, omega0]), atol=1e-15)
        np.testing.assert_allclose(w_dot, np_euler_rhs(MOMENTS, omega0), atol=1e-15)
    else:
        np.testing.assert_allclose(q_dot, 0.5 * np_multiply(np.r_[0.0, w0], Q0), atol=1e-15)
        np.testing.assert_allclose(w_dot, np_rotate(np_euler_rhs(MOMENTS, omega0), Q0), atol=1e-15)
    if solver == "CF4":
        solver, controller = jq.CF4(), diffrax.ConstantStepSize()
    else:
        solver, controller = jq.RKMK45(), diffrax.PIDController(rtol=1e-11, atol=1e-11)
    solution = diffrax.diffeqsolve(
        diffrax.ODETerm(field),
        solver,
        0.0,
        3.0,
        1e-2,
        y0,
        stepsize_controller=controller,
        max_steps=10_000,
    )
    q_end, w_end = solution.ys[0][-1], solution.ys[1][-1]
    if frame == "world":
        w_end = jq.rotate(w_end, jq.conjugate(q_end))
    assert quat_distance(q_end, q_ref[0]) < 1e-8
    np.testing.assert_allclose(w_end, w_ref[0], atol=1e-8)


# --------------------------------------------------------------------------------------------------
# Transformations of the point-mass and Euler-equation functions: jit == eager, vmap == loop,
# forward == reverse == finite differences.


def _spd(key):
    a = jax.random.normal(key, (3, 3))
    return a @ a.T + 2.0 * jnp.eye(3)


def _symmetrized(function, index):
    """`function` with its argument `index` symmetrised, so that finite differences in arbitrary
    directions stay symmetric (a concrete non-symmetric inertia is rejected)."""

    def wrapped(*args):
        args = list(args)
        args[index] = 0.5 * (args[index] + jnp.swapaxes(args[index], -1, -2))
        return function(*args)

    return wrapped


@pytest.mark.parametrize(
    "function, make_args",
    [
        (jq.center_of_mass, lambda k: (jnp.array([1.0, 2.0, 0.5]), jax.random.normal(k, (3, 3)))),
        (jq.inertia_tensor, lambda k: (jnp.array([1.0, 2.0, 0.5]), jax.random.normal(k, (3, 3)))),
        (
            jq.angular_momentum,
            lambda k: (jnp.array([1.0, 2.0, 0.5]), *jax.random.normal(k, (2, 3, 3))),
        ),
        (
            _symmetrized(jq.euler_equations, 1),
            lambda k: (jax.random.normal(k, (3,)), _spd(k), jnp.ones(3)),
        ),
        (jq.euler_equations, lambda k: (jax.random.normal(k, (3,)), jnp.array([1.0, 2.0, 3.0]))),
        (_symmetrized(jq.kinetic_energy, 1), lambda k: (jax.random.normal(k, (3,)), _spd(k))),
        (_symmetrized(lambda inertia: jq.principal_axes(inertia)[0], 0), lambda k: (_spd(k),)),
    ],
)
def test_transformations(function, make_args, getkey):
    keys = jax.random.split(getkey(), 3)
    batches = [make_args(k) for k in keys]
    eager = [function(*args) for args in batches]
    np.testing.assert_allclose(jax.jit(function)(*batches[0]), eager[0], rtol=1e-13, atol=1e-14)
    stacked = [jnp.stack(parts) for parts in zip(*batches, strict=True)]
    np.testing.assert_allclose(
        jax.vmap(function)(*stacked), jnp.stack(eager), rtol=1e-13, atol=1e-14
    )
    check_grads(jax.jit(function), batches[0], order=1, modes=("fwd", "rev"), eps=1e-6)


# --- shared principal moments and a batch of three bodies ---------------------------------------


@pytest.mark.parametrize("batch", [(3,), (2, 3), (3, 1)])
def test_shared_moments_with_a_batch_of_three_bodies(batch):
    """Shared moments (3,) broadcast against three bodies became (3, 3) inside the library and were
    read as an inertia matrix (singular: NaN from simulate_rigid_body, wrong ω̇ from euler_equations).
    Every entry point must equal the body-by-body result."""
    moments = jnp.array([1.0, 2.0, 3.0])
    key_q, key_w = jax.random.split(jax.random.key(3))
    q0 = jq.random(key_q, batch)
    omega = 0.7 * jax.random.normal(key_w, batch + (3,))
    flat_q, flat_w = q0.reshape(-1, 4), omega.reshape(-1, 3)

    def per_body(f):
        return jnp.stack([f(q, w) for q, w in zip(flat_q, flat_w, strict=True)])

    def close(got, want):
        np.testing.assert_allclose(got.reshape(want.shape), want, rtol=1e-12, atol=1e-13)

    close(jq.euler_equations(omega, moments), per_body(lambda q, w: jq.euler_equations(w, moments)))
    close(jq.kinetic_energy(omega, moments), per_body(lambda q, w: jq.kinetic_energy(w, moments)))
    run = functools.partial(jq.simulate_rigid_body, dt=0.01, num_steps=20, save="final")
    qs, ws = run(q0, omega, moments)
    close(qs, per_body(lambda q, w: run(q, w, moments)[0]))
    close(ws, per_body(lambda q, w: run(q, w, moments)[1]))
    field = jq.rigid_body_vector_field(moments)
    q_dot, w_dot = field(0.0, (q0, omega), None)
    close(q_dot, per_body(lambda q, w: field(0.0, (q, w), None)[0]))
    close(w_dot, per_body(lambda q, w: field(0.0, (q, w), None)[1]))
    if len(batch) == 1:
        result = jq.simulate_ensemble(q0, omega, 0.01, 20, inertia=moments, frame="body")
        close(result.final, per_body(lambda q, w: run(q, w, moments)[0]))
    # A (3, 3) the caller passes is still a matrix: diag(1, 2, 3) gives the moments' result.
    close(run(q0, omega, jnp.diag(moments))[0], qs.reshape(-1, 4))


@pytest.mark.parametrize("method", ["cf4", "midpoint", "euler"])
def test_float32_long_run_is_compensated_and_renormalised(method):
    """float32 rigid bodies use `integrate`'s long-run mode: Kahan-compensated increments of q and
    q/|q| every 1,000 steps. A sphere spinning at 1.4 rad/s for 5·10⁴ steps of 1e-3 s: 1.7e-7 rad
    from the closed form exp(ωT) (SciPy) and unit to round-off; plainly stepped (the option off, as
    before a review) 8.6e-4 rad and |q| − 1 = −2.5e-4 (cf4) or 1.2e-5 rad (midpoint, euler). The
    rigid-body ensemble takes the same steps (equal to round-off), so does a shape-changing body."""
    q0 = jnp.asarray(jq.from_rotvec(jnp.array([0.2, -0.3, 0.5])), jnp.float32)
    omega = jnp.array([1.1, 0.3, 0.8], jnp.float32)
    dt, steps = 1e-3, 50_000
    spin = float(np.float32(dt)) * steps * np.asarray(omega, np.float64)
    exact = _scipy_rotation(q0) * Rotation.from_rotvec(spin)  # body frame: q0 ⊗ exp(ωT)

    def error(q):
        return (_scipy_rotation(q) * exact.inv()).magnitude()

    sphere = jnp.ones(3, jnp.float32)
    kwargs = dict(method=method, save="final")
    q, w = jq.simulate_rigid_body(q0, omega, sphere, dt, steps, **kwargs)
    assert q.dtype == jnp.float32
    assert error(q) < 5e-7
    assert abs(float(jnp.linalg.norm(q.astype(jnp.float64))) - 1.0) < 3e-7
    plain, _ = jq.simulate_rigid_body(
        q0, omega, sphere, dt, steps, compensated=False, renormalize_every=None, **kwargs
    )
    assert error(plain) > 5e-6  # the check above has teeth
    ensemble = jq.simulate_ensemble(
        q0[None], omega[None], dt, steps, inertia=sphere, frame="body", method=method
    )
    np.testing.assert_allclose(ensemble.final[0], q, rtol=0, atol=2e-7)


def _scipy_rotation(q):
    q = np.asarray(q, np.float64)
    return Rotation.from_quat(np.r_[q[1:], q[0]])


def test_long_run_options_are_validated_and_gradients_flow():
    """`compensated` / `renormalize_every` as `integrate` takes them; derivatives through the
    renormalisations match central differences (float64), and through the compensated float32
    steps the float64 ones."""
    q0, omega, inertia = jq.identity(), jnp.array([0.3, 0.2, 0.9]), jnp.array([1.0, 2.0, 3.0])
    with pytest.raises(ValueError, match="`compensated`=True needs a Lie method"):
        jq.simulate_rigid_body(q0, omega, inertia, 0.01, 3, method="rk4", compensated=True)
    with pytest.raises(ValueError, match="`renormalize_every` must be >= 1"):
        jq.simulate_rigid_body(q0, omega, inertia, 0.01, 3, renormalize_every=0)

    @functools.partial(jax.jit, static_argnums=1)
    def loss(w, dtype):  # across four renormalisations (every 7 of the 30 steps)
        args = (q0.astype(dtype), w.astype(dtype), inertia.astype(dtype))
        q, _ = jq.simulate_rigid_body(*args, 0.05, 30, save="final", renormalize_every=7)
        return jnp.sum(q[1:] ** 2)

    g32 = jax.grad(loss)(omega.astype(jnp.float32), jnp.float32)
    g64 = jax.grad(loss)(omega, jnp.float64)
    h = 1e-6
    central = [
        (loss(omega + h * e, jnp.float64) - loss(omega - h * e, jnp.float64)) / (2 * h)
        for e in jnp.eye(3)
    ]
    np.testing.assert_allclose(g64, central, rtol=1e-7, atol=1e-9)
    np.testing.assert_allclose(g32, g64, rtol=0, atol=2e-5)


def test_float32_asymmetric_body_compensates_omega_too():
    """In float32 ω's Runge–Kutta update is Kahan-compensated as well: an asymmetric body
    (I = (1, 2, 3)) after 5·10⁴ steps of 1e-3 s ends 5.1e-6 rad (ω 3.3e-6) from the float64 run,
    1.1e-4 rad (ω 1.4e-4) when stepped plainly, as before a review."""
    q0 = jq.from_rotvec(jnp.array([0.2, -0.3, 0.5]))
    omega, inertia = jnp.array([1.1, 0.0, 0.8]), jnp.array([1.0, 2.0, 3.0])
    steps = 50_000
    reference, omega_reference = jq.simulate_rigid_body(
        q0, omega, inertia, 1e-3, steps, save="final"
    )

    def run(**kwargs):
        args = (x.astype(jnp.float32) for x in (q0, omega, inertia))
        q, w = jq.simulate_rigid_body(*args, 1e-3, steps, save="final", **kwargs)
        angle = float(jq.angle_between(q.astype(jnp.float64), reference))
        return angle, float(jnp.max(jnp.abs(w - omega_reference)))

    angle, omega_error = run()
    assert angle < 2e-5 and omega_error < 2e-5
    plain_angle, plain_omega_error = run(compensated=False, renormalize_every=None)
    assert plain_angle > 5e-5 and plain_omega_error > 5e-5


def test_compensated_step_with_a_tuple_state_matches_the_plain_step():
    """The Kahan-compensated step advances any pytree x like `lie_step` does: a tuple x = (a, b)
    came back scrambled (b's new value swapped with a's compensation; a review)."""
    from jaxquat._integrate import compensated_lie_step, lie_step

    def field(t, q, x):
        a, b = x
        return a, (b, -a)

    q = jq.from_rotvec(jnp.array([0.1, 0.2, 0.3], jnp.float32))
    x = (jnp.array([0.2, 0.2, 0.3], jnp.float32), jnp.array([1.0, 0.0, 0.0], jnp.float32))
    zeros = (jnp.zeros(4, jnp.float32), tuple(jnp.zeros(3, jnp.float32) for _ in x))
    for method in ("euler", "midpoint", "cf4"):
        q1, x1 = lie_step(method, field, 0.0, q, x, 0.01, frame="body")
        q2, x2, (c_q, c_x) = compensated_lie_step(
            method, field, 0.0, q, x, zeros, 0.01, frame="body"
        )
        np.testing.assert_allclose(q2, q1, rtol=0, atol=1e-7)
        assert isinstance(x2, tuple) and isinstance(c_x, tuple)
        for got, want, compensation in zip(x2, x1, c_x, strict=True):
            np.testing.assert_allclose(got, want, rtol=0, atol=1e-7)
            assert np.all(np.abs(np.asarray(compensation)) < 1e-7)


class _Damping(eqx.Module):
    rate: jax.Array

    def __call__(self, t, q, omega):
        return -self.rate * omega


class _CyclingShape(eqx.Module):
    amplitude: jax.Array

    def __call__(self, t):
        stretch = 1.0 + self.amplitude * jnp.sin(t)
        return jnp.array([[1.0, 0.0, 0.0], [0.0, stretch, 0.0], [0.0, 0.0, 1.0]])


def test_repeated_simulations_compile_once():
    """Without a torque, or with `equinox.Module` callables, new values of the arrays (q0, ω0,
    inertia, Δt, t0, masses, angular momentum, the Modules' arrays) reuse the compiled run; a call
    outside `jit` once traced and compiled the whole run again every time (0.4-2 s a call). The
    reused runs are checked against closed forms: a symmetric top (I₁ = I₂) precesses about its
    axis at ω₃ (I₃ − I₁)/I₁, and a damping torque's work."""
    q0 = jnp.array([1.0, 0.0, 0.0, 0.0])

    def top(omega3, inertia3, dt, t0):
        inertia = jnp.array([1.0, 1.0, inertia3])
        omega0 = jnp.array([0.3, 0.0, omega3])
        return jq.simulate_rigid_body(q0, omega0, inertia, dt, 50, t0=t0, save="final")

    def damped(rate, dt):
        omega0 = jnp.array([0.2, -0.4, 1.1])
        return jq.simulate_rigid_body(
            q0, omega0, jnp.array([1.0, 2.0, 3.0]), dt, 40, torque=_Damping(rate)
        )

    def deformable(masses, momentum, amplitude):
        return jq.simulate_deformable_body(
            masses, _CyclingShape(amplitude), q0, 0.05, 30, angular_momentum=momentum
        )

    top(jnp.asarray(1.0), jnp.asarray(2.0), jnp.asarray(0.01), jnp.asarray(0.0))
    damped(jnp.asarray(0.5), jnp.asarray(0.02))
    deformable(jnp.array([1.0, 2.0, 1.5]), jnp.array([0.0, 0.0, 0.1]), jnp.asarray(0.3))
    with count_lowerings() as lowered:
        q, omega = top(jnp.asarray(2.0), jnp.asarray(1.5), jnp.asarray(0.02), jnp.asarray(3.0))
        _, omegas = damped(jnp.asarray(0.25), jnp.asarray(0.05))
        qs, positions = deformable(
            jnp.array([2.0, 1.0, 0.5]), jnp.array([0.3, 0.0, 0.2]), jnp.asarray(0.2)
        )
        jax.block_until_ready((q, omega, omegas, qs, positions))
    assert lowered == [], f"{len(lowered)} programs compiled again"
    # Body-frame ω of the top: the transverse part turns at Ω = ω₃ (I₃ − I₁)/I₁ = 1 rad/s, for 1 s.
    angle = 2.0 * (1.5 - 1.0) / 1.0 * 1.0
    np.testing.assert_allclose(omega, [0.3 * np.cos(angle), 0.3 * np.sin(angle), 2.0], atol=1e-8)
    # The torque −c ω does work −c |ω|²: the kinetic energy E(t) = E₀ − c ∫|ω|² dt.
    energy = jq.kinetic_energy(omegas, jnp.array([1.0, 2.0, 3.0]))
    power = 0.25 * jnp.sum(omegas**2, axis=-1)
    work = 0.05 * (jnp.cumsum(power) - 0.5 * (power[0] + power))  # trapezoidal ∫ from 0 to t
    np.testing.assert_allclose(energy, energy[0] - work, rtol=1e-5)  # trapezoid: 1.2e-6
    assert qs.shape == (31, 4) and positions.shape == (31, 3, 3)


_GAIN = {"value": 0.5}


def _global_damping(t, q, omega):
    return -_GAIN["value"] * omega


class _Plain:  # a plain class: its instances do not hash by value, nor its bound methods
    def __init__(self, rate):
        self.rate = rate

    def __eq__(self, other):
        return isinstance(other, _Plain) and self.rate is other.rate

    __hash__ = None

    def torque(self, t, q, omega):
        return -self.rate * omega


def test_callables_with_state_are_traced_at_each_call():
    """A plain function or bound method may read state that changes between calls (a global gain,
    an attribute set to a tracer of an outer `jax.grad`): it is traced at each call, never replayed
    from a compiled run. Checked against the closed form of a sphere under the torque −c ω,
    ω(t) = ω₀ exp(−c t / I)."""
    q0 = jnp.array([1.0, 0.0, 0.0, 0.0])
    omega0 = jnp.array([0.2, -0.4, 1.1])
    sphere = jnp.array([2.0, 2.0, 2.0])

    def final_omega(torque):
        return jq.simulate_rigid_body(q0, omega0, sphere, 0.01, 100, torque=torque, save="final")[1]

    for gain in (0.5, 2.0):
        _GAIN["value"] = gain
        expected = omega0 * np.exp(-gain * 1.0 / 2.0)
        np.testing.assert_allclose(final_omega(_global_damping), expected, rtol=1e-9)
    plain = _Plain(0.5)
    np.testing.assert_allclose(final_omega(plain.torque), omega0 * np.exp(-0.25), rtol=1e-9)

    def loss(rate):
        plain.rate = rate
        return final_omega(plain.torque)[2]

    for rate in (0.5, 1.5):  # d/dc of ω₀ exp(−c/2) is −ω₀/2 exp(−c/2)
        np.testing.assert_allclose(jax.grad(loss)(rate), -0.55 * np.exp(-rate / 2.0), rtol=1e-8)


def _molecule_shape(s):
    """A bent triatomic in ångström as a function of dimensionless time s."""
    angle = 1.8 + 0.3 * jnp.sin(s)
    r1 = 0.96 * (1 + 0.05 * jnp.sin(2 * s))
    r2 = 0.96 * (1 - 0.05 * jnp.cos(3 * s))
    return jnp.array(
        [
            [0.0, 0.0, 0.0],
            [r1, 0.0, 0.0],
            [r2 * jnp.cos(angle), r2 * jnp.sin(angle), 0.05 * jnp.sin(s)],
        ]
    )


@pytest.mark.parametrize("mass_dtype", [np.float32, np.float64])
@pytest.mark.parametrize("momentum", [0.0, 2.0])
def test_float32_deformable_body_in_si_units_of_a_molecule(momentum, mass_dtype):
    # Masses ~1e-26 kg at ~1e-10 m: I ≈ 1e-46 kg m² underflows float32 (and I⁻¹ overflows), Π ≈ ħ.
    # The orientation must not depend on the units: it was NaN (float64 masses), a false "single
    # point" ValueError (float32 masses), and, once finite, 1e-4 rad off with L = 2ħ (a subnormal
    # Kahan compensation of Π ≈ 1e-41).
    amu, angstrom, fs, hbar = 1.66e-27, 1e-10, 1e-15, 1.0546e-34
    masses = np.array([16.0, 1.0, 1.0])
    q0 = jnp.array([1.0, 0.0, 0.0, 0.0], jnp.float32)
    natural = momentum * hbar / (amu * angstrom**2 / fs)  # in amu Å² / fs
    reference, _ = jq.simulate_deformable_body(  # float64, in amu, Å and fs
        jnp.asarray(masses),
        lambda t: _molecule_shape(t / 10.0),
        q0.astype(jnp.float64),
        0.5,
        200,
        angular_momentum=jnp.array([0.0, 0.0, natural]),
    )
    qs, _ = jq.simulate_deformable_body(
        np.asarray(masses * amu, mass_dtype),  # float64 masses are cast to q0's float32
        lambda t: _molecule_shape(t / (10.0 * fs)) * angstrom,
        q0,
        0.5 * fs,
        200,
        angular_momentum=jnp.array([0.0, 0.0, momentum * hbar], jnp.float32),
    )
    assert qs.dtype == jnp.float32
    error = np.asarray(jq.angle_between(qs.astype(jnp.float64), reference))
    assert np.all(np.isfinite(error))
    assert error.max() < 1e-5


@pytest.mark.parametrize(
    "mass_scale, length_scale",
    [(1e-26, 1e-10), (2e30, 1.5e11), (1.0, 1e-20)],  # L_int = Σ m x × ẋ under/overflowed float32
)
def test_float32_deformable_body_internal_momentum_at_any_scale(mass_scale, length_scale):
    # With L = 0 the body turns only through its internal momentum Σ mᵢ (xᵢ − c) × ẋᵢ, ≈ 1e-46 for
    # molecules over seconds and ≈ 1e52 for stars at 1 au: computed at its own scale it was 0 (the
    # body did not turn, 0.17 rad off, silently) or inf (NaN), while I and Π were carried scaled.
    masses = np.array([16.0, 1.0, 1.3])
    q0 = jnp.array([1.0, 0.0, 0.0, 0.0], jnp.float32)
    reference, _ = jq.simulate_deformable_body(
        jnp.asarray(masses), lambda t: _molecule_shape(t / 3.0), q0.astype(jnp.float64), 0.05, 100
    )
    qs, _ = jq.simulate_deformable_body(
        jnp.asarray(masses * mass_scale, jnp.float32),
        lambda t: _molecule_shape(t / 3.0) * jnp.float32(length_scale),
        q0,
        0.05,
        100,
    )
    error = np.asarray(jq.angle_between(qs.astype(jnp.float64), reference))
    assert np.all(np.isfinite(error))
    assert error.max() < 1e-5
