"""Regression tests for input handling of the core API (algebra, rotations, geometry, kinematics).

NaN input must come out NaN (never hidden as 0 / identity / finite angles), bad Python arguments raise
a `ValueError` naming the argument, batch mismatches name the user's arguments, and empty means raise.
"""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jaxquat as jq
from jaxquat import _numerics as nx

NAN = float("nan")
Q = jnp.array([0.5, 0.5, 0.5, 0.5])
ID = jnp.array([1.0, 0.0, 0.0, 0.0])
V = jnp.array([0.1, 0.2, 0.3])
ZERO3 = jnp.zeros(3)
SEQS = ("xyz", "zyx", "XYZ", "zxz", "ZXZ", "XYX")


def _outputs(out):
    return [np.asarray(x) for x in (out if isinstance(out, tuple) else (out,))]


# --- 1. NaN in, NaN out ---------------------------------------------------------------------------

# One-quaternion functions whose every output component depends on every input component.
QUAT_FUNCS = {
    "norm": jq.norm,
    "normalize": jq.normalize,
    "inverse": jq.inverse,
    "exp": jq.exp,
    "log": jq.log,
    "to_rotvec": jq.to_rotvec,
    "to_matrix": jq.to_matrix,
    "to_axis_angle": jq.to_axis_angle,
    **{f"to_euler_{seq}": (lambda q, seq=seq: jq.to_euler(q, seq)) for seq in SEQS},
    "angle_between(q, .)": lambda q: jq.angle_between(q, Q),
    "angle_between(., q)": lambda q: jq.angle_between(Q, q),
    "slerp(q, .)": lambda q: jq.slerp(q, Q, 0.3),
    "slerp(., q)": lambda q: jq.slerp(Q, q, 0.3),
    "mean": lambda q: jq.mean(jnp.stack([Q, q])),
    "step": lambda q: jq.step(q, V, 0.1),
    "angular_velocity": lambda q: jq.angular_velocity(jnp.stack([Q, q]), 0.1),
    "rotate(., q)": lambda q: jq.rotate(V, q),
}

# Functions that act component-wise: a NaN component must give a NaN somewhere in the output.
ELEMENTWISE_QUAT_FUNCS = {
    "conjugate": jq.conjugate,
    "from_xyzw": jq.from_xyzw,
    "to_xyzw": jq.to_xyzw,
    "canonicalize": jq.canonicalize,
    "multiply(q, .)": lambda q: jq.multiply(q, Q),
    "multiply(., q)": lambda q: jq.multiply(Q, q),
    "dot": lambda q: jq.dot(q, Q),
    "rate": lambda q: jq.rate(q, V),
    "corrected_rate": lambda q: jq.corrected_rate(q, V, 0.1),
}

VEC_FUNCS = {
    "from_rotvec": jq.from_rotvec,
    "from_axis_angle(axis)": lambda v: jq.from_axis_angle(v, 0.3),
    **{f"from_euler_{seq}": (lambda v, seq=seq: jq.from_euler(seq, v)) for seq in SEQS},
    "from_two_vectors(a, .)": lambda v: jq.from_two_vectors(v, V),
    "from_two_vectors(., b)": lambda v: jq.from_two_vectors(jnp.array([1.0, 0.0, 0.0]), v),
    "step(omega)": lambda v: jq.step(Q, v, 0.1),
    "corrected_rate(omega)": lambda v: jq.corrected_rate(Q, v, 0.1),
    "rate(omega)": lambda v: jq.rate(Q, v),
    "rotate(v)": lambda v: jq.rotate(v, Q),
    "rotate(center)": lambda v: jq.rotate(V, Q, v),
    "from_vector": jq.from_vector,
}


@pytest.mark.parametrize("base", [Q, ID, -ID], ids=["generic", "identity", "minus_identity"])
@pytest.mark.parametrize("index", range(4))
@pytest.mark.parametrize("name", sorted(QUAT_FUNCS))
def test_nan_quaternion_gives_all_nan(name, index, base):
    q = base.at[index].set(NAN)
    for out in _outputs(QUAT_FUNCS[name](q)):
        assert np.all(np.isnan(out)), f"{name}({q}) = {out}: NaN input was hidden"


@pytest.mark.parametrize("base", [Q, ID], ids=["generic", "identity"])
@pytest.mark.parametrize("index", range(4))
@pytest.mark.parametrize("name", sorted(ELEMENTWISE_QUAT_FUNCS))
def test_nan_quaternion_gives_nan_elementwise(name, index, base):
    q = base.at[index].set(NAN)
    out = np.asarray(ELEMENTWISE_QUAT_FUNCS[name](q))
    assert np.any(np.isnan(out)), f"{name}({q}) = {out}: NaN input was hidden"


@pytest.mark.parametrize("base", [V, ZERO3], ids=["generic", "zero"])
@pytest.mark.parametrize("index", range(3))
@pytest.mark.parametrize("name", sorted(VEC_FUNCS))
def test_nan_vector_gives_nan(name, index, base):
    v = base.at[index].set(NAN)
    out = np.asarray(VEC_FUNCS[name](v))
    assert np.any(np.isnan(out)), f"{name}({v}) = {out}: NaN input was hidden"


def test_nan_vector_part_gives_nan():
    assert np.all(np.isnan(jq.vector_part(ID.at[2].set(NAN))[1]))


@pytest.mark.parametrize("axis", [ZERO3, V], ids=["zero_axis", "axis"])
def test_from_axis_angle_nan_angle(axis):
    assert np.all(np.isnan(jq.from_axis_angle(axis, NAN)))
    assert np.all(np.isnan(jax.jit(jq.from_axis_angle)(axis, NAN)))


def test_from_axis_angle_nan_axis_is_all_nan():
    assert np.all(np.isnan(jq.from_axis_angle(ZERO3.at[1].set(NAN), 0.3)))
    assert np.all(np.isnan(jq.from_axis_angle(V.at[1].set(NAN), 0.3)))


@pytest.mark.parametrize("value", [np.inf, -np.inf])
def test_from_axis_angle_infinite_axis_is_all_nan(value):
    """An infinite axis has no direction: (inf, 0, 0) gave a finite w and a NaN x, which reads as a
    quaternion; now NaN throughout, as `from_rotvec` and `to_axis_angle` give for infinities."""
    for axis in (ZERO3.at[0].set(value), V.at[2].set(value)):
        assert np.all(np.isnan(jq.from_axis_angle(axis, 0.5)))
        assert np.all(np.isnan(jax.jit(jq.from_axis_angle)(axis, 0.5)))
    assert np.all(np.isnan(jq.from_rotvec(ZERO3.at[0].set(value))))


def test_from_axis_angle_zero_axis_still_identity():
    np.testing.assert_array_equal(jq.from_axis_angle(ZERO3, 1.3), ID)
    np.testing.assert_array_equal(
        jq.from_axis_angle(jnp.zeros((2, 3)), jnp.ones(2)), jnp.tile(ID, (2, 1))
    )


def test_nan_scalar_arguments():
    assert np.all(np.isnan(jq.slerp(Q, Q, NAN)))
    assert np.all(np.isnan(jq.step(Q, ZERO3, NAN)))
    assert np.all(np.isnan(jq.corrected_rate(Q, ZERO3, NAN)))
    assert np.all(np.isnan(jq.angular_velocity(jnp.stack([Q, Q]), NAN)))


def test_safe_norm_and_atan2_propagate_nan_keep_zero_gradient():
    assert np.isnan(nx.safe_norm(jnp.array([NAN, 0.0, 0.0])))
    assert np.isnan(nx.safe_atan2(jnp.asarray(NAN), jnp.asarray(0.0)))
    assert np.isnan(nx.safe_atan2(jnp.asarray(0.0), jnp.asarray(NAN)))
    assert float(nx.safe_norm(jnp.zeros(3))) == 0.0
    assert float(nx.safe_atan2(jnp.asarray(0.0), jnp.asarray(0.0))) == 0.0
    np.testing.assert_array_equal(jax.grad(nx.safe_norm)(jnp.zeros(3)), np.zeros(3))
    np.testing.assert_array_equal(jax.grad(jq.norm)(jnp.zeros(4)), np.zeros(4))
    gy, gx = jax.grad(nx.safe_atan2, argnums=(0, 1))(0.0, 0.0)
    assert float(gy) == 0.0 and float(gx) == 0.0


def test_gradients_at_identity_and_zero_stay_finite():
    jac_axis, jac_angle = jax.jacrev(jq.from_axis_angle, argnums=(0, 1))(ZERO3, 0.3)
    np.testing.assert_array_equal(jac_axis, np.zeros((4, 3)))
    np.testing.assert_array_equal(jac_angle, np.zeros(4))
    for seq in SEQS:
        jac = jax.jacrev(lambda q, seq=seq: jq.to_euler(q, seq))(ID)
        assert np.all(np.isfinite(jac)), seq
    jac = jax.jacrev(lambda q: jnp.concatenate([x.ravel() for x in jq.to_axis_angle(q)]))(ID)
    assert np.all(np.isfinite(jac))
    axis, angle = jq.to_axis_angle(ID)
    np.testing.assert_array_equal(axis, [1.0, 0.0, 0.0])
    assert float(angle) == 0.0


# --- 2. bad Python arguments ----------------------------------------------------------------------


@pytest.mark.parametrize("shape", [-1, 2.5, (2, -1), (2.0,), "ab", None, True, (True, 2)])
def test_identity_bad_shape(shape):
    with pytest.raises(ValueError, match="`shape` must be a non-negative int"):
        jq.identity(shape)


@pytest.mark.parametrize("shape", [-1, 2.5, (2, -1), None, True])
def test_random_bad_shape(key, shape):
    with pytest.raises(ValueError, match="`shape` must be a non-negative int"):
        jq.random(key, shape)


@pytest.mark.parametrize(
    "bad, message",
    [
        (42, "got 42"),
        ("abc", "got 'abc'"),
        (None, "got None"),
        (np.zeros(2), r"got shape \(2,\), dtype float64"),
        (np.zeros(3, np.uint32), r"got shape \(3,\), dtype uint32"),
    ],
)
def test_random_bad_key(bad, message):
    """JAX's own errors here were TypeErrors about "key data"."""
    with pytest.raises(ValueError, match=r"`key` must be a jax.random key .*" + message):
        jq.random(bad, 2)


def test_random_batch_of_keys_and_legacy_keys():
    for keys in [
        jax.random.split(jax.random.key(0), 3),
        jax.random.split(jax.random.PRNGKey(0), 3),
    ]:
        with pytest.raises(
            ValueError, match=r"`key` must be one key; got a batch of keys \(shape \(3,.*jax.vmap"
        ):
            jq.random(keys, 2)
        assert jax.vmap(lambda k: jq.random(k, 2))(keys).shape == (3, 2, 4)
    # Legacy uint32 key data (as a NumPy array too) draws what its typed key draws.
    legacy = jax.random.PRNGKey(7)
    want = np.asarray(jq.random(jax.random.wrap_key_data(legacy), 5))
    np.testing.assert_array_equal(jq.random(legacy, 5), want)
    np.testing.assert_array_equal(jq.random(np.asarray(legacy), 5), want)
    np.testing.assert_array_equal(
        jax.jit(lambda k: jq.random(k, 5))(legacy),
        jax.jit(lambda k: jq.random(k, 5))(jax.random.wrap_key_data(legacy)),
    )


@pytest.mark.parametrize("dtype", ["foo", jnp.int32, np.int64, bool, 3])
def test_identity_and_random_bad_dtype(key, dtype):
    with pytest.raises(ValueError, match="`dtype` must be a float dtype"):
        jq.identity(2, dtype)
    with pytest.raises(ValueError, match="`dtype` must be a float dtype"):
        jq.random(key, 2, dtype)


def test_identity_and_random_good_arguments(key):
    assert jq.identity(np.int64(2)).shape == (2, 4)
    assert jq.identity([2, 3], jnp.float32).dtype == jnp.float32
    assert jq.identity(0).shape == (0, 4)
    assert jq.identity().shape == (4,)
    assert jq.random(key, (np.int32(3),), "float32").shape == (3, 4)


@pytest.mark.parametrize("bad", [[[1.0, 2.0], [3.0]], None, [1.0, None], "abc"])
def test_as_float_array_bad_input_names_argument(bad):
    with pytest.raises(ValueError, match="`thing` must be an array of numbers"):
        nx.as_float_array(bad, "thing")


def test_public_functions_reject_ragged_and_none():
    with pytest.raises(ValueError, match="`q` must be an array of numbers"):
        jq.normalize([[1.0, 0.0, 0.0, 0.0], [1.0]])
    with pytest.raises(ValueError, match="`angle` must be an array of numbers"):
        jq.from_axis_angle([0.0, 0.0, 1.0], None)
    with pytest.raises(ValueError, match="`t` must be an array of numbers"):
        jq.slerp(Q, Q, None)


# --- 3. batch mismatches name the user's arguments ------------------------------------------------

Q2, Q3 = jnp.tile(Q, (2, 1)), jnp.tile(Q, (3, 1))
V2, V3 = jnp.tile(V, (2, 1)), jnp.tile(V, (3, 1))


@pytest.mark.parametrize(
    "call, names",
    [
        (lambda: jq.from_axis_angle(V2, jnp.ones(3)), ("axis", "angle")),
        (lambda: jq.from_two_vectors(V2, V3), ("a", "b")),
        (lambda: jq.angle_between(Q2, Q3), ("p", "q")),
        (lambda: jq.slerp(Q2, Q2, jnp.ones(3)), ("p", "q", "t")),
        (lambda: jq.squad(Q2, Q3, Q2, Q2, 0.5), ("p", "a", "b", "q", "t")),
        (lambda: jq.squad_control_points(Q2, Q2, Q3), ("previous", "current", "following")),
        (lambda: jq.rate(Q2, V3), ("q", "omega")),
    ],
)
def test_broadcast_mismatch_names_arguments(call, names):
    with pytest.raises(ValueError, match="do not broadcast") as info:
        call()
    for name in names:
        assert f"`{name}` has shape" in str(info.value), str(info.value)


def test_rate_still_broadcasts():
    assert jq.rate(Q2, V).shape == (2, 4)
    assert jq.rate(Q, V3).shape == (3, 4)


# --- 4. empty mean --------------------------------------------------------------------------------


@pytest.mark.parametrize(
    "shape, axis", [((0, 4), None), ((2, 0, 4), 1), ((2, 0, 4), None), ((0, 2, 4), (0,))]
)
def test_mean_of_nothing_raises(shape, axis):
    with pytest.raises(ValueError, match="at least one quaternion"):
        jq.mean(jnp.zeros(shape), axis=axis)
    with pytest.raises(ValueError, match="at least one quaternion"):
        jax.jit(lambda q: jq.mean(q, axis=axis))(jnp.zeros(shape))


def test_mean_empty_kept_axis_is_fine():
    assert jq.mean(jnp.ones((0, 2, 4)), axis=1).shape == (0, 4)
    np.testing.assert_allclose(jq.mean(Q), Q, atol=1e-12)


# --- 5. callables with the wrong number of arguments ---------------------------------------------

_I = jnp.array([1.0, 0.0, 0.0, 0.0])
_INERTIA = jnp.array([1.0, 2.0, 3.0])


@pytest.mark.parametrize(
    "call, message",
    [
        (
            lambda: jq.integrate(_I, lambda t: jnp.ones(3), 0.1, 2, method="magnus8"),
            r"`omega` must be callable as omega\(t, q\) \(2 positional arguments\); its signature is \(t\)",
        ),
        (
            lambda: jq.kinematic_vector_field(lambda t: jnp.ones(3)),
            r"`omega` must be callable as omega\(t, q\) or omega\(t, q, args\)",
        ),
        (
            lambda: jq.simulate_ensemble(_I[None], lambda t: jnp.ones(3), 0.1, 2),
            r"`omega` must be callable as omega\(t, q\)",
        ),
        (
            lambda: jq.simulate_ensemble(
                _I[None], jnp.ones((1, 3)), 0.1, 2, inertia=_INERTIA, torque=lambda t, q: 0.0
            ),
            r"`torque` must be callable as torque\(t, q, omega\) \(3 positional arguments\)",
        ),
        (
            lambda: jq.simulate_rigid_body(
                _I, jnp.ones(3), _INERTIA, 0.1, 2, torque=lambda t, q: 0.0
            ),
            r"`torque` must be callable as torque\(t, q, omega\)",
        ),
        (
            lambda: jq.rigid_body_vector_field(_INERTIA, torque=lambda t: 0.0),
            r"`torque` must be callable as torque\(t, q, omega\)",
        ),
        (
            lambda: jq.simulate_deformable_body(jnp.ones(2), lambda: jnp.zeros((2, 3)), _I, 0.1, 2),
            r"`positions` must be callable as positions\(t\) \(1 positional argument\); its signature is \(\)",
        ),
    ],
)
def test_callables_of_the_wrong_arity_name_the_argument(call, message):
    """A user function that cannot take the documented arguments is a ValueError naming it, at the
    call, not a TypeError from inside the trace."""
    with pytest.raises(ValueError, match=message):
        call()


@pytest.mark.parametrize(
    "omega",
    [
        lambda t, q: jnp.ones(3),
        lambda t, q=None: jnp.ones(3),
        lambda *args: jnp.ones(3),
        lambda t, q, extra=1.0, **kw: jnp.ones(3),
        jq.sampled(jnp.ones((3, 3)), 0.1),
    ],
)
def test_callables_that_accept_the_arguments_pass(omega):
    np.testing.assert_allclose(
        jq.integrate(_I, omega, 0.1, 2, save="final"),
        jq.integrate(_I, jnp.ones(3), 0.1, 2, save="final"),
        atol=1e-6,
    )


@pytest.mark.parametrize("method", ["euler", "magnus4", "cf4"])
def test_omega_returning_a_list_is_an_array_and_a_string_is_an_error(method):
    """What the diffrax fields accept, integrate accepts: a list from omega(t, q) is an array (it was
    refused as "shape ()"); a non-numeric result is a ValueError naming omega(t, q), not JAX's
    TypeError from inside the trace."""
    want = jq.integrate(_I, jnp.array([0.0, 0.0, 1.0]), 0.1, 5, save="final", method=method)
    got = jq.integrate(_I, lambda t, q: [0.0, 0.0, 1.0], 0.1, 5, save="final", method=method)
    np.testing.assert_allclose(got, want, atol=1e-15)
    with pytest.raises(ValueError, match=r"`omega\(t, q\)` must be an array of numbers; got str"):
        jq.integrate(_I, lambda t, q: "abc", 0.1, 5, method=method)


def test_public_names_are_listed_and_documented():
    """`jaxquat.__all__` lists the public API (helper-52 found none); each name has a docstring
    and `from jaxquat import *` brings exactly these."""
    names = {n for n in dir(jq) if not n.startswith("_")}
    assert jq.__all__ == sorted(names)
    assert {"integrate", "rotate", "corrected_vector_field", "simulate_deformable_body"} <= names
    namespace: dict = {}
    exec("from jaxquat import *", namespace)
    assert {n for n in namespace if not n.startswith("_")} == names
    assert [n for n in jq.__all__ if not (getattr(jq, n).__doc__ or "").strip()] == []
