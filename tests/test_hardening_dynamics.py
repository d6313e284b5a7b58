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


def test_step_counts_of_any_integer_kind():
    """`integrate` took a NumPy or concrete JAX integer as `num_steps`; `simulate_rigid_body` and
    `simulate_deformable_body` checked it but kept the value as given, which their compiled run then
    traced (a raw TracerBoolConversionError for `np.int64(5)`), and `simulate_ensemble` (and the
    fit's `substeps`) refused a JAX integer. The same results as a Python int; bools, floats and
    traced counts are still ValueErrors naming the argument."""
    q0, omega, moments = jq.identity(), jnp.array([0.3, -0.2, 0.9]), jnp.array([1.0, 2.0, 3.0])
    masses = jnp.array([1.0, 2.0, 1.5])

    def shape(t):
        base = jnp.array([[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]])
        return base * (1.0 + 0.1 * jnp.sin(t))

    runs = {
        "rigid": lambda n: jq.simulate_rigid_body(q0, omega, moments, 0.1, n, save_every=n)[0],
        "deformable": lambda n: jq.simulate_deformable_body(
            masses, shape, q0, 0.1, n, save_every=n
        )[0],
        "ensemble": lambda n: jq.simulate_ensemble(q0, omega, 0.1, n, save_every=n).saved,
        "integrate": lambda n: jq.integrate(q0, omega, 0.1, n, save_every=n),
    }
    for name, run in runs.items():
        expected = np.asarray(run(5))
        assert expected.shape[0] == 2, name
        for count in (np.int64(5), np.int32(5), jnp.int32(5), jnp.asarray(5)):
            np.testing.assert_array_equal(run(count), expected, err_msg=f"{name} {count!r}")
        for bad in (True, 5.0, jnp.asarray(True), jnp.ones(2, int)):
            with pytest.raises(ValueError, match="num_steps"):
                run(bad)
    times = jnp.linspace(0.0, 1.0, 6)
    observed = jq.integrate(q0, omega, 0.2, 5)
    fit = jq.fit_angular_velocity(times, observed, substeps=jnp.int32(2))
    np.testing.assert_allclose(fit.omega, omega, atol=1e-9)
    with pytest.raises(ValueError, match="substeps"):
        jq.fit_angular_velocity(times, observed, substeps=True)


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


# --------------------------------------------------------------------------------------------------
# Step times that the time dtype cannot tell apart


def _time_callables():
    """The four entry points that call a function of time, each as run(q0, t0, dt, shift) with the
    function of time written in the time τ = t − shift; one-stage methods, whose only times are the
    step times (a stage at t + c·dt is rounded to the spacing too)."""

    def omega(shift):
        return lambda t, q: jnp.stack([0.5 + 0.01 * (t - shift), 0.2 + 0 * t, 0 * t]).astype(
            q.dtype
        )

    def torque(shift):
        return lambda t, q, w: jnp.stack([0.1 * (t - shift), 0 * t, 0 * t]).astype(q.dtype)

    def positions(shift):
        return lambda t: jnp.diag(jnp.stack([1.0 + 0.01 * (t - shift), 1.5 + 0 * t, 2.0 + 0 * t]))

    return {
        "integrate": lambda q0, t0, dt, s: jq.integrate(q0, omega(s), dt, 4, t0=t0, save="final"),
        "simulate_rigid_body": lambda q0, t0, dt, s: jq.simulate_rigid_body(
            q0,
            OMEGA.astype(q0.dtype),
            MOMENTS.astype(q0.dtype),
            dt,
            4,
            torque=torque(s),
            t0=t0,
            method="euler",
        )[0][-1],
        "simulate_deformable_body": lambda q0, t0, dt, s: jq.simulate_deformable_body(
            jnp.ones(3, q0.dtype), positions(s), q0, dt, 4, t0=t0, method="euler"
        )[-1],
        "simulate_ensemble": lambda q0, t0, dt, s: jq.simulate_ensemble(
            q0[None], omega(s), dt=dt, num_steps=4, t0=t0
        ).final[0],
    }


@pytest.mark.parametrize("name", list(_time_callables()))
@pytest.mark.parametrize("dtype", ["float32", "float64"])
def test_step_times_the_dtype_cannot_tell_apart_are_an_error(name, dtype):
    """t0 + k·dt in the run's time dtype: where its spacing exceeds half a step, consecutive step
    times can coincide and the function of time stands still (float32 at a Unix time, 1.7e9, is
    128 s apart; at 1e20 even float64 never moves). Those are a `ValueError`, blaming the origin or
    the run's length; at the boundary (spacing = dt with every step time exact, also a run ending
    exactly on 2ⁿ where the spacing doubles) the run equals the same run counted from t0 = 0, bit
    for bit."""
    run = _time_callables()[name]
    q0 = Q0.astype(dtype)
    # simulate_ensemble forms its times in float64 when x64 is on (this suite): float64 cases only.
    time_dtype = "float64" if name == "simulate_ensemble" else dtype
    exponent = np.finfo(time_dtype).nmant + 1  # spacing above 2**exponent is 2: more than dt = 1
    t0, dt = np.asarray(2.0**exponent, time_dtype), np.asarray(1.0, time_dtype)
    with pytest.raises(ValueError, match=rf"`t0` = .* {time_dtype} times near \|t0\| are 2 apart"):
        run(q0, t0, dt, t0)
    with pytest.raises(ValueError, match="smaller .t0."):
        jax.jit(lambda: run(q0, 1e20, 0.01, 0.0))()
    zero = np.zeros_like(t0)
    for t0 in (2.0 ** (exponent - 1), 2.0**exponent - 4):  # spacing 1 = dt: every time exact
        t0 = np.asarray(t0, time_dtype)
        np.testing.assert_array_equal(run(q0, t0, dt, t0), run(q0, zero, dt, 0.0))
    # Four steps from 2**exponent − 3 end at 2**exponent + 1, past the boundary: the run's length
    # is to blame, not its origin.
    with pytest.raises(ValueError, match=r"reach \|t\| = .* Split the run into shorter runs"):
        t0 = np.asarray(2.0**exponent - 3, time_dtype)
        run(q0, t0, dt, t0)
    run(q0, 0.0, 0.0, 0.0)  # dt = 0: time stands still by request


def test_step_times_matter_only_for_functions_of_time():
    """A constant ω or samples (looked up by the time since their own t0) never see t0 + k·dt, nor
    does a callable whose output does not depend on t (a damping torque, an ω(q), positions that
    do not change), wrapped in jax.jit, eqx.filter_jit, checkpoint or cond or not, in any float
    dtype (bfloat16 included), and `num_steps = 0` has no step times to tell apart."""
    import equinox as eqx

    final = jq.integrate(Q0, OMEGA, 0.01, 5, t0=1e20, save="final")
    np.testing.assert_allclose(final, jq.integrate(Q0, OMEGA, 0.01, 5, save="final"), atol=0)
    samples = jq.sampled(jnp.tile(OMEGA, (5, 1)), 0.01, t0=1e20)
    final = jq.integrate(Q0, samples, 0.01, 5, t0=1e20, save="final")
    np.testing.assert_allclose(final, jq.integrate(Q0, OMEGA, 0.01, 5, save="final"), atol=0)

    def omega_of_q(t, q):  # reads t only for its dtype and shape
        return jnp.zeros_like(t) + 0.5 * q[..., 1:]

    args = (Q0, omega_of_q, 0.01, 5)
    np.testing.assert_array_equal(
        jq.integrate(*args, t0=1e20, method="rk4"), jq.integrate(*args, method="rk4")
    )
    ensemble = jq.simulate_ensemble(Q0[None], omega_of_q, dt=0.01, num_steps=5, t0=1e20)
    np.testing.assert_array_equal(ensemble.final[0], jq.integrate(*args, save="final"))

    class Damping(eqx.Module):  # a torque as a Module, as a neural network would be
        c: jax.Array

        def __call__(self, t, q, w):
            return -self.c * w

    def damping(t, q, w):
        return -0.1 * w

    def branching(t, q, w):
        return jax.lax.cond(jnp.all(w > 0), damping, lambda *a: 2 * damping(*a), t, q, w)

    @jax.custom_jvp
    def smooth(t, q, w):  # custom derivatives: the primal is what runs
        return -0.1 * w

    smooth.defjvp(lambda primals, tangents: (smooth(*primals), -0.1 * tangents[2]))

    def looped(t, q, w):  # t carried through a while loop, never into the torque
        state = (0, -0.1 * w, t)
        return jax.lax.while_loop(lambda c: c[0] < 2, lambda c: (c[0] + 1, c[1], c[2]), state)[1]

    torques = {
        "plain": damping,
        "custom_jvp": smooth,
        "while_loop": looped,
        "jit": jax.jit(damping),
        "filter_jit Module": eqx.filter_jit(Damping(jnp.array(0.1))),
        "checkpoint": jax.checkpoint(damping),
        "cond": branching,
    }
    # float16 times past 32 are 0.03 apart, more than dt = 0.01 (bfloat16 past 2: 0.016): harmless
    # for a torque that does not read t. (A float16 rigid body with a jitted damping torque over
    # 3,000 steps is what a first version of this check refused.)
    for dtype in (jnp.float16, jnp.bfloat16):
        q, w, i = (x.astype(dtype) for x in (Q0, OMEGA, MOMENTS))
        for name, torque in torques.items():
            qs, _ = jq.simulate_rigid_body(q, w, i, 0.01, 3_000, torque=torque, save="final")
            assert qs.dtype == dtype and bool(jnp.isfinite(qs.astype(float)).all()), name
            jq.simulate_rigid_body(q, w, i, 0.01, 4, torque=torque, t0=40.0)
    for name, torque in torques.items():
        ensemble = jq.simulate_ensemble(
            Q0[None], OMEGA, dt=0.01, num_steps=5, t0=1e20, inertia=MOMENTS, torque=torque
        )
        expected = jq.simulate_rigid_body(Q0, OMEGA, MOMENTS, 0.01, 5, torque=torque, save="final")
        np.testing.assert_allclose(ensemble.final[0], expected[0], atol=1e-15, err_msg=name)

    still = jnp.diag(jnp.array([1.0, 1.5, 2.0]))
    for positions in (lambda t: still, jax.jit(lambda t: still)):
        qs, _ = jq.simulate_deformable_body(
            jnp.ones(3), positions, Q0, 0.01, 5, t0=1e20, angular_momentum=jnp.array([0, 0, 1.0])
        )
        expected, _ = jq.simulate_deformable_body(
            jnp.ones(3), positions, Q0, 0.01, 5, angular_momentum=jnp.array([0, 0, 1.0])
        )
        np.testing.assert_array_equal(qs, expected)

    def omega_of_t(t, q):
        return jnp.stack([0.5 + 0.01 * t, 0.2 + 0 * t, 0 * t])

    final = jq.integrate(Q0, omega_of_t, 0.01, 0, t0=1e20, save="final")  # no steps: q0
    np.testing.assert_array_equal(final, Q0)
    # A callable of the wrong arity is named as such, not tripped over by the time check.
    with pytest.raises(ValueError, match=r"`omega` must be callable as omega\(t, q\)"):
        jq.integrate(Q0, lambda t: OMEGA, 0.01, 5, t0=1e20)


def _step_times(t0, dt, num_steps, dtype, half_steps=False):
    """The step times t0 + float(k)·dt as the runs form them, each operation rounded to `dtype`
    (NumPy computes float16 and bfloat16 in float32 and rounds once more, which is exact for a sum
    or a product of two such numbers); with `half_steps`, interleaved with the stage times
    t_k + ½dt of midpoint, rk4 and cf4."""
    dtype = jnp.dtype(dtype)
    k = np.arange(num_steps + 1).astype(dtype)
    times = np.asarray(t0, dtype) + k * np.asarray(dt, dtype)
    if not half_steps:
        return times
    halves = times[:-1] + np.asarray(0.5, dtype) * np.asarray(dt, dtype)
    return np.stack([times[:-1], halves], -1).reshape(-1)


@pytest.mark.parametrize("method", ["euler", "midpoint"])
@pytest.mark.parametrize("dtype", ["float16", "bfloat16", "float32"])
def test_step_times_the_check_accepts_increase(dtype, method):
    """Against the arithmetic itself: for runs around the boundary (the spacing of the run's largest
    |t| from a sixteenth of a step to four steps; origins at zero, on and off the grid of the step, half a step
    off it; runs crossing zero), every run the check accepts has strictly increasing times as the
    dtype forms them: the step times for a one-stage method, and the half steps between them too
    for midpoint (and rk4 and cf4). Of the runs it refuses, a good share do have two equal times
    (the rest step unevenly, by one spacing or two), among them a step of exactly the spacing from
    an origin half a spacing off its grid (ties round to even). From t0 = 0 a one-stage method's
    times are one rounding of k·dt: a spacing up to just under a step is accepted."""
    from jaxquat._integrate import check_times_advance

    def check(t0, dt, num_steps):
        check_times_advance(t0, dt, num_steps, dtype, "`f(t)`", lambda t: True, "", method)

    rng = np.random.default_rng(5)
    eps = float(jnp.finfo(dtype).eps)
    accepted = refused = stalled = 0
    for _ in range(400):
        dt = float(np.asarray(2.0 ** rng.uniform(-8, 2) * rng.choice([1, -1]), dtype))
        scale = abs(dt) / eps * 2.0 ** rng.uniform(-4, 2)  # where the spacing is dt/16 .. 4 dt
        t0 = float(rng.uniform(-1, 1) * scale)
        num_steps = int(rng.integers(1, min(4000, 2 * scale / abs(dt)) + 2))
        origin = rng.random()
        if origin < 0.2:
            t0 = 0.0
        elif origin < 0.5:
            t0 = round(t0 / dt) * dt + (dt / 2 if rng.random() < 0.5 else 0.0)
        t0 = float(np.asarray(t0, dtype))
        times = _step_times(t0, dt, num_steps, dtype, method == "midpoint").astype(np.float64)
        if not np.all(np.isfinite(times)):
            continue
        increasing = bool(np.all(np.diff(times) * np.sign(dt) > 0))
        try:
            check(t0, dt, num_steps)
        except ValueError:
            refused += 1
            stalled += not increasing
        else:
            accepted += 1
            assert increasing, (t0, dt, num_steps)
    assert accepted > 60 and refused > 60 and stalled > refused / 4, (accepted, refused, stalled)
    # The tie: a step equal to the spacing, from an origin half a step off the grid.
    times = _step_times(0.5, 1.0, 2 ** (jnp.finfo(dtype).nmant + 1) + 3, dtype)
    assert np.any(np.diff(times.astype(np.float64)) == 0)
    with pytest.raises(ValueError, match="Split the run"):
        check(0.5, 1.0, times.size - 1)
    if method == "euler":  # exact times, whose spacing reaches the step
        check(0.0, 1.0, times.size - 4)
    # From 0, a spacing between half a step and a step: one rounding, the times increase.
    dt = float(np.asarray(0.75, dtype))
    num_steps = int(2 ** jnp.finfo(dtype).nmant * 1.2)
    times = _step_times(0.0, dt, num_steps, dtype).astype(np.float64)
    assert np.all(np.diff(times) > 0) and np.diff(times).min() < dt / 1.4  # uneven, increasing
    if method == "euler":
        check(0.0, dt, num_steps)
    else:  # the half steps collapse onto the step times
        halves = _step_times(0.0, dt, num_steps, dtype, True).astype(np.float64)
        assert np.any(np.diff(halves) <= 0)
        with pytest.raises(ValueError, match="evaluates at half steps too"):
            check(0.0, dt, num_steps)


def test_step_times_from_zero_one_stage_methods_take_a_coarser_spacing():
    """From t0 = 0 the step times are one rounding of k·dt: float16 times from 0 over 1,200 steps
    of 0.01 reach 12, where the spacing is 0.0078, over half a step, yet they increase (refused by
    an earlier version of the check, although the run had worked). A one-stage method runs; cf4
    calls the torque at half steps too, which collapse onto step times there, and is refused."""
    times = np.float16(0) + np.arange(1201).astype(np.float16) * np.float16(0.01)
    steps = np.diff(times.astype(np.float64))
    assert steps.min() > 0 and steps.max() > 1.5 * steps.min()  # increasing, unevenly
    halves = times[:-1] + np.float16(0.5) * np.float16(0.01)
    assert np.any(halves == times[1:]) or np.any(halves == times[:-1])
    torque = lambda t, q, w: jnp.stack([0.1 * jnp.sin(t), 0 * t, 0 * t]).astype(q.dtype)  # noqa: E731
    q, w, i = (x.astype(jnp.float16) for x in (Q0, OMEGA, MOMENTS))
    qs, _ = jq.simulate_rigid_body(q, w, i, 0.01, 1200, torque=torque, method="euler", save="final")
    assert bool(jnp.isfinite(qs.astype(float)).all())
    with pytest.raises(ValueError, match="method 'cf4' evaluates at half steps too"):
        jq.simulate_rigid_body(q, w, i, 0.01, 1200, torque=torque, save="final")


def test_step_times_that_overflow_are_named():
    """A float16 t0 of 1e6 is infinite in the run's dtype, and so is a run from 0 reaching 1e5:
    both named, with a function of time; the advice for a float32 state names float64."""
    torque = lambda t, q, w: jnp.stack([t, 0 * t, 0 * t]).astype(q.dtype)  # noqa: E731
    q, w, i = (x.astype(jnp.float16) for x in (Q0, OMEGA, MOMENTS))
    with pytest.raises(
        ValueError, match=r"`t0` = 1e\+06 overflows float16 \(largest 65504\).*\|t0\|"
    ):
        jq.simulate_rigid_body(q, w, i, 0.01, 4, torque=torque, t0=1e6)
    with pytest.raises(ValueError, match=r"reach \|t\| = 100000, beyond the largest float16"):
        jq.simulate_rigid_body(q, w, i, 1000.0, 100, torque=torque)
    q, w, i = (x.astype(jnp.float32) for x in (Q0, OMEGA, MOMENTS))
    with pytest.raises(ValueError, match=r"1\.7e\+09.* 128 apart.* or use a float64 state"):
        jq.simulate_rigid_body(q, w, i, 0.01, 4, torque=torque, t0=1.7e9)
    # A float64 state has no wider dtype to advise: each entry point leaves its advice out.
    q0 = Q0.astype(jnp.float64)
    runs = {
        "simulate_rigid_body": lambda: jq.simulate_rigid_body(
            q0, OMEGA, MOMENTS, 0.01, 4, torque=torque, t0=1e20
        ),
        "integrate": lambda: jq.integrate(
            q0, lambda t, q: jnp.stack([t, 0 * t, 0 * t]), 0.01, 4, t0=1e20
        ),
        "simulate_ensemble": lambda: jq.simulate_ensemble(
            q0[None], lambda t, q: jnp.stack([t, 0 * t, 0 * t]), 0.01, 4, t0=1e20
        ),
    }
    for name, run in runs.items():
        with pytest.raises(ValueError, match="apart") as raised:
            run()
        message = str(raised.value)
        assert "float64 times near |t0| are" in message, name
        assert "use a float64" not in message and "in float64" not in message, name
        assert "x64" not in message, name
