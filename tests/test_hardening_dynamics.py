"""Input hardening of the integrator, rigid-body dynamics and solver entry points.

Every bad input raises a `ValueError` at trace time (also under `jax.jit`) naming the argument and what
was expected; valid inputs near the rejected ones keep working.
"""

import functools

import diffrax
import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jaxquat as jq

Q0 = jnp.array([1.0, 0.0, 0.0, 0.0])
MOMENTS = jnp.array([1.0, 2.0, 3.5])
OMEGA = jnp.array([0.3, -0.2, 1.0])


# --------------------------------------------------------------------------------------------------
# Defect 1: a non-scalar dt / t0


@pytest.mark.parametrize("batch", [(), (2,)])
def test_simulate_rigid_body_array_dt_names_dt(batch):
    q0 = jnp.broadcast_to(Q0, batch + (4,))
    omega0 = jnp.broadcast_to(OMEGA, batch + (3,))
    with pytest.raises(ValueError, match=r"`dt` must be a scalar; got shape \(2,\)"):
        jq.simulate_rigid_body(q0, omega0, MOMENTS, jnp.array([0.1, 0.2]), 2)
    with pytest.raises(ValueError, match=r"`t0` must be a scalar"):
        jq.simulate_rigid_body(q0, omega0, MOMENTS, 0.1, 2, t0=jnp.zeros(2))


def test_simulate_deformable_body_array_dt_names_dt():
    def positions(t):
        return jnp.eye(3) * (1.0 + 0.1 * t)

    with pytest.raises(ValueError, match=r"`dt` must be a scalar"):
        jq.simulate_deformable_body(jnp.ones(3), positions, Q0, jnp.array([0.1, 0.2]), 2)
    with pytest.raises(ValueError, match=r"`t0` must be a scalar"):
        jq.simulate_deformable_body(jnp.ones(3), positions, Q0, 0.1, 2, t0=jnp.zeros(3))


def test_scalar_dt_still_works_under_jit_and_vmap():
    run = jax.jit(lambda dt: jq.simulate_rigid_body(Q0, OMEGA, MOMENTS, dt, 4, save="final")[0])
    single = run(0.05)
    batched = jax.vmap(run)(jnp.array([0.05, 0.05]))
    np.testing.assert_allclose(batched, jnp.stack([single, single]), atol=1e-14)


def test_corrected_vector_field_array_dt_names_dt():
    with pytest.raises(ValueError, match=r"`dt` must be a scalar"):
        jq.corrected_vector_field(OMEGA, jnp.array([0.1, 0.2]))


@pytest.mark.parametrize("bad", [float("nan"), float("inf"), -np.inf, jnp.array(jnp.nan)])
def test_non_finite_dt_and_t0_name_the_argument(bad):
    """A NaN or infinite step or start time is an error, not an all-NaN trajectory (the simulations
    used to return one), also when it is a constant under `jit` (`integrate` used to miss that)."""

    def positions(t):
        return jnp.eye(3) * (1.0 + 0.1 * t)

    calls = {
        "integrate": lambda **kw: jq.integrate(
            Q0, OMEGA, kw.get("dt", 0.1), 3, t0=kw.get("t0", 0.0), save="final"
        )[None],
        "simulate_rigid_body": lambda **kw: jq.simulate_rigid_body(
            Q0, OMEGA, MOMENTS, kw.get("dt", 0.1), 3, t0=kw.get("t0", 0.0)
        ),
        "simulate_deformable_body": lambda **kw: jq.simulate_deformable_body(
            jnp.ones(3), positions, Q0, kw.get("dt", 0.1), 3, t0=kw.get("t0", 0.0)
        ),
    }
    for name, call in calls.items():
        for argument in ("dt", "t0"):
            kwargs = {argument: bad}
            with pytest.raises(ValueError, match=rf"`{argument}` must be finite"):
                call(**kwargs)
            with pytest.raises(ValueError, match=rf"`{argument}` must be finite"):
                jax.jit(functools.partial(call, **kwargs))()  # a constant under jit: still checked
        assert np.all(np.isfinite(np.asarray(call()[0]))), name
    with pytest.raises(ValueError, match=r"`dt` must be finite"):
        jq.corrected_vector_field(OMEGA, bad)


# --------------------------------------------------------------------------------------------------
# Defect 2: a torque callable returning the wrong shape


@pytest.mark.parametrize("frame", ["body", "world"])
@pytest.mark.parametrize("bad_shape", [(4,), (5, 3), (), (2,)])
def test_torque_wrong_shape_names_torque(frame, bad_shape):
    def torque(t, q, omega):
        return jnp.ones(bad_shape)

    with pytest.raises(
        ValueError, match=r"`torque\(t, q, omega\)` must return shape \(\.\.\., 3\)"
    ):
        jq.simulate_rigid_body(Q0, OMEGA, MOMENTS, 0.1, 2, torque=torque, frame=frame)
    with pytest.raises(ValueError, match=r"`torque.*\(3,\)"):
        jax.jit(
            lambda w: jq.simulate_rigid_body(Q0, w, MOMENTS, 0.1, 2, torque=torque, frame=frame)
        )(OMEGA)


def test_torque_must_not_add_batch_axes():
    q0 = jnp.broadcast_to(Q0, (2, 4))
    omega0 = jnp.broadcast_to(OMEGA, (2, 3))
    with pytest.raises(ValueError, match=r"`torque.*\(2, 3\); got shape \(3, 3\)"):
        jq.simulate_rigid_body(q0, omega0, MOMENTS, 0.1, 2, torque=lambda t, q, w: jnp.ones((3, 3)))


def test_torque_broadcasting_to_the_state_still_works():
    q0 = jnp.broadcast_to(Q0, (2, 4))
    omega0 = jnp.broadcast_to(OMEGA, (2, 3))
    tau = jnp.array([0.0, 0.0, 0.1])
    q_shared, w_shared = jq.simulate_rigid_body(
        q0, omega0, MOMENTS, 0.1, 3, torque=lambda t, q, w: tau, save="final"
    )
    q_full, w_full = jq.simulate_rigid_body(
        q0,
        omega0,
        MOMENTS,
        0.1,
        3,
        torque=lambda t, q, w: jnp.broadcast_to(tau, w.shape),
        save="final",
    )
    np.testing.assert_allclose(q_shared, q_full, atol=1e-15)
    np.testing.assert_allclose(w_shared, w_full, atol=1e-15)


def test_rigid_body_vector_field_torque_wrong_shape_names_torque():
    field = jq.rigid_body_vector_field(MOMENTS, torque=lambda t, q, w: jnp.ones(4))
    with pytest.raises(ValueError, match=r"`torque\(t, q, omega\)`"):
        diffrax.diffeqsolve(diffrax.ODETerm(field), jq.CF4(), 0.0, 0.1, 0.05, (Q0, OMEGA))


# --------------------------------------------------------------------------------------------------
# Defect 3: bools as counts, non-bools as flags


@pytest.mark.parametrize(
    ("kwargs", "name"),
    [
        (dict(num_steps=True), "num_steps"),
        (dict(num_steps=np.True_), "num_steps"),
        (dict(save_every=True), "save_every"),
        (dict(unroll=True), "unroll"),
        (dict(renormalize_every=True), "renormalize_every"),
        (dict(checkpoint="yes"), "checkpoint"),
        (dict(checkpoint=1), "checkpoint"),
        (dict(checkpoint=None), "checkpoint"),
        (dict(compensated="x"), "compensated"),
        (dict(compensated=0), "compensated"),
    ],
)
def test_integrate_rejects_bad_static_arguments(kwargs, name):
    args = dict(num_steps=4)
    args.update(kwargs)
    num_steps = args.pop("num_steps")
    with pytest.raises(ValueError, match=f"`{name}`"):
        jq.integrate(Q0, OMEGA, 0.1, num_steps, **args)
    with pytest.raises(ValueError, match=f"`{name}`"):
        jax.jit(lambda w: jq.integrate(Q0, w, 0.1, num_steps, **args))(OMEGA)


@pytest.mark.parametrize("value", [0, -3])
def test_integrate_rejects_non_positive_renormalize_every(value):
    with pytest.raises(ValueError, match="`renormalize_every` must be >= 1"):
        jq.integrate(Q0, OMEGA, 0.1, 4, renormalize_every=value)


def test_integrate_accepts_bool_flags_and_numpy_ints():
    base = jq.integrate(Q0, OMEGA, 0.1, 4, method="midpoint")
    for kwargs in (
        dict(checkpoint=False),
        dict(checkpoint=np.True_),
        dict(compensated=True),
        dict(compensated=None),
        dict(renormalize_every=None),
        dict(renormalize_every=np.int64(2)),
        dict(unroll=2),
    ):
        out = jq.integrate(Q0, OMEGA, 0.1, np.int64(4), method="midpoint", **kwargs)
        np.testing.assert_allclose(out, base, atol=1e-14)


@pytest.mark.parametrize(
    ("kwargs", "name"),
    [
        (dict(num_steps=True), "num_steps"),
        (dict(save_every=True), "save_every"),
        (dict(num_steps=-1), "num_steps"),
        (dict(num_steps=2.0), "num_steps"),
    ],
)
def test_simulations_reject_bad_step_counts(kwargs, name):
    args = dict(num_steps=2)
    args.update(kwargs)
    num_steps = args.pop("num_steps")
    with pytest.raises(ValueError, match=f"`{name}`"):
        jq.simulate_rigid_body(Q0, OMEGA, MOMENTS, 0.1, num_steps, **args)
    with pytest.raises(ValueError, match=f"`{name}`"):
        jq.simulate_deformable_body(
            jnp.ones(3), lambda t: jnp.eye(3) * (1.0 + t), Q0, 0.1, num_steps, **args
        )


@pytest.mark.parametrize("dt", [0.0, -0.1, float("nan"), jnp.array(0.0)])
def test_sampled_rejects_non_positive_interval(dt):
    with pytest.raises(ValueError, match=r"`dt` \(the sampling interval\) must be finite and > 0"):
        jq.sampled(jnp.ones((3, 3)), dt)


def test_sampled_traced_interval_is_not_checked():
    out = jax.jit(lambda dt: jq.integrate(Q0, jq.sampled(jnp.ones((3, 3)), dt), 0.1, 3))(0.1)
    assert out.shape == (4, 4)


# --------------------------------------------------------------------------------------------------
# Defect 4: batch mismatches name the arguments


@pytest.mark.parametrize(
    ("call", "pattern"),
    [
        (lambda: jq.center_of_mass(jnp.ones((2, 3)), jnp.ones((4, 3, 3))), "`masses`.*`positions`"),
        (
            lambda: jq.inertia_tensor(jnp.ones(3), jnp.ones((2, 3, 3)), about=jnp.zeros((4, 3))),
            "`positions`.*`about`",
        ),
        (
            lambda: jq.angular_momentum(jnp.ones(3), jnp.ones((2, 3, 3)), jnp.ones((4, 3, 3))),
            "`positions`.*`velocities`",
        ),
        (lambda: jq.euler_equations(jnp.ones((2, 3)), jnp.ones((4, 3))), "`omega_body`.*`inertia`"),
        (
            lambda: jq.euler_equations(jnp.ones((2, 3)), MOMENTS, jnp.ones((4, 3))),
            "`omega_body`.*`torque`",
        ),
        (lambda: jq.kinetic_energy(jnp.ones((2, 3)), jnp.ones((4, 3))), "`inertia`.*`omega_body`"),
        (
            lambda: jq.kinetic_energy(jnp.ones((2, 3)), jnp.broadcast_to(jnp.eye(3), (4, 3, 3))),
            "`inertia`.*`omega_body`",
        ),
        (
            lambda: jq.simulate_rigid_body(jnp.ones((2, 4)), jnp.ones((3, 3)), MOMENTS, 0.1, 2),
            "`q0`.*`omega0`",
        ),
        (
            lambda: jq.simulate_rigid_body(Q0, jnp.ones((2, 3)), jnp.ones((5, 3)), 0.1, 2),
            "`omega0`.*`inertia`",
        ),
    ],
)
def test_batch_mismatch_names_arguments(call, pattern):
    with pytest.raises(ValueError, match=pattern):
        call()


def test_kinematic_vector_field_omega_batch_names_omega():
    field = jq.kinematic_vector_field(jnp.ones((3, 3)))
    with pytest.raises(
        ValueError, match=r"`omega` must have shape \(\.\.\., 3\) with leading axes"
    ):
        field(0.0, jnp.broadcast_to(Q0, (2, 4)), None)
    # Broadcasting ω over the state's batch is fine.
    out = jq.kinematic_vector_field(OMEGA)(0.0, jnp.broadcast_to(Q0, (2, 4)), None)
    assert out.shape == (2, 4)


# --------------------------------------------------------------------------------------------------
# Defect 5: empty point sets, count mismatch


@pytest.mark.parametrize(
    "call",
    [
        lambda: jq.center_of_mass(jnp.ones(0), jnp.ones((0, 3))),
        lambda: jq.inertia_tensor(jnp.ones(0), jnp.ones((0, 3))),
        lambda: jq.inertia_tensor(jnp.ones(0), jnp.ones((0, 3)), about=jnp.zeros(3)),
        lambda: jq.angular_momentum(jnp.ones(0), jnp.ones((0, 3)), jnp.ones((0, 3))),
        lambda: jq.center_of_mass(jnp.ones((2, 0)), jnp.ones((2, 0, 3))),
        lambda: jq.simulate_deformable_body(
            jnp.ones(0), lambda t: jnp.ones((0, 3)) * t, Q0, 0.1, 2
        ),
    ],
)
def test_empty_point_set_raises(call):
    with pytest.raises(ValueError, match="at least one point mass is needed"):
        call()
    with pytest.raises(ValueError, match="at least one point mass is needed"):
        jax.jit(call)()


def test_point_count_mismatch_names_masses_and_positions():
    with pytest.raises(ValueError, match=r"`masses`.*n = 3.*`positions`.*got shape \(2,\)"):
        jq.center_of_mass(jnp.ones(2), jnp.ones((3, 3)))
    with pytest.raises(ValueError, match=r"`masses`.*`positions`"):
        jq.inertia_tensor(jnp.ones(4), jnp.ones((3, 3)))


def test_single_point_mass_still_works():
    np.testing.assert_allclose(jq.center_of_mass(jnp.ones(1), jnp.ones((1, 3))), jnp.ones(3))
    np.testing.assert_allclose(jq.inertia_tensor(jnp.ones(1), jnp.ones((1, 3))), jnp.zeros((3, 3)))


# --------------------------------------------------------------------------------------------------
# Defect 6: principal_axes wants a matrix


@pytest.mark.parametrize("shape", [(2, 2), (4, 3), (3,)])
def test_principal_axes_wrong_shape_says_matrix(shape):
    inertia = jnp.eye(2) if shape == (2, 2) else jnp.ones(shape)
    with pytest.raises(ValueError, match=r"`inertia` must have shape \(\.\.\., 3, 3\)"):
        jq.principal_axes(inertia)


def test_inertia_wrong_shape_names_both_forms():
    with pytest.raises(
        ValueError, match=r"`inertia` must be a \(\.\.\., 3, 3\) matrix or principal"
    ):
        jq.euler_equations(OMEGA, jnp.eye(2))


@pytest.mark.parametrize(
    "y, match",
    [
        (
            (jnp.ones((2, 4)), jnp.ones((3, 3))),
            r"`y\[0\] \(q\)` has shape \(2, 4\); `y\[1\] \(omega\)`",
        ),
        ((jnp.ones(4), jnp.ones(4)), r"`y\[1\] \(omega\)` must have shape \(\.\.\., 3\)"),
        ((jnp.ones(3), jnp.ones(3)), r"`y\[0\] \(q\)` must have shape \(\.\.\., 4\)"),
        (jnp.ones(7), r"the state `y` must be a pair \(q, omega\)"),
        ((jnp.ones(4),), r"tuple of length 1"),
    ],
)
def test_rigid_body_vector_field_bad_state_names_the_part(y, match):
    """A malformed state is a ValueError naming y[0] (q) or y[1] (omega), never a JAX TypeError."""
    field = jq.rigid_body_vector_field(MOMENTS)
    with pytest.raises(ValueError, match=match):
        field(0.0, y, None)


# --------------------------------------------------------------------------------------------------
# Review of 2026-11-25: exact gyroscopic term, degenerate deformable shapes


def test_euler_equations_axisymmetric_slender_body_is_exact_under_jit():
    """(I₂ − I₃) ω₂ ω₃ / I₁ is exactly 0 for I₂ = I₃; the cross-product form I₂ω₂ω₃ − I₃ω₃ω₂, once
    XLA contracted it into a fused multiply-add, left a residue that 1/I₁ = 1e8 made ω̇₁ = −1.1."""
    omega = jnp.array([0.3, -0.81234567, 0.5345678], jnp.float32)
    for moments in ([1e-8, 1.0, 1.0], [1.0, 1e-8, 1.0], [1.0, 1.0, 1e-8]):
        moments = jnp.asarray(moments, jnp.float32)
        axis = int(np.argmin(moments))
        rate = np.asarray(jax.jit(jq.euler_equations)(omega, moments))
        assert rate[axis] == 0.0
        # The others against the component form in float64.
        i, w = np.asarray(moments, np.float64), np.asarray(omega, np.float64)
        want = np.array(
            [
                (i[1] - i[2]) * w[1] * w[2] / i[0],
                (i[2] - i[0]) * w[2] * w[0] / i[1],
                (i[0] - i[1]) * w[0] * w[1] / i[2],
            ]
        )
        np.testing.assert_allclose(np.delete(rate, axis), np.delete(want, axis), rtol=1e-6)


def test_slender_axisymmetric_body_float32_matches_the_closed_form():
    """Torque-free, I₂ = I₃ = I⊥: ω₁ is constant and (ω₂, ω₃) turns at λ = (I⊥ − I₁) ω₁ / I⊥ (Landau &
    Lifshitz §33). With I₁ = 1e-6 in float32, ω₁ drifted by 1e-3 over 10 s before."""
    i1, w0 = 1e-6, np.array([0.3, -0.8, 0.5])
    moments = jnp.array([i1, 1.0, 1.0], jnp.float32)
    dt, steps = 0.01, 1000
    _, omegas = jq.simulate_rigid_body(
        jnp.array([1.0, 0.0, 0.0, 0.0], jnp.float32),
        jnp.asarray(w0, jnp.float32),
        moments,
        dt,
        steps,
    )
    t = dt * np.arange(steps + 1)
    lam = (1.0 - i1) * w0[0]
    c, s = np.cos(lam * t), np.sin(lam * t)
    want = np.stack([np.full_like(t, w0[0]), w0[1] * c + w0[2] * s, w0[2] * c - w0[1] * s], -1)
    np.testing.assert_allclose(np.asarray(omegas[:, 0]), w0[0], rtol=0, atol=1e-7)
    np.testing.assert_allclose(np.asarray(omegas, np.float64), want, rtol=0, atol=2e-5)


@pytest.mark.parametrize(
    "points",
    [
        [[0.0, 0.0, 0.0], [1.0, 0.0, 0.0]],  # a dumbbell
        [[1.0, 2.0, 3.0]],  # one point
        [[0.0, 0.0, 0.0], [1.0, 1.0, 1.0], [3.0, 3.0, 3.0]],  # three on a line
    ],
)
def test_deformable_body_on_one_line_raises(points):
    """Collinear (or single) point masses have a singular inertia about the centre of mass: the spin
    about the line is undetermined, and every state after the first was NaN."""
    points = jnp.asarray(points)
    with pytest.raises(ValueError, match=r"`positions\(t0\)`.*(on one line|single point)"):
        jq.simulate_deformable_body(
            jnp.ones(points.shape[0]), lambda t: points + 0.0 * t, jnp.array([1.0, 0, 0, 0]), 0.1, 2
        )


def test_deformable_body_positions_may_return_a_nested_list():
    """A list is an array everywhere else (it was an AttributeError in the shape check)."""
    triangle = [[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [0.0, 2.0, 0.0]]
    momentum = jnp.array([0.1, 0.2, 0.3])
    args = (jnp.array([1.0, 2.0, 3.0]),)
    q_list, _ = jq.simulate_deformable_body(
        *args, lambda t: triangle, jnp.array([1.0, 0, 0, 0]), 0.1, 5, angular_momentum=momentum
    )
    q_array, _ = jq.simulate_deformable_body(
        *args,
        lambda t: jnp.asarray(triangle),
        jnp.array([1.0, 0, 0, 0]),
        0.1,
        5,
        angular_momentum=momentum,
    )
    np.testing.assert_array_equal(np.asarray(q_list), np.asarray(q_array))
    with pytest.raises(
        ValueError, match=r"`positions\(t\)` must return an array of shape \(n, 3\)"
    ):
        jq.simulate_deformable_body(*args, lambda t: "abc", jnp.array([1.0, 0, 0, 0]), 0.1, 5)
