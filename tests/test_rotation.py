"""Rotations: the seeds' worked examples, SciPy agreement on 10⁴ random rotations (every conversion,
all 12 Euler sequences in both cases), nearest-rotation `from_matrix`, two-vector alignment, closed-form
derivatives at the identity, and bad-input errors."""

from __future__ import annotations

import math
import warnings

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from helpers import (
    SEED_CENTRE,
    SEED_MASSES,
    SEED_POSITIONS,
    SEED_ROTATED,
    SEED_ROTATED_CENTRE,
    assert_quat_close,
    near_pi,
    quat_distance,
    random_unit,
)
from scipy.spatial.transform import Rotation

import jaxquat as jq

N = 10_000
SEQUENCES = ["xyz", "xzy", "yxz", "yzx", "zxy", "zyx", "xyx", "xzx", "yxy", "yzy", "zxz", "zyz"]
ALL_SEQUENCES = SEQUENCES + [s.upper() for s in SEQUENCES]


@pytest.fixture(scope="module")
def rotations():
    """10⁴ Haar-random unit quaternions plus 10³ within 1e-6 … 1e-3 of a half-turn."""
    key = jax.random.key(2024)
    k1, k2, k3 = jax.random.split(key, 3)
    q = random_unit(k1, (N,))
    eps = 10.0 ** jax.random.uniform(k2, (1000,), minval=-6.0, maxval=-3.0)
    half_turns = jax.vmap(lambda k, e: near_pi(k, e))(jax.random.split(k3, 1000), eps)
    return np.asarray(jnp.concatenate([q, half_turns]))


def wrapped(a):
    """Angles mod 2π into (−π, π] (for comparing angles equal up to a full turn)."""
    return np.angle(np.exp(1j * np.asarray(a)))


# ---------------------------------------------------------------------------------------------------
# The seeds' worked examples (issue 2, acceptance 1), to 1e-12.

Q = np.array([1.0, 2.0, 3.0, 4.0])


def test_seed_rotate_with_and_without_centre():
    np.testing.assert_allclose(jq.rotate([3, 0, 0], Q), [-2, 2, 1], atol=1e-12)
    np.testing.assert_allclose(jq.rotate([3, 0, 0], Q, [0, 0, 0]), [-2, 2, 1], atol=1e-12)
    np.testing.assert_allclose(jq.rotate([1, 2, 3], jq.identity()), [1, 2, 3], atol=1e-12)


def test_seed_composition():
    q1, q2 = Q, np.array([4.0, 3.0, 2.0, 1.0])
    v = np.array([9.0, 0.0, 0.0])
    composed = jq.rotate(v, jq.multiply(q2, q1))
    np.testing.assert_allclose(composed, [-1, -4, 8], atol=1e-12)
    np.testing.assert_allclose(jq.rotate(jq.rotate(v, q1), q2), [-1, -4, 8], atol=1e-12)
    # Rotations do not commute: q1 after q2 is a different rotation.
    assert np.max(np.abs(jq.rotate(v, jq.multiply(q1, q2)) - composed)) > 1.0


def test_seed_axis_angle():
    q = jq.from_axis_angle([0, 0, 2], math.pi / 2)
    np.testing.assert_allclose(q, [0.7071067811865476, 0, 0, 0.7071067811865475], atol=1e-12)
    np.testing.assert_allclose(jq.rotate([1, 0, 0], q), [0, 1, 0], atol=1e-12)
    # The seed's rotate(axis=[0,0,1], angle=π/2, center=[0,1,0]) of (1,0,0): (1,−1,0) ↦ (1,1,0), + c.
    q = jq.from_axis_angle([0, 0, 1], math.pi / 2)
    np.testing.assert_allclose(jq.rotate([1, 0, 0], q, center=[0, 1, 0]), [1, 2, 0], atol=1e-12)


def test_seed_rotate_takes_axis_and_angle_keywords():
    """The seed's `rotate(v; axis, angle, center)`, with its printed result."""
    got = jq.rotate([1, 0, 0], axis=[0, 0, 1], angle=math.pi / 2)
    np.testing.assert_allclose(got, [2.220446049250313e-16, 1.0, 0.0], rtol=0, atol=1e-16)
    got = jq.rotate([1, 0, 0], axis=[0, 0, 1], angle=math.pi / 2, center=[0, 1, 0])
    np.testing.assert_allclose(got, [1, 2, 0], atol=1e-12)
    # Batched against SciPy: axes (not unit) and angles per vector, one centre, under jit.
    rng = np.random.default_rng(5)
    v, axis, angle = rng.normal(size=(50, 3)), rng.normal(size=(50, 3)), rng.uniform(-7, 7, 50)
    c = np.array([0.5, -1.0, 2.0])
    expected = Rotation.from_rotvec(angle[:, None] * axis / np.linalg.norm(axis, axis=1)[:, None])
    got = jax.jit(lambda v, n, a: jq.rotate(v, axis=n, angle=a, center=c))(v, axis, angle)
    np.testing.assert_allclose(got, expected.apply(v - c) + c, atol=1e-13)


@pytest.mark.parametrize(
    "kwargs, message",
    [
        (dict(axis=[0, 0, 1]), "got only `axis`"),
        (dict(angle=1.0), "got only `angle`"),
        ({}, "got neither"),
        (dict(q=[1, 0, 0, 0], axis=[0, 0, 1]), "not both; got `q` and `axis`"),
        (dict(q=[1, 0, 0, 0], angle=1.0), "not both; got `q` and `angle`"),
        (dict(q=[1, 0, 0, 0], axis=[0, 0, 1], angle=1.0), "got `q` and `axis` and `angle`"),
        (dict(axis=[0, 1], angle=1.0), r"`axis` must have shape \(\.\.\., 3\)"),
    ],
)
def test_rotate_needs_exactly_one_form_of_the_rotation(kwargs, message):
    with pytest.raises(ValueError, match=message):
        jq.rotate([1.0, 0.0, 0.0], **kwargs)


def test_seed_matrix_to_quaternion():
    c = math.cos(math.pi / 4)
    m = np.array([[c, -c, 0], [c, c, 0], [0, 0, 1]])
    np.testing.assert_allclose(m @ [math.sqrt(2), 0, 0], [1, 1, 0], atol=1e-12)
    q = jq.from_matrix(m)
    np.testing.assert_allclose(q, [0.9238795325112867, 0, 0, 0.3826834323650898], atol=1e-12)
    np.testing.assert_allclose(jq.rotate([math.sqrt(2), 0, 0], q), [1, 1, 0], atol=1e-12)


def test_seed_quaternion_to_matrix():
    m = np.asarray(jq.to_matrix(Q))
    exact = np.array([[-2 / 3, 2 / 15, 11 / 15], [2 / 3, -1 / 3, 2 / 3], [1 / 3, 14 / 15, 2 / 15]])
    np.testing.assert_allclose(m, exact, atol=1e-12)
    printed = np.array(
        [
            [-0.666667, 0.133333, 0.733333],
            [0.666667, -0.333333, 0.666667],
            [0.333333, 0.933333, 0.133333],
        ]
    )
    np.testing.assert_allclose(m, printed, atol=5e-7)  # the seed prints 6 digits
    np.testing.assert_allclose(m @ [3, 0, 0], [-2, 2, 1], atol=1e-12)
    np.testing.assert_allclose(jq.rotate([3, 0, 0], Q), m @ [3, 0, 0], atol=1e-12)


def test_seed_matrix_round_trips(rotations):
    q = rotations[:1000]
    m = jq.to_matrix(q)
    np.testing.assert_allclose(jq.to_matrix(jq.from_matrix(m)), m, atol=1e-12)
    assert_quat_close(jq.from_matrix(jq.to_matrix(q)), q, atol=1e-12)
    # The seed's counterexample: q = −1 comes back as +1, the same rotation.
    np.testing.assert_allclose(
        jq.from_matrix(jq.to_matrix([-1.0, 0, 0, 0])), [1, 0, 0, 0], atol=1e-12
    )


# The DeformableBodies.jl example of seed 001 (data in helpers.py): the centre of mass is computed
# inline here; the dynamics module's center_of_mass is tested against it in test_dynamics.py.


def test_seed_point_mass_rotation_about_centre_of_mass():
    masses, positions = jnp.asarray(SEED_MASSES), jnp.asarray(SEED_POSITIONS)
    centre = jnp.sum(masses[:, None] * positions, axis=0) / jnp.sum(masses)
    np.testing.assert_allclose(centre, SEED_CENTRE, rtol=0, atol=1e-15)
    rotated = jq.rotate(positions, Q, center=centre)
    np.testing.assert_allclose(rotated, SEED_ROTATED, rtol=0, atol=1e-12)
    # to the digits printed (17 significant): agreement to a few units in the last place.
    assert np.max(np.abs(np.asarray(rotated) - SEED_ROTATED)) < 1e-15
    rotated_centre = jnp.sum(masses[:, None] * rotated, axis=0) / jnp.sum(masses)
    np.testing.assert_allclose(rotated_centre, SEED_ROTATED_CENTRE, rtol=0, atol=1e-15)
    # Rotation about the centre of mass keeps it fixed and keeps every distance to it.
    np.testing.assert_allclose(
        np.linalg.norm(np.asarray(rotated) - SEED_CENTRE, axis=-1),
        np.linalg.norm(SEED_POSITIONS - SEED_CENTRE, axis=-1),
        atol=1e-15,
    )


# ---------------------------------------------------------------------------------------------------
# SciPy, 10⁴ random rotations (+10³ near half-turns), float64 (issue 2, acceptance 2).


def test_matrix_conversions_match_scipy(rotations):
    r = Rotation.from_quat(rotations, scalar_first=True)
    np.testing.assert_allclose(jq.to_matrix(rotations), r.as_matrix(), rtol=0, atol=1e-12)
    from_m = np.asarray(jq.from_matrix(r.as_matrix()))
    scipy_q = Rotation.from_matrix(r.as_matrix()).as_quat(scalar_first=True)
    assert quat_distance(from_m, scipy_q) < 1e-12
    assert np.all(from_m[:, 0] >= 0)
    np.testing.assert_allclose(np.linalg.norm(from_m, axis=-1), 1.0, atol=1e-14)


def test_rotvec_axis_angle_and_xyzw_match_scipy(rotations):
    r = Rotation.from_quat(rotations, scalar_first=True)
    rotvec = r.as_rotvec()
    np.testing.assert_allclose(jq.to_rotvec(rotations), rotvec, rtol=0, atol=1e-12)
    vectors = np.random.default_rng(0).normal(size=(N, 3)) * 2.0  # |r| up to ~8: past π too
    scipy_q = Rotation.from_rotvec(vectors).as_quat(scalar_first=True)
    assert quat_distance(jq.from_rotvec(vectors), scipy_q) < 1e-12
    axis, angle = jq.to_axis_angle(rotations)
    np.testing.assert_allclose(
        np.asarray(axis) * np.asarray(angle)[:, None], rotvec, rtol=0, atol=1e-12
    )
    assert np.all((np.asarray(angle) >= 0) & (np.asarray(angle) <= np.pi))
    angles = np.linalg.norm(vectors, axis=-1)
    assert quat_distance(jq.from_axis_angle(3.0 * vectors, angles), scipy_q) < 1e-12
    np.testing.assert_allclose(jq.to_xyzw(rotations), r.as_quat(), rtol=0, atol=1e-15)
    np.testing.assert_allclose(
        jq.from_xyzw(r.as_quat()), r.as_quat(scalar_first=True), rtol=0, atol=1e-15
    )
    np.testing.assert_array_equal(jq.from_xyzw(jq.to_xyzw(rotations)), rotations)


def test_from_axis_angle_with_a_zero_axis_is_the_identity():
    # A rotation needs an axis: about the zero vector any angle gives the identity (unit), as
    # documented, batched alongside proper axes, with a zero gradient w.r.t. the angle there.
    axes = jnp.array([[0.0, 0.0, 0.0], [0.0, 0.0, 2.0]])
    q = np.asarray(jq.from_axis_angle(axes, jnp.array([1.0, np.pi])))
    np.testing.assert_array_equal(q[0], [1.0, 0.0, 0.0, 0.0])
    np.testing.assert_allclose(q[1], [0.0, 0.0, 0.0, 1.0], atol=1e-15)
    g = jax.grad(lambda a: jq.from_axis_angle(jnp.zeros(3), a)[0])(1.0)
    assert g == 0.0


def test_rotate_matches_scipy_apply(rotations):
    rng = np.random.default_rng(1)
    v, c = rng.normal(size=(len(rotations), 3)), rng.normal(size=(len(rotations), 3))
    r = Rotation.from_quat(rotations, scalar_first=True)
    np.testing.assert_allclose(jq.rotate(v, rotations), r.apply(v), rtol=0, atol=1e-12)
    np.testing.assert_allclose(jq.rotate(v, rotations, c), r.apply(v - c) + c, rtol=0, atol=1e-12)
    # Non-unit quaternions rotate like their normalisation.
    np.testing.assert_allclose(jq.rotate(v, 3.7 * rotations), r.apply(v), rtol=0, atol=1e-12)


@pytest.mark.parametrize("seq", ALL_SEQUENCES)
def test_euler_matches_scipy(seq, rotations):
    rng = np.random.default_rng(abs(hash(seq)) % 2**32)
    angles = rng.uniform(-np.pi, np.pi, size=(N, 3))
    if seq[0].lower() == seq[2].lower():
        angles[:, 1] = np.abs(angles[:, 1])
    else:
        angles[:, 1] /= 2
    scipy_q = Rotation.from_euler(seq, angles).as_quat(scalar_first=True)
    assert quat_distance(jq.from_euler(seq, angles), scipy_q) < 1e-12
    ours = np.asarray(jq.to_euler(rotations, seq))
    theirs = Rotation.from_quat(rotations, scalar_first=True).as_euler(seq)
    assert np.max(np.abs(wrapped(ours - theirs))) < 1e-12
    # SciPy's ranges: first and third in [−π, π], middle in [0, π] (proper) or [−π/2, π/2].
    assert np.all(np.abs(ours) <= np.pi)
    if seq[0].lower() == seq[2].lower():
        assert np.all((ours[:, 1] >= 0) & (ours[:, 1] <= np.pi))
    else:
        assert np.all(np.abs(ours[:, 1]) <= np.pi / 2)
    # Round trip: the angles reproduce the rotation.
    assert quat_distance(jq.from_euler(seq, ours), rotations) < 1e-12


@pytest.mark.parametrize("seq", ["xyz", "ZYX", "zxz", "YXY"])
def test_euler_gimbal_lock_follows_scipy(seq):
    """At (and within 1e-7 of) gimbal lock the third angle is set to 0, as SciPy does."""
    rng = np.random.default_rng(3)
    proper = seq[0].lower() == seq[2].lower()
    middles = (
        [0.0, np.pi, 1e-8, np.pi - 1e-8] if proper else [np.pi / 2, -np.pi / 2, np.pi / 2 - 1e-8]
    )
    angles = rng.uniform(-np.pi, np.pi, size=(len(middles) * 50, 3))
    angles[:, 1] = np.repeat(middles, 50)
    q = Rotation.from_euler(seq, angles).as_quat(scalar_first=True)
    with warnings.catch_warnings():
        warnings.filterwarnings("ignore", "Gimbal lock detected", UserWarning)
        theirs = Rotation.from_quat(q, scalar_first=True).as_euler(seq)
    ours = np.asarray(jq.to_euler(q, seq))
    assert np.max(np.abs(wrapped(ours - theirs))) < 1e-12
    np.testing.assert_array_equal(ours[:, 2], 0.0)
    assert quat_distance(jq.from_euler(seq, ours), q) < 1e-7  # exact up to the 1e-7 lock window


# ---------------------------------------------------------------------------------------------------
# from_matrix: the nearest rotation (acceptance 6), and derivatives.


@pytest.mark.parametrize("dtype", [np.float32, np.float64])
def test_from_matrix_sign_of_an_exact_half_turn_does_not_depend_on_the_batch(dtype):
    """A symmetric matrix of trace −1 gives w = 0 exactly; the sign was left to the eigensolver, and
    the power steps (a batch of rotations) and `eigh` (a batch holding any other matrix) disagreed:
    adding a matrix to the batch negated the result. Ties are broken as SciPy's canonical form."""
    rng = np.random.default_rng(8)
    axes = np.concatenate([np.ones((1, 3)) / np.sqrt(3.0), rng.normal(size=(40, 3))])
    axes[[1, 2, 3]] = np.eye(3)[[2, 1, 0]]  # half-turns about z, y, x: x (and y) are zero there
    axes /= np.linalg.norm(axes, axis=-1, keepdims=True)
    m = (2.0 * axes[:, :, None] * axes[:, None, :] - np.eye(3)).astype(dtype)
    alone = np.asarray(jq.from_matrix(m))
    with_other = np.asarray(jq.from_matrix(np.concatenate([m, [np.diag([1.0, 2.0, 3.0])]])))[:-1]
    single = np.stack([np.asarray(jq.from_matrix(x)) for x in m[:4]])
    tolerance = 1e-6 if dtype == np.float32 else 1e-14
    np.testing.assert_allclose(with_other, alone, rtol=0, atol=tolerance)
    np.testing.assert_allclose(single, alone[:4], rtol=0, atol=tolerance)
    # The rotation is SciPy's; where w is exactly 0 the sign is that of SciPy's canonical form
    # (first non-zero of x, y, z positive; SciPy on these float32 matrices in float64 sees w ≠ 0).
    theirs = Rotation.from_matrix(m.astype(np.float64)).as_quat(canonical=True, scalar_first=True)
    assert quat_distance(alone, theirs) < 10 * tolerance
    tie = alone[:, 0] == 0
    assert tie[:4].all() and np.all(alone[:, 0] >= 0)
    first_nonzero = np.take_along_axis(
        alone[tie, 1:], np.argmax(alone[tie, 1:] != 0, 1)[:, None], 1
    )
    assert np.all(first_nonzero > 0)
    if dtype == np.float64:
        np.testing.assert_allclose(alone, theirs, rtol=0, atol=tolerance)


def test_from_matrix_is_the_nearest_rotation_and_differentiable():
    rng = np.random.default_rng(4)
    q = np.asarray(random_unit(jax.random.key(4), (200,)))
    m = np.asarray(jq.to_matrix(q)) + 1e-3 * rng.normal(size=(200, 3, 3))
    u, _, vt = np.linalg.svd(m)
    d = np.sign(
        np.linalg.det(u @ vt)
    )  # SO(3) projection: flip the smallest singular direction if needed
    projection = np.einsum("nij,nj,njk->nik", u, np.stack([np.ones(200), np.ones(200), d], -1), vt)
    nearest = np.asarray(jax.jit(lambda m: jq.to_matrix(jq.from_matrix(m)))(m))
    assert np.max(np.abs(nearest - projection)) < 1e-6
    assert np.max(np.abs(nearest - projection)) < 1e-13  # in fact exact to round-off
    # Differentiable there: jacfwd == jacrev == central differences (all in one compiled call).
    m0 = m[0]
    h = 1e-6
    steps = h * np.eye(9).reshape(9, 3, 3)
    perturbed = np.concatenate([m0 + steps, m0 - steps])

    def loss(r, q0, m0):  # ‖R(exp(r) q₀) − M‖², stationary at r = 0 if q₀ is the nearest rotation
        return jnp.sum((jq.to_matrix(jq.multiply(jq.from_rotvec(r), q0)) - m0) ** 2)

    @jax.jit
    def derivatives(m0, perturbed):
        stationarity = jax.grad(loss)(jnp.zeros(3), jq.from_matrix(m0), m0)
        return (
            jax.jacfwd(jq.from_matrix)(m0),
            jax.jacrev(jq.from_matrix)(m0),
            jq.from_matrix(perturbed),
            stationarity,
        )

    forward, reverse, values, stationarity = derivatives(m0, perturbed)
    fd = np.moveaxis((np.asarray(values[:9]) - np.asarray(values[9:])) / (2 * h), 0, -1).reshape(
        4, 3, 3
    )
    np.testing.assert_allclose(forward, fd, atol=1e-8)
    np.testing.assert_allclose(reverse, forward, atol=1e-12)
    # Optimality: ‖R − M‖² is stationary along every tangent direction at the result.
    np.testing.assert_allclose(stationarity, 0.0, atol=1e-13)


def test_from_matrix_derivative_at_identity_closed_form():
    """At M = I: q ≈ (1, (M₃₂ − M₂₃)/4, (M₁₃ − M₃₁)/4, (M₂₁ − M₁₂)/4) to first order."""
    derivatives = jax.jit(lambda m: (jax.jacfwd(jq.from_matrix)(m), jax.jacrev(jq.from_matrix)(m)))
    with jax.debug_nans(True):
        forward, reverse = derivatives(jnp.eye(3))
    expected = np.zeros((4, 3, 3))
    for n, (i, j) in enumerate([(2, 1), (0, 2), (1, 0)]):
        expected[n + 1, i, j], expected[n + 1, j, i] = 0.25, -0.25
    np.testing.assert_allclose(forward, expected, atol=1e-14)
    np.testing.assert_allclose(reverse, expected, atol=1e-14)


def test_rotvec_derivatives_at_zero_closed_form():
    """d from_rotvec / dr at 0 is ½·[0; I₃]; d to_rotvec / dq at the identity is [0 | 2·I₃]."""

    @jax.jit
    def derivatives(r, q):
        return (
            jax.jacfwd(jq.from_rotvec)(r),
            jax.jacrev(jq.from_rotvec)(r),
            jax.jacfwd(jq.to_rotvec)(q),
            jax.jacrev(jq.to_rotvec)(q),
        )

    with jax.debug_nans(True):
        fwd_from, rev_from, fwd_to, rev_to = derivatives(jnp.zeros(3), jq.identity())
    for d_from in (fwd_from, rev_from):
        np.testing.assert_array_equal(d_from, 0.5 * np.vstack([np.zeros((1, 3)), np.eye(3)]))
    for d_to in (fwd_to, rev_to):
        np.testing.assert_array_equal(d_to, np.hstack([np.zeros((3, 1)), 2.0 * np.eye(3)]))
    np.testing.assert_array_equal(jq.from_rotvec(jnp.zeros(3)), [1, 0, 0, 0])
    np.testing.assert_array_equal(jq.to_rotvec(jq.identity()), [0, 0, 0])


# ---------------------------------------------------------------------------------------------------
# from_two_vectors.


def test_from_two_vectors_is_the_shortest_alignment():
    rng = np.random.default_rng(5)
    a, b = rng.normal(size=(1000, 3)), 3.0 * rng.normal(size=(1000, 3))
    q = jq.from_two_vectors(a, b)
    a_unit = a / np.linalg.norm(a, axis=-1, keepdims=True)
    b_unit = b / np.linalg.norm(b, axis=-1, keepdims=True)
    np.testing.assert_allclose(jq.rotate(a_unit, q), b_unit, atol=1e-12)
    np.testing.assert_allclose(jnp.linalg.norm(q, axis=-1), 1.0, atol=1e-14)
    axis, angle = jq.to_axis_angle(q)
    between = np.arctan2(np.linalg.norm(np.cross(a, b), axis=-1), np.sum(a * b, axis=-1))
    np.testing.assert_allclose(angle, between, atol=1e-12)  # the smallest possible angle
    np.testing.assert_allclose(
        np.sum(np.asarray(axis) * a_unit, -1), 0.0, atol=1e-12
    )  # axis ⟂ a, b
    np.testing.assert_allclose(np.sum(np.asarray(axis) * b_unit, -1), 0.0, atol=1e-12)
    scipy_q = np.stack(
        [
            Rotation.align_vectors(b[n][None], a[n][None])[0].as_quat(scalar_first=True)
            for n in range(20)
        ]
    )
    assert quat_distance(q[:20], scipy_q) < 1e-12
    assert_quat_close(
        jq.from_two_vectors([1.0, 2.0, 3.0], [2.0, 4.0, 6.0]), jq.identity(), atol=1e-15
    )


def test_from_two_vectors_antiparallel_is_a_half_turn_without_nan():
    a = np.array([[1.0, 0, 0], [0, 0, -2.0], [1.0, 2.0, 3.0], [-0.3, 0.1, 0.7]])
    jacobian = jax.jit(jax.vmap(jax.jacrev(jq.from_two_vectors, argnums=(0, 1))))
    with jax.debug_nans(True):
        q = np.asarray(jq.from_two_vectors(a, -2.5 * a))
        jac = jacobian(a, -2.5 * a)
    assert np.all(np.isfinite(q)) and all(np.all(np.isfinite(j)) for j in jac)
    np.testing.assert_allclose(q[:, 0], 0.0, atol=1e-15)  # a half-turn
    np.testing.assert_allclose(np.linalg.norm(q, axis=-1), 1.0, atol=1e-15)
    np.testing.assert_allclose(np.sum(q[:, 1:] * a, -1), 0.0, atol=1e-15)  # axis ⟂ a
    np.testing.assert_allclose(jq.rotate(a, q), -a, atol=1e-14)
    # Nearly antiparallel (1e-9 rad off): still the exact shortest rotation, no cancellation.
    b = np.asarray(jq.rotate(-a[0], jq.from_axis_angle([0, 0, 1], 1e-9)))
    np.testing.assert_allclose(jq.rotate(a[0], jq.from_two_vectors(a[0], b)), b, atol=1e-15)


# ---------------------------------------------------------------------------------------------------
# Bad input (acceptance 5).


@pytest.mark.parametrize(
    "call, match",
    [
        (
            lambda: jq.from_matrix(np.eye(4)),
            r"`m` must have shape \(\.\.\., 3, 3\); got shape \(4, 4\)",
        ),
        (lambda: jq.to_matrix(np.zeros(3)), r"`q` must have shape \(\.\.\., 4\); got shape \(3,\)"),
        (lambda: jq.from_euler("xyz", np.zeros(2)), r"`angles` must have shape \(\.\.\., 3\)"),
        (lambda: jq.to_euler(np.zeros((2, 3)), "xyz"), r"`q` must have shape \(\.\.\., 4\)"),
        (
            lambda: jq.rotate(np.zeros(3), Q, center=np.zeros(4)),
            r"`center` must have shape \(\.\.\., 3\)",
        ),
        (
            lambda: jq.from_two_vectors(np.zeros(2), np.ones(3)),
            r"`a` must have shape \(\.\.\., 3\)",
        ),
        (lambda: jq.from_rotvec(np.zeros((3, 4))), r"`r` must have shape \(\.\.\., 3\)"),
        (lambda: jq.from_axis_angle(np.zeros(4), 1.0), r"`axis` must have shape \(\.\.\., 3\)"),
        (lambda: jq.from_xyzw(np.zeros(3)), r"`q` must have shape \(\.\.\., 4\)"),
    ],
)
def test_wrong_trailing_dimension_raises(call, match):
    with pytest.raises(ValueError, match=match):
        call()


@pytest.mark.parametrize("seq", ["xyw", "xxz", "xYz", "xy", "xyzx", "", 123, None, "XZZ"])
def test_unknown_euler_sequence_raises(seq):
    with pytest.raises(ValueError, match=r"`seq` must be 3 axes .*got"):
        jq.from_euler(seq, np.zeros(3))
    with pytest.raises(ValueError, match=r"`seq` must be 3 axes .*got"):
        jq.to_euler(Q, seq)


def test_swapped_euler_arguments_say_the_order():
    """`from_euler(angles, seq)` printed the whole angle array as the sequence (helper-76)."""
    order = r"got an array of shape \(3,\) \(the arguments are from_euler\(seq, angles\)"
    with pytest.raises(ValueError, match=r"`seq` must be 3 axes in a string.*" + order):
        jq.from_euler(np.array([0.1, 0.2, 0.3]), "xyz")
    with pytest.raises(ValueError, match=r"got an array of shape \(4,\)"):
        jq.to_euler("xyz", Q)


@pytest.mark.parametrize("frame", [1, None, "World", b"world"])
def test_bad_frame_raises(frame):
    with pytest.raises(ValueError, match=r"`frame` must be one of 'world', 'body'; got"):
        jq.rate(Q, np.zeros(3), frame=frame)
    with pytest.raises(ValueError, match=r"`frame` must be one of"):
        jq.step(Q, np.zeros(3), 0.1, frame=frame)


@pytest.mark.parametrize(
    "dtype, angles, tol",
    [("float32", [1e-7, 3e-8, 1e-9, 1e-20], 1e-6), ("float64", [1e-16, 5e-17, 1e-30], 1e-14)],
)
def test_from_matrix_keeps_rotations_below_round_off_of_one(dtype, angles, tol):
    """A rotation of 3e-8 rad has a float32 matrix that still carries it (m₂₁ − m₁₂ ≈ 2θ n_x), though
    eigh alone returned the identity; SciPy recovers it, and so must we (relative error of the
    rotation vector, against the generating one and SciPy's)."""
    axis = np.array([0.3, -0.5, 0.8]) / np.linalg.norm([0.3, -0.5, 0.8])
    for angle in angles:
        m = Rotation.from_rotvec(angle * axis).as_matrix().astype(dtype)
        q = jq.from_matrix(jnp.asarray(m))
        assert q.dtype == jnp.dtype(dtype)
        r = np.asarray(jq.to_rotvec(q), dtype=np.float64)
        scipy_r = Rotation.from_matrix(m.astype(np.float64)).as_rotvec()
        assert np.linalg.norm(r - angle * axis) <= tol * angle
        assert np.linalg.norm(r - scipy_r) <= tol * angle


@pytest.mark.parametrize(
    "dtype, scales", [("float32", [1e20, 1e-20, 1e30]), ("float64", [1e155, 1e-160, 1e300])]
)
def test_from_two_vectors_for_vectors_whose_squared_length_overflows(dtype, scales):
    """|a|² overflows (or underflows) but a still has a direction: a quarter turn about z, unit."""
    want = np.array([math.sqrt(0.5), 0.0, 0.0, math.sqrt(0.5)])
    for scale in scales:
        for a, b in [([scale, 0.0, 0.0], [0.0, 1.0, 0.0]), ([1.0, 0.0, 0.0], [0.0, scale, 0.0])]:
            q = jq.from_two_vectors(jnp.asarray(a, dtype), jnp.asarray(b, dtype))
            np.testing.assert_allclose(np.asarray(q, np.float64), want, atol=1e-6)


def test_from_two_vectors_derivative_is_that_of_the_directions():
    """The overflow guard divides by the largest component; the derivative must still be the
    directions' (checked against central differences on unnormalised inputs of several lengths)."""
    a = jnp.array([0.3, -1.2, 0.5])
    b = jnp.array([1.1, 0.4, -0.7])
    for scale in [1e-3, 1.0, 1e4]:
        f = lambda a: jq.from_two_vectors(a, b)  # noqa: E731
        jac = np.asarray(jax.jacfwd(f)(scale * a))
        np.testing.assert_allclose(np.asarray(jax.jacrev(f)(scale * a)), jac, atol=1e-12)
        h = 1e-6 * scale
        fd = np.stack(
            [(f(scale * a + h * e) - f(scale * a - h * e)) / (2 * h) for e in np.eye(3)], -1
        )
        np.testing.assert_allclose(jac, fd, rtol=1e-7, atol=1e-9 / scale)


@pytest.mark.parametrize("dtype", ["float32", "float64"])
def test_from_two_vectors_exactly_antiparallel_has_w_non_negative(dtype):
    """cos(fl(π)/2) < 0 in float32: w must still be ≥ 0 (documented), the result a half-turn."""
    for a in ([1.0, 0.0, 0.0], [0.0, 2.0, 0.0], [1.0, 2.0, 3.0]):
        a = jnp.asarray(a, dtype)
        q = jq.from_two_vectors(a, -a)
        assert float(q[0]) >= 0.0
        assert abs(float(jq.to_axis_angle(q)[1]) - math.pi) < 1e-6


@pytest.mark.parametrize(
    "dtype, lengths", [("float32", [1e-20, 1e20, 1e-30]), ("float64", [1e-170, 1e170, 1e-300])]
)
def test_from_axis_angle_normalises_axes_whose_squared_length_over_or_underflows(dtype, lengths):
    """The closed form (cos θ/2, sin θ/2 n̂) for axes of any length the dtype holds: |axis|² under-
    flowed to 0 (identity returned) or overflowed to inf (a non-unit (cos θ/2, 0, 0, 0)) before."""
    angle = np.pi / 2
    for length in lengths:
        for axis in ([0.0, length, 0.0], [length, -2 * length, 2 * length]):
            axis = np.asarray(axis, dtype)
            n = np.asarray(axis, np.float64) / length
            n /= np.linalg.norm(n)
            want = np.concatenate([[np.cos(angle / 2)], np.sin(angle / 2) * n])
            q = jq.from_axis_angle(axis, np.asarray(angle, dtype))
            assert q.dtype == dtype
            np.testing.assert_allclose(np.asarray(q, np.float64), want, atol=1e-6)
    # The derivative is the direction's: against central differences at an ordinary length.
    axis = jnp.array([0.3, -1.2, 0.5])
    jac = np.asarray(jax.jacfwd(jq.from_axis_angle)(axis, 0.7))
    np.testing.assert_allclose(
        np.asarray(jax.jacrev(jq.from_axis_angle)(axis, 0.7)), jac, atol=1e-14
    )
    h = 1e-6
    fd = np.stack(
        [
            (jq.from_axis_angle(axis + h * e, 0.7) - jq.from_axis_angle(axis - h * e, 0.7))
            / (2 * h)
            for e in np.eye(3)
        ],
        -1,
    )
    np.testing.assert_allclose(jac, fd, atol=1e-9)


@pytest.mark.parametrize("dtype", ["float32", "float64"])
def test_from_two_vectors_exactly_antiparallel_is_the_same_under_jit(dtype):
    """Under `jit` the cross product of exactly antiparallel vectors is rounding noise (fused
    multiply-adds), not 0: the documented half-turn about â × e must still be returned, as without
    `jit`, with a bounded Jacobian (it was 1e16 in float64)."""
    for a in ([1.0, 2.0, 3.0], [-0.3, 0.1, 0.7], [2.0, -5.0, 1.0]):
        a = jnp.asarray(a, dtype)
        for b in (-a, -2.5 * a):
            eager = np.asarray(jq.from_two_vectors(a, b))
            jitted = np.asarray(jax.jit(jq.from_two_vectors)(a, b))
            np.testing.assert_allclose(jitted, eager, rtol=0, atol=4 * np.finfo(dtype).eps)
            # â × e with e the basis vector of â's smallest |component|, as documented.
            axis = np.cross(np.asarray(a, np.float64), np.eye(3)[np.argmin(np.abs(a))])
            axis /= np.linalg.norm(axis)
            np.testing.assert_allclose(jitted[1:], axis, atol=1e-6)
            jac = jax.jit(jax.jacfwd(jq.from_two_vectors, argnums=1))(a, b)
            assert np.max(np.abs(np.asarray(jac))) < 10.0 / float(jnp.linalg.norm(b))


def test_to_euler_float32_near_zero_middle_angle_is_not_locked():
    """float32 resolves middle angles near 0 far below 1e-7, so the gimbal-lock window there is
    SciPy's 1e-7 (it was widened to 1.5e-6, as at π): SciPy's angles for a middle angle of 1e-6."""
    angles = np.array([[1.2, 1e-6, -2.1], [-0.4, 5e-7, 2.5], [3.0, 1e-6, 0.3]])
    for seq in ("ZXZ", "zyz", "XYX"):
        q = Rotation.from_euler(seq, angles).as_quat(scalar_first=True).astype(np.float32)
        theirs = Rotation.from_quat(q.astype(np.float64), scalar_first=True).as_euler(seq)
        ours = np.asarray(jq.to_euler(q, seq), np.float64)
        assert np.max(np.abs(wrapped(ours - theirs))) < 2e-6
        assert quat_distance(jq.from_euler(seq, ours), q) < 5e-7


@pytest.mark.parametrize("seq", ["zxz", "ZXZ", "yzy", "xyz", "XYZ", "zyx"])
def test_to_euler_float32_near_the_pi_lock_is_scipys_on_the_same_input(seq):
    """The lock at π (Tait–Bryan: +π/2) is SciPy's 1e-7 in float32 too: its window was 4π·eps ≈
    1.5e-6, as π − middle cancels, and a rotation 1e-6 from the lock came back with its third angle
    0 and 1.1e-6 rad off. The reference: SciPy in float64 on the same float32 quaternions, and the
    rotation itself; inputs exactly at the lock (built in float32) still lock, as SciPy's do."""
    lock = np.pi if seq[0].lower() == seq[2].lower() else np.pi / 2
    for distance in (2e-7, 1e-6, 1.4e-6, 0.0):
        angles = np.array([[0.3, lock - distance, -1.1], [-2.5, lock - distance, 0.7]])
        q = Rotation.from_euler(seq, angles).as_quat(scalar_first=True).astype(np.float32)
        with warnings.catch_warnings():
            warnings.filterwarnings("ignore", "Gimbal lock detected", UserWarning)
            theirs = Rotation.from_quat(q.astype(np.float64), scalar_first=True).as_euler(seq)
        ours = np.asarray(jq.to_euler(q, seq), np.float64)
        assert quat_distance(jq.from_euler(seq, ours), q) < 3e-7, distance
        if distance == 0.0:
            np.testing.assert_array_equal(ours[:, 2], 0.0)
        else:  # (the first and third angles are ill-conditioned near the lock: ~eps / distance)
            assert np.max(np.abs(wrapped(ours - theirs))) < 0.5, distance
            assert np.all(ours[:, 2] != 0.0), distance


@pytest.mark.parametrize("seq", ["xyz", "zyx", "yzx", "XZY", "ZXY", "YXZ"])
def test_to_euler_float32_small_tait_bryan_angles_keep_their_relative_accuracy(seq):
    """The Tait–Bryan middle angle is not `proper middle − π/2` (which rounds to a multiple of
    float32's spacing near π/2, 6e-8, and lost every angle below ~1e-6): SciPy in float64 on the same
    float32 quaternions, rotations of 1e-9 to 1e-3 rad, to float32 round-off relative to the angle."""
    rng = np.random.default_rng(11)
    for scale in (1e-9, 1e-7, 1e-5, 1e-3):
        q = Rotation.from_rotvec(scale * rng.normal(size=(100, 3))).as_quat(scalar_first=True)
        q = q.astype(np.float32)
        theirs = Rotation.from_quat(q.astype(np.float64), scalar_first=True).as_euler(seq)
        ours = np.asarray(jq.to_euler(q, seq), np.float64)
        assert ours.dtype == np.float64 and jq.to_euler(q, seq).dtype == jnp.float32
        np.testing.assert_allclose(ours, theirs, rtol=0, atol=1e-3 * scale)


# --- Extreme magnitudes: a quaternion of any normal magnitude is still a rotation ----------------------

_EXTREME = [
    (np.float32, 1e25),  # |q|² overflows float32 (> 3.4e38)
    (np.float32, 1e-25),  # |q|² underflows to 0 (flushed subnormal)
    (np.float32, 1e38),
    (np.float64, 1e200),
    (np.float64, 1e-200),
]


@pytest.mark.parametrize("dtype, scale", _EXTREME)
@pytest.mark.parametrize("compile", [False, True], ids=["eager", "jit"])
def test_conversions_of_extreme_magnitude_match_scipy(dtype, scale, compile):
    rng = np.random.default_rng(11)
    unit = rng.normal(size=(6, 4))
    unit /= np.linalg.norm(unit, axis=-1, keepdims=True)
    v = rng.normal(size=(6, 3))
    ref = Rotation.from_quat(unit[:, [1, 2, 3, 0]])
    q = jnp.asarray(unit * scale, dtype)
    tol = 2e-6 if dtype == np.float32 else 2e-15
    wrap = jax.jit if compile else (lambda f: f)
    got = {
        "normalize": (wrap(jq.normalize)(q), unit),
        "to_matrix": (wrap(jq.to_matrix)(q), ref.as_matrix()),
        "to_rotvec": (wrap(jq.to_rotvec)(q), ref.as_rotvec()),
        "to_euler": (wrap(lambda q: jq.to_euler(q, "zyx"))(q), ref.as_euler("zyx")),
        "rotate": (wrap(jq.rotate)(jnp.asarray(v, dtype), q), ref.apply(v)),
        "to_axis_angle": (
            wrap(lambda q: jq.to_axis_angle(q)[0] * jq.to_axis_angle(q)[1][..., None])(q),
            ref.as_rotvec(),
        ),
        "norm/scale": (np.asarray(wrap(jq.norm)(q), np.float64) / scale, np.ones(6)),
        "log[w] - ln(scale)": (wrap(jq.log)(q)[:, 0] - math.log(scale), np.zeros(6)),
        "from_matrix(scale R)": (
            jq.canonicalize(wrap(jq.from_matrix)(jnp.asarray(ref.as_matrix() * scale, dtype))),
            np.where(unit[:, :1] < 0, -unit, unit),
        ),
    }
    if scale < 1e30:  # 1/1e38 is subnormal in float32, and XLA flushes subnormals to zero
        got["inverse * scale"] = (
            np.asarray(wrap(jq.inverse)(q), np.float64) * scale,
            unit * [1, -1, -1, -1],
        )
    for name, (value, expected) in got.items():
        value = np.asarray(value, np.float64)
        # ln(1e±25) ≈ ±58 in float32 carries 4e-6 of round-off
        limit = 30 * tol if name.startswith("log") else tol
        assert value.dtype == np.float64 and np.all(np.isfinite(value)), name
        np.testing.assert_allclose(value, expected, rtol=0, atol=limit, err_msg=name)


@pytest.mark.parametrize("dtype, scale", [(np.float32, 1e25), (np.float64, 1e-200)])
def test_derivatives_at_extreme_magnitude_are_the_scaled_unit_ones(dtype, scale):
    # Every conversion is homogeneous of degree 0 in q, so d f(s u)/dq = f'(u)/s.
    unit = jnp.asarray([0.3, -0.5, 0.7, 0.4], dtype)
    unit = unit / jnp.sqrt(jnp.sum(unit * unit))
    v = jnp.asarray([0.2, -1.0, 0.6], dtype)
    for name, f in [
        ("to_matrix", lambda q: jq.to_matrix(q)[0, 1]),
        ("to_rotvec", lambda q: jq.to_rotvec(q)[2]),
        ("rotate", lambda q: jq.rotate(v, q)[1]),
        ("normalize", lambda q: jq.normalize(q)[3]),
    ]:
        at_scale = np.asarray(jax.grad(f)(unit * jnp.asarray(scale, dtype)), np.float64) * scale
        at_unit = np.asarray(jax.grad(f)(unit), np.float64)
        tol = 1e-5 if dtype == np.float32 else 1e-14
        np.testing.assert_allclose(at_scale, at_unit, rtol=0, atol=tol, err_msg=name)


@pytest.mark.parametrize(
    "dtype, offset", [(np.float32, 0.0), (np.float32, 1e-6), (np.float64, 1e-12)]
)
def test_reverse_mode_derivatives_at_a_half_turn_are_the_closed_forms(dtype, offset):
    """float32 `from_axis_angle(z, π)` has w = cos(π/2) = −4.4e-8, flipped to w > 0: the series branch
    of atan2(s, w)/s, unused there, overflowed in x = s²/w² and made `grad` NaN for to_rotvec, log,
    slerp and angular_velocity (within ~1e-5 rad of π in float32; `jacfwd` was finite)."""
    z = jnp.asarray([0.0, 0.0, 1.0], dtype)
    a = jnp.asarray(np.pi - offset, dtype)

    def turn(angle):
        return jq.from_axis_angle(z, angle)

    cases = {
        # d/da of (rotation vector)_z = a, of (log)_z = a/2, of ω_z = a/Δt, of slerp(1, R_z(a), ½)_z
        # = sin(a/4) (no half-turn flip: w > 0 here, or the shortest path is the same arc).
        "to_rotvec": (lambda a: jq.to_rotvec(turn(a))[2], 1.0),
        "log": (lambda a: jq.log(turn(a))[3], 0.5),
        "angular_velocity": (
            lambda a: jq.angular_velocity(jnp.stack([jq.identity(dtype=dtype), turn(a)]), 0.1)[
                0, 2
            ],
            10.0,
        ),
    }
    tol = 1e-5 if dtype == np.float32 else 1e-12
    for name, (f, expected) in cases.items():
        assert abs(float(jax.grad(f)(a)) - expected) <= tol, name
    q = turn(a)
    gradient = np.asarray(jax.grad(lambda q: jnp.sum(jq.to_rotvec(q)))(q))
    assert np.all(np.isfinite(gradient))
    forward = np.asarray(jax.jacfwd(lambda q: jnp.sum(jq.to_rotvec(q)))(q))
    np.testing.assert_allclose(gradient, forward, rtol=1e-6, atol=1e-6)
    # slerp halfway: the z-component is ±sin(a/4) along the arc from the identity (the sign depends on
    # which of q, −q is nearer, which float32's w = −4.4e-8 at π leaves to rounding): slope ±cos(a/4)/4.
    slope = float(jax.grad(lambda a: jq.slerp(jq.identity(dtype=dtype), turn(a), 0.5)[3])(a))
    assert np.isfinite(slope) and abs(abs(slope) - np.cos(float(a) / 4) / 4) <= tol


@pytest.mark.parametrize("compile", [False, True], ids=["eager", "jit"])
def test_axes_near_the_float64_maximum_keep_their_direction(compile):
    """`unit_vector` divided by the largest component, and XLA's x/m = x·(1/m) flushed 1/m to zero
    above ~4.5e307: from_axis_angle and from_two_vectors gave NaN there. It now scales by `prescale`."""
    wrap = jax.jit if compile else (lambda f: f)
    axis = np.array([1e308, 2e307, 0.0])
    got = np.asarray(wrap(jq.from_axis_angle)(jnp.asarray(axis), 1.0))
    expected = Rotation.from_rotvec(axis / np.linalg.norm(axis / 1e308) / 1e308).as_quat(
        scalar_first=True
    )
    np.testing.assert_allclose(got, expected, rtol=0, atol=2e-16)
    turn = np.asarray(
        wrap(jq.from_two_vectors)(jnp.asarray([1e308, 0, 0.0]), jnp.asarray([0, 1.0, 0]))
    )
    np.testing.assert_allclose(turn, [np.sqrt(0.5), 0, 0, np.sqrt(0.5)], rtol=0, atol=2e-16)


@pytest.mark.parametrize("compile", [False, True])
def test_conversions_of_no_rotation_are_nan(compile):
    """q = 0 (also all-subnormal q, which XLA:CPU flushes to zero) and infinite components name no
    rotation: the conversions give NaN, as `normalize`, `inverse` and `to_matrix` do, where they used to invent
    the identity (to_rotvec, to_axis_angle) or a quarter-turn (to_euler "xyz" gave (0, −π/2, 0))."""
    qs = np.array([[0.0, 0, 0, 0], [np.inf, 0, 0, 0], [1.0, -np.inf, 0, 0], [1e-320, 0, 0, 1e-320]])
    maybe = jax.jit if compile else (lambda f: f)
    assert np.all(np.isnan(maybe(jq.to_rotvec)(qs)))
    axis, angle = maybe(jq.to_axis_angle)(qs)
    assert np.all(np.isnan(axis)) and np.all(np.isnan(angle))
    for seq in ["xyz", "ZYX", "zxz", "XYX"]:
        assert np.all(np.isnan(maybe(lambda q, s=seq: jq.to_euler(q, s))(qs))), seq
    # So are `to_matrix`, `normalize`, `inverse` and `rotate` (an infinite component gave a matrix
    # with ones on its diagonal, q/|q| = (NaN, 0, 0, 0) and q⁻¹ = (NaN, −0, −0, −0)).
    for f in (jq.to_matrix, jq.normalize, jq.inverse, lambda q: jq.rotate(np.ones(3), q)):
        out = maybe(f)(qs)
        assert np.all(np.isnan(out)), out
    np.testing.assert_allclose(
        maybe(jq.to_matrix)(np.array([0.1, 0.2, -0.3, 0.4])),
        Rotation.from_quat([0.2, -0.3, 0.4, 0.1]).as_matrix(),
        atol=1e-15,
    )
    # Ordinary inputs are untouched: SciPy's conversions of the same (non-unit) quaternions.
    good = np.array([[2.0, 0, 0, 0], [0.1, 0.2, -0.3, 0.4], [-3.0, 1e-3, 0, 0]])
    reference = Rotation.from_quat(good[:, [1, 2, 3, 0]])
    np.testing.assert_allclose(maybe(jq.to_rotvec)(good), reference.as_rotvec(), atol=1e-15)
    np.testing.assert_allclose(
        maybe(lambda q: jq.to_euler(q, "xyz"))(good), reference.as_euler("xyz"), atol=1e-15
    )


@pytest.mark.parametrize("dtype", [jnp.float16, jnp.bfloat16])
def test_half_precision_matrices_and_means(dtype):
    """float16/bfloat16 inputs to the eigenvector-based functions: XLA:CPU has no half-precision eigh,
    so they are computed in float32 and returned in the input dtype (they raised NotImplementedError
    from inside eigh, or "not inexact" for a bfloat16 inertia), agreeing with SciPy to the dtype's
    resolution."""
    rotation = Rotation.from_rotvec([0.3, -1.2, 0.5])
    m = jnp.asarray(rotation.as_matrix(), dtype)
    q = jq.from_matrix(m)
    assert q.dtype == dtype
    want = rotation.as_quat()[[3, 0, 1, 2]]
    np.testing.assert_allclose(np.asarray(q, np.float64), want, atol=2e-2)
    mean = jq.mean(jnp.asarray(np.stack([want, want]), dtype))
    assert mean.dtype == dtype
    np.testing.assert_allclose(np.asarray(mean, np.float64), want, atol=2e-2)
    moments, axes = jq.principal_axes(jnp.diag(jnp.asarray([1.0, 2.0, 3.0], dtype)))
    assert moments.dtype == dtype and axes.dtype == dtype
    np.testing.assert_allclose(np.asarray(moments, np.float64), [1.0, 2.0, 3.0], atol=2e-2)
    assert float(jq.angle_between(axes.astype(jnp.float32), jq.identity(dtype=jnp.float32))) < 2e-2
    grad = jax.grad(lambda m: jnp.sum(jq.from_matrix(m).astype(jnp.float32)))(m)
    assert grad.dtype == dtype and np.all(np.isfinite(np.asarray(grad, np.float64)))


def _davenport(m):
    """Davenport's K for matrices M, as `from_matrix` forms it (written out here)."""
    m = np.asarray(m)
    trace = np.trace(m, axis1=-2, axis2=-1)
    a = np.stack(
        [m[..., 2, 1] - m[..., 1, 2], m[..., 0, 2] - m[..., 2, 0], m[..., 1, 0] - m[..., 0, 1]], -1
    )
    k = np.zeros(m.shape[:-2] + (4, 4))
    k[..., 0, 0] = trace
    k[..., 0, 1:] = k[..., 1:, 0] = a
    k[..., 1:, 1:] = m + np.swapaxes(m, -1, -2) - trace[..., None, None] * np.eye(3)
    return k


@pytest.mark.parametrize("dtype", ["float64", "float32"])
def test_from_matrix_power_steps_on_rotations_and_eigh_elsewhere(dtype):
    """`from_matrix` takes the top eigenvector of Davenport's matrix by power steps when every matrix
    of the batch is proven converged (near rotations), and by `eigh` otherwise; both give the nearest
    rotation, SciPy's quaternion for rotations."""
    from jaxquat._numerics import _davenport_power, _top_eigenvector

    rng = np.random.default_rng(8)
    n = 2000
    rotations = Rotation.random(n, random_state=9)
    half_turns = Rotation.from_rotvec(np.pi * Rotation.random(n, random_state=10).as_matrix()[:, 0])
    near = {
        "rotations": rotations.as_matrix(),
        "half-turns": half_turns.as_matrix(),
        "small angles": Rotation.from_rotvec(1e-9 * rng.normal(size=(n, 3))).as_matrix(),
        "noise 1e-2": rotations.as_matrix() + 1e-2 * rng.normal(size=(n, 3, 3)),
        "scaled 1e-30": 1e-30 * rotations.as_matrix(),
    }
    eps = np.finfo(dtype).eps
    for name, m in near.items():
        k = jnp.asarray(_davenport(m / np.max(np.abs(m))), dtype)
        _, converged = _davenport_power(k)
        assert bool(jnp.all(converged)), name
        power = _top_eigenvector(k, True)
        by_eigh = _top_eigenvector(k, False)
        gap = np.minimum(
            np.linalg.norm(power - by_eigh, axis=-1), np.linalg.norm(power + by_eigh, axis=-1)
        )
        assert np.max(gap) <= 64 * eps, (name, np.max(gap))
        q = jq.from_matrix(jnp.asarray(m, dtype))
        scipy = Rotation.from_matrix(m).as_quat(scalar_first=True)
        error = np.minimum(np.linalg.norm(q - scipy, axis=-1), np.linalg.norm(q + scipy, axis=-1))
        assert np.max(error) <= 32 * eps, (name, np.max(error))
    # Far from rotations (a reflection, 0, most Gaussian matrices) the check fails; where it passes,
    # the power steps did find the top eigenvector. One failing matrix sends its batch through eigh:
    # the result is still the nearest rotation (SVD Procrustes).
    far = np.concatenate([-np.eye(3)[None], np.zeros((1, 3, 3)), rng.normal(size=(200, 3, 3))])
    k = jnp.asarray(_davenport(far), dtype)
    power, converged = _davenport_power(k)
    assert not bool(converged[0]) and not bool(converged[1])
    assert np.mean(converged) < 0.1
    by_eigh = _top_eigenvector(k, False)
    gap = np.minimum(
        np.linalg.norm(power - by_eigh, axis=-1), np.linalg.norm(power + by_eigh, axis=-1)
    )
    assert np.max(np.where(converged, gap, 0.0)) <= 64 * eps
    mixed = np.concatenate([rotations.as_matrix()[:100], rng.normal(size=(1, 3, 3))])
    q = np.asarray(jq.from_matrix(jnp.asarray(mixed, dtype)), np.float64)
    u, _, vt = np.linalg.svd(mixed)
    u[..., :, 2] *= np.sign(np.linalg.det(u @ vt))[..., None]
    nearest = np.einsum("nij,nij->n", u @ vt, mixed)
    mine = np.einsum("nij,nij->n", np.asarray(jq.to_matrix(jnp.asarray(q))), mixed)
    assert np.all(mine >= nearest - 64 * eps * np.abs(nearest))
    # Under vmap (nested, or with the matrix unbatched) the whole batch takes one branch, as in a
    # batched call: the program keeps its `cond` (vmap's own rule would compute both branches and
    # select), and the values are the batched call's.
    batched = jax.vmap(jq.from_matrix)(jnp.asarray(mixed, dtype))
    np.testing.assert_allclose(batched, q.astype(dtype), atol=16 * eps)
    nested = jax.vmap(jax.vmap(jq.from_matrix))(jnp.asarray(near["rotations"], dtype)[None])
    np.testing.assert_allclose(
        nested[0], jq.from_matrix(jnp.asarray(near["rotations"], dtype)), atol=16 * eps
    )
    scaled = jax.vmap(lambda s, m: s * jq.from_matrix(m), in_axes=(0, None))
    np.testing.assert_allclose(
        scaled(jnp.arange(3.0, dtype=dtype), jnp.asarray(mixed[0], dtype))[2],
        2 * q[0],
        atol=32 * eps,
    )
    program = jax.make_jaxpr(jax.vmap(jq.from_matrix))(jnp.asarray(mixed, dtype)).jaxpr
    assert _eigh_outside_cond(program) == 0 and _eigh_outside_cond(program, inside=True) == 1


def _eigh_outside_cond(jaxpr, inside=False) -> int:
    """The `eigh` calls of a jaxpr and the jaxprs it calls, not counting (or, `inside`, counting only)
    those in the branches of a `cond`."""
    count = 0
    for eqn in jaxpr.eqns:
        if eqn.primitive.name == "eigh":
            count += not inside
        for value in eqn.params.values():
            for sub in value if isinstance(value, tuple) else (value,):
                sub = getattr(sub, "jaxpr", sub)
                if hasattr(sub, "eqns"):
                    if eqn.primitive.name == "cond":
                        count += _eigh_outside_cond(sub, inside=False) if inside else 0
                    else:
                        count += _eigh_outside_cond(sub, inside)
    return count


def test_from_matrix_derivatives_are_those_of_eigh_on_the_power_path():
    """The derivative is perturbation theory about the eigenvector, whichever way it was computed:
    forward and reverse mode agree with central differences at the identity, near a half-turn and
    at a generic rotation, on the power path."""
    from jaxquat._numerics import _davenport_power

    for rotvec in ([0.0, 0.0, 0.0], [0.0, 0.0, np.pi - 1e-3], [0.3, -1.2, 0.7]):
        m = jnp.asarray(Rotation.from_rotvec(rotvec).as_matrix())
        assert bool(_davenport_power(jnp.asarray(_davenport(m)))[1])
        forward = jax.jacfwd(jq.from_matrix)(m)
        reverse = jax.jacrev(jq.from_matrix)(m)
        h = 1e-6
        central = np.zeros((4, 3, 3))
        for i in range(3):
            for j in range(3):
                e = np.zeros((3, 3))
                e[i, j] = h
                central[:, i, j] = (jq.from_matrix(m + e) - jq.from_matrix(m - e)) / (2 * h)
        np.testing.assert_allclose(forward, central, atol=1e-8, err_msg=str(rotvec))
        np.testing.assert_allclose(reverse, central, atol=1e-8, err_msg=str(rotvec))
