"""A registry of the public functions of algebra / rotation / geometry / kinematics drives the JAX
transformation checks (STYLE.md rule 16, issue 2 acceptance 3 and 4):

- batch shapes `()`, `(1,)`, `(3, 1, 2)` equal a loop over single elements; leading axes broadcast;
- `jit` equals eager (op by op), `vmap` equals a loop;
- float32 in gives float32 out (and agrees with float64);
- `jacfwd` == `jacrev` == central finite differences at random points, exactly at the singular point
  (identity / zero rotation vector / ω = 0), at 1e-12 and 1e-6 from it and near angle π; float64 to
  1e-7 and float32 to 1e-3 relative; every Jacobian at every kind of point is NaN-free under
  `jax_debug_nans`.

Finite differences are always taken in float64 (the float32 Jacobians are compared with them at the
same, float32-representable, points), and all points of one function are batched into one call.
"""

from __future__ import annotations

import dataclasses
import functools
import math
from collections.abc import Callable

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jaxquat as jq

KINDS = ("random", "at", "1e-12", "1e-6", "pi")
ALL_KINDS = KINDS
REGULAR = ("random", "pi")  # functions not differentiable at their singular point
NUM_RANDOM = 4
NEAR_PI = 1e-4  # "near π" means a rotation angle of π − 1e-4 (w = 5e-5 ≫ the FD step)
FD_STEP = 1e-6


# ---------------------------------------------------------------------------------------------------
# Independent NumPy references used to build inputs (not the library's own functions).


def np_multiply(p, q):
    pw, pv = p[..., :1], p[..., 1:]
    qw, qv = q[..., :1], q[..., 1:]
    return np.concatenate(
        [pw * qw - np.sum(pv * qv, -1, keepdims=True), pw * qv + qw * pv + np.cross(pv, qv)], -1
    )


def np_matrix(q):
    w, x, y, z = q / np.linalg.norm(q)
    return np.array(
        [
            [1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
            [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
            [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)],
        ]
    )


def unit_vector(rng):
    v = rng.normal(size=3)
    return v / np.linalg.norm(v)


def quat_at_angle(rng, angle):
    return np.concatenate([[math.cos(angle / 2)], math.sin(angle / 2) * unit_vector(rng)])


def random_quat(rng):
    x = rng.normal(size=4)
    return x / np.linalg.norm(x)


def kind_angle(kind, near_pi=NEAR_PI):
    return {"at": 0.0, "1e-12": 1e-12, "1e-6": 1e-6, "pi": math.pi - near_pi}[kind]


def rotation(rng, kind, near_pi=NEAR_PI):
    """A unit quaternion: Haar-random, or at the given angle from the identity."""
    if kind == "random":
        return random_quat(rng)
    return quat_at_angle(rng, kind_angle(kind, near_pi))


def rotvec(rng, kind, near_pi=NEAR_PI):
    if kind == "random":
        return rng.normal(size=3)
    return kind_angle(kind, near_pi) * unit_vector(rng)


def relative_pair(rng, kind, near_pi=NEAR_PI):
    """(p, q) with p random and q = p ⊗ δ, δ of the given kind (q = p exactly for "at")."""
    p = random_quat(rng)
    if kind == "at":
        return p, p.copy()
    return p, np_multiply(p, rotation(rng, kind, near_pi))


# ---------------------------------------------------------------------------------------------------
# The registry.


@dataclasses.dataclass(frozen=True)
class Entry:
    name: str
    fn: Callable  # positional array arguments -> one array
    sample: Callable  # (rng, kind) -> tuple of float64 numpy arrays (one point, no batch axes)
    grad_kinds: tuple[str, ...] = KINDS  # where jacfwd == jacrev == FD is asserted
    broadcasts: bool = True  # leading axes of different arguments broadcast against each other
    fd_step: float = FD_STEP
    float32_gradients: bool = True  # also check float32 Jacobians (each costs one more compile)

    def __repr__(self):
        return self.name


def _dt(rng):
    return np.asarray(rng.uniform(0.05, 0.5))


def _omega(rng, kind, dt, near_pi=NEAR_PI):
    """Angular velocity with |ω|Δt of the given kind."""
    if kind == "random":
        return rng.normal(size=3)
    return kind_angle(kind, near_pi) * unit_vector(rng) / dt


def _kinematics_sample(rng, kind, near_pi=NEAR_PI):
    dt = _dt(rng)
    return random_quat(rng), _omega(rng, kind, dt, near_pi), dt


def _mean_sample(rng, kind):
    centre = rotation(rng, kind, near_pi=1e-3)
    spread = 0.3 if kind == "random" else 1e-5
    if kind == "at":
        qs = np.stack([centre] * 3)
    else:
        qs = np.stack([np_multiply(centre, quat_at_angle(rng, spread)) for _ in range(3)])
    qs = qs * np.array([1.0, -1.0, 1.0])[:, None]  # the mean is sign-invariant
    return qs, rng.uniform(0.5, 1.5, size=3)


def _two_vectors_sample(rng, kind):
    a = rng.normal(size=3)
    if kind == "random":
        return a, rng.normal(size=3)
    # b = 2.5 · (a rotated by the kind's angle about an axis ⟂ a); near π: nearly antiparallel.
    axis = np.cross(a, unit_vector(rng))
    axis /= np.linalg.norm(axis)
    angle = kind_angle(kind, near_pi=1e-3)
    b = np_matrix(np.concatenate([[math.cos(angle / 2)], math.sin(angle / 2) * axis])) @ a
    return a, 2.5 * b


def _matrix_sample(rng, kind):
    m = np_matrix(rotation(rng, kind))
    if kind == "random":  # slightly non-orthogonal: from_matrix projects (acceptance 6)
        m = m + 1e-3 * rng.normal(size=(3, 3))
    return (m,)


def _euler_angles(rng, kind):
    if kind == "random":
        return rng.uniform(-math.pi, math.pi, size=3)
    if kind == "pi":
        return (math.pi - NEAR_PI) * np.array([1.0, -1.0, 1.0])
    return kind_angle(kind) * unit_vector(rng)


def _squad_sample(rng, kind):
    p, q = relative_pair(rng, kind)
    a = np_multiply(p, quat_at_angle(rng, 0.2))
    b = np_multiply(q, quat_at_angle(rng, 0.2))
    return p, a, b, q, np.asarray(rng.uniform(0.0, 1.0))


def _control_points_sample(rng, kind):
    current = random_quat(rng)
    return (
        np_multiply(current, rotation(rng, kind)),
        current,
        np_multiply(current, rotation(rng, kind)),
    )


def _both_frames(function):
    def fn(*args):
        return jnp.stack([function(*args, frame="world"), function(*args, frame="body")], axis=-2)

    return fn


def _angular_velocity(q0, q1, dt):
    qs = jnp.stack([q0, q1])
    return jnp.stack(
        [
            jq.angular_velocity(qs, dt[None], frame="world")[0],
            jq.angular_velocity(qs, dt[None], frame="body")[0],
        ],
        axis=-2,
    )


def _angular_velocity_sample(rng, kind):
    q0 = random_quat(rng)
    return q0, np_multiply(rotation(rng, kind), q0), _dt(rng)


def _axis_angle(q):
    axis, angle = jq.to_axis_angle(q)
    return jnp.concatenate([axis, angle[..., None]], axis=-1)


def _q(rng, kind):
    return (rotation(rng, kind),)


def _scaled_q(rng, kind):
    return (1.3 * rotation(rng, kind),)


REGISTRY = [
    # Algebra
    Entry("multiply", jq.multiply, lambda rng, kind: (rng.normal(size=4), rotation(rng, kind))),
    Entry("conjugate", jq.conjugate, _scaled_q),
    Entry("inverse", jq.inverse, _scaled_q),
    Entry("norm", jq.norm, _scaled_q),
    Entry("normalize", jq.normalize, _scaled_q),
    Entry("dot", jq.dot, lambda rng, kind: (rng.normal(size=4), rotation(rng, kind))),
    Entry("from_vector", jq.from_vector, lambda rng, kind: (rotvec(rng, kind),)),
    Entry("vector_part", jq.vector_part, _q),
    Entry(
        "exp",
        jq.exp,
        lambda rng, kind: (np.concatenate([[0.3 * rng.normal()], 0.5 * rotvec(rng, kind)]),),
    ),
    Entry("log", jq.log, _scaled_q),
    # Rotations
    Entry(
        "rotate",
        jq.rotate,
        lambda rng, kind: (rng.normal(size=3), 1.3 * rotation(rng, kind), rng.normal(size=3)),
    ),
    Entry(
        "rotate_origin",
        lambda v, q: jq.rotate(v, q),
        lambda rng, kind: (rng.normal(size=3), rotation(rng, kind)),
    ),
    Entry(
        "from_axis_angle",
        jq.from_axis_angle,
        lambda rng, kind: (
            2.0 * rng.normal(size=3),
            np.asarray(rng.normal() if kind == "random" else kind_angle(kind)),
        ),
    ),
    # The axis is undefined at the identity (and its derivative ~ 1/angle near it).
    Entry("to_axis_angle", _axis_angle, _scaled_q, grad_kinds=REGULAR),
    Entry("from_rotvec", jq.from_rotvec, lambda rng, kind: (rotvec(rng, kind),)),
    Entry("to_rotvec", jq.to_rotvec, _scaled_q),
    Entry("to_matrix", jq.to_matrix, _scaled_q),
    Entry("from_matrix", jq.from_matrix, _matrix_sample),
    Entry("from_xyzw", jq.from_xyzw, _q),
    Entry("to_xyzw", jq.to_xyzw, _q),
    Entry(
        "from_euler_xyz",
        functools.partial(jq.from_euler, "xyz"),
        lambda rng, kind: (_euler_angles(rng, kind),),
    ),
    Entry(
        "from_euler_ZXZ",
        functools.partial(jq.from_euler, "ZXZ"),
        lambda rng, kind: (_euler_angles(rng, kind),),
    ),
    Entry("to_euler_xyz", lambda q: jq.to_euler(q, "xyz"), _scaled_q),
    Entry("to_euler_ZYX", lambda q: jq.to_euler(q, "ZYX"), _scaled_q),
    # Proper Euler sequences are in gimbal lock at the identity.
    Entry("to_euler_zxz", lambda q: jq.to_euler(q, "zxz"), _scaled_q, grad_kinds=REGULAR),
    Entry("to_euler_YXY", lambda q: jq.to_euler(q, "YXY"), _scaled_q, grad_kinds=REGULAR),
    # Near antiparallel the derivative grows like 1/|â + b̂| (here 1e3): a smaller FD step.
    Entry("from_two_vectors", jq.from_two_vectors, _two_vectors_sample, fd_step=1e-7),
    # Geometry. angle_between is a cone |δ| at p = q: at 1e-12 / 1e-6 from it finite differences
    # cannot resolve the derivative; test_geometry checks it there against its closed form.
    # Exactly at the apex the central difference of a cone is only O(step) accurate: a small step.
    Entry(
        "angle_between",
        jq.angle_between,
        relative_pair,
        grad_kinds=("random", "at", "pi"),
        fd_step=1e-8,
    ),
    Entry(
        "slerp",
        jq.slerp,
        lambda rng, kind: (*relative_pair(rng, kind), np.asarray(rng.uniform(-0.2, 1.2))),
    ),
    # squad is slerp ∘ slerp, whose float32 Jacobians are checked above; its float64 check alone
    # is the most expensive compile of this file, so float32 is skipped for it (time budget).
    Entry("squad", jq.squad, _squad_sample, float32_gradients=False),
    Entry("squad_control_points", jq.squad_control_points, _control_points_sample),
    Entry(
        "canonicalize",
        jq.canonicalize,
        lambda rng, kind: (rng.choice([-1.0, 1.0]) * rotation(rng, kind),),
    ),
    Entry(
        "mean",
        lambda q, weights: jq.mean(q, weights, axis=-1),
        _mean_sample,
        broadcasts=False,
    ),
    # (atol loose enough for the float32-rounded inputs of the dtype test.)
    Entry("check_unit", functools.partial(jq.check_unit, atol=1e-5), _q),
    # Kinematics: world and body frame in one entry (outputs stacked).
    Entry("rate", _both_frames(jq.rate), lambda rng, kind: _kinematics_sample(rng, kind)[:2]),
    # The tan pole at |ω|Δt = π: "near π" is π − 1e-2 there (derivative ~ 1/(π − θ)², so a smaller
    # FD step).
    Entry(
        "corrected_rate",
        _both_frames(jq.corrected_rate),
        lambda rng, kind: _kinematics_sample(rng, kind, near_pi=1e-2),
        fd_step=1e-8,
    ),
    Entry("step", _both_frames(jq.step), _kinematics_sample),
    Entry(
        "angular_velocity",
        _angular_velocity,
        _angular_velocity_sample,
        broadcasts=False,
    ),
]


# ---------------------------------------------------------------------------------------------------
# Utilities.


def _rng(entry, salt=0):
    return np.random.default_rng([sum(map(ord, entry.name)), len(entry.name), salt])


def _batched_sample(entry, batch, salt=0):
    """Random points stacked to `batch + element shape` for every argument."""
    rng = _rng(entry, salt)
    size = math.prod(batch)
    points = [entry.sample(rng, "random") for _ in range(size)]
    return tuple(
        np.stack([p[i] for p in points]).reshape(batch + np.shape(points[0][i]))
        for i in range(len(points[0]))
    )


def _assert_close(actual, expected, rtol, atol):
    actual = np.asarray(actual, dtype=np.float64)
    expected = np.asarray(expected, dtype=np.float64)
    assert actual.shape == expected.shape, (actual.shape, expected.shape)
    np.testing.assert_allclose(actual, expected, rtol=rtol, atol=atol)


# The checks compile many small programs; XLA's backend optimisations are irrelevant to them and
# cost a third of the compile time.
_FAST_COMPILE = {"xla_backend_optimization_level": 0, "xla_llvm_disable_expensive_passes": True}


def _compiled(fn, *args):
    """`jax.jit(fn)(*args)`, compiled without backend optimisations."""
    return jax.jit(fn).lower(*args).compile(compiler_options=_FAST_COMPILE)(*args)


# ---------------------------------------------------------------------------------------------------
# Batching, broadcasting, jit, vmap, dtype.


def _eager_loop(entry, args):
    """Eager, element by element and op by op (`jax.disable_jit`: the public functions' compilation of
    eager calls, `_numerics.eager_jit`, is off): the reference (points stacked on axis 0)."""
    with jax.disable_jit():
        return np.stack(
            [np.asarray(entry.fn(*(a[n] for a in args))) for n in range(args[0].shape[0])]
        )


@pytest.mark.parametrize("entry", REGISTRY, ids=lambda e: e.name)
def test_batching_jit_vmap_dtype(entry):
    """Under jit, equal to an eager loop over single elements (batch shape ()):
    - batch shape (3, 1, 2), with the other arguments broadcasting from (2,) where the function
      broadcasts leading axes;
    - vmap over 6 elements each of batch shape (1,);
    - float32 in gives float32 out."""
    args = _batched_sample(entry, (6,))
    reference = _eager_loop(entry, args)
    assert reference.dtype == np.float64
    broadcast = entry.broadcasts and len(args) > 1
    grid = (args[0].reshape((3, 1, 2) + args[0].shape[1:]),) + tuple(
        a[:2] if broadcast else a.reshape((3, 1, 2) + a.shape[1:]) for a in args[1:]
    )
    ones = tuple(a[:, None] for a in args)
    args32 = tuple(a.astype(np.float32) for a in args)

    def transformed(grid, ones, flat32):
        return entry.fn(*grid), jax.vmap(entry.fn)(*ones), entry.fn(*flat32)

    out_grid, out_ones, out32 = _compiled(transformed, grid, ones, args32)
    assert out_grid.shape == (3, 1, 2) + reference.shape[1:] and out_grid.dtype == jnp.float64
    if broadcast:  # element (i, 0, k) pairs the first argument's element 2i + k with the others' k
        expected = np.stack(  # (compiled per element: the loop above checked op-by-op evaluation)
            [
                np.asarray(entry.fn(args[0][2 * i + k], *(a[k] for a in args[1:])))
                for i in range(3)
                for k in range(2)
            ]
        )
    else:
        expected = reference
    _assert_close(out_grid, expected.reshape(out_grid.shape), rtol=1e-12, atol=1e-14)
    assert out_ones.shape == (6, 1) + reference.shape[1:]
    _assert_close(out_ones[:, 0], reference, rtol=1e-12, atol=1e-14)
    assert out32.dtype == jnp.float32
    # float32 agrees with float64 (the inputs differ by their float32 rounding).
    _assert_close(out32, reference, rtol=1e-4, atol=1e-4)


def test_identity_and_random_shapes_and_dtypes():
    for shape in [(), (1,), (3, 1, 2)]:
        for dtype in [jnp.float32, jnp.float64]:
            e = jq.identity(shape, dtype)
            assert e.shape == shape + (4,) and e.dtype == dtype
            np.testing.assert_array_equal(np.asarray(e)[..., 0], 1.0)
            np.testing.assert_array_equal(np.asarray(e)[..., 1:], 0.0)
    assert jq.identity(3).shape == (3, 4) and jq.identity().dtype == jnp.float64
    key = jax.random.key(7)
    r = jax.jit(jq.random, static_argnums=(1, 2))(key, (3, 1, 2), jnp.float32)
    assert r.shape == (3, 1, 2, 4) and r.dtype == jnp.float32
    keys = jax.random.split(key, 3)
    batched = jax.jit(jax.vmap(jq.random))(keys)
    assert batched.shape == (3, 4) and batched.dtype == jnp.float64
    np.testing.assert_allclose(
        batched, np.stack([np.asarray(jq.random(k)) for k in keys]), rtol=1e-15
    )
    assert jq.random(key, 5).shape == (5, 4)


# ---------------------------------------------------------------------------------------------------
# Gradients.


def _grad_points(entry, kinds):
    """Points of every kind (NUM_RANDOM random ones, two of each other kind) stacked on axis 0."""
    rng = _rng(entry, salt=5)
    labels, points = [], []
    for kind in kinds:
        for _ in range(NUM_RANDOM if kind == "random" else 2):
            labels.append(kind)
            points.append(entry.sample(rng, kind))
    args = tuple(
        np.stack([np.asarray(p[i], dtype=np.float64) for p in points])
        for i in range(len(points[0]))
    )
    return labels, args


def _jacobians(fn, args):
    argnums = tuple(range(len(args)))
    forward = jax.vmap(jax.jacfwd(fn, argnums=argnums))(*args)
    reverse = jax.vmap(jax.jacrev(fn, argnums=argnums))(*args)
    return forward, reverse


def _perturbed(entry, args):
    """Inputs for central differences: every point × every input component × ±step, flattened."""
    sizes = [math.prod(a.shape[1:]) for a in args]
    blocks = []
    for i, a in enumerate(args):
        delta = (entry.fd_step * np.eye(sizes[i])).reshape((sizes[i],) + a.shape[1:])
        shifts = np.concatenate([delta, -delta])
        blocks.append(
            [
                np.repeat(b[:, None], 2 * sizes[i], axis=1) + (shifts[None] if j == i else 0.0)
                for j, b in enumerate(args)
            ]
        )
    return [
        np.concatenate([blocks[i][j] for i in range(len(args))], axis=1).reshape(
            (-1,) + args[j].shape[1:]
        )
        for j in range(len(args))
    ]


def _differences(entry, args, outs):
    """Turn the outputs at `_perturbed(entry, args)` into Jacobians (N, *out, *in) per argument."""
    sizes = [math.prod(a.shape[1:]) for a in args]
    outs = np.asarray(outs, dtype=np.float64).reshape((args[0].shape[0], 2 * sum(sizes), -1))
    jacobians, start = [], 0
    for size in sizes:
        block = outs[:, start : start + 2 * size]
        start += 2 * size
        diff = (block[:, :size] - block[:, size:]) / (2 * entry.fd_step)  # (N, D, out)
        jacobians.append(np.moveaxis(diff, 1, -1))  # (N, out, D)
    return jacobians


@pytest.mark.parametrize("entry", REGISTRY, ids=lambda e: e.name)
def test_gradients_match_finite_differences(entry):
    labels, args = _grad_points(entry, ALL_KINDS)
    args32 = tuple(a.astype(np.float32) for a in args)
    checked = np.array([label in entry.grad_kinds for label in labels])
    labels = [label for label in labels if label in entry.grad_kinds]
    # Finite differences in float64, at the float64 points and at the float32-rounded ones.
    fd_inputs = [
        np.concatenate([x, y])
        for x, y in zip(
            _perturbed(entry, tuple(a[checked] for a in args)),
            _perturbed(entry, tuple(a.astype(np.float64)[checked] for a in args32)),
            strict=True,
        )
    ]

    def everything(args64, args32, fd_inputs):
        ad32 = _jacobians(entry.fn, args32) if entry.float32_gradients else None
        return _jacobians(entry.fn, args64), ad32, jax.vmap(entry.fn)(*fd_inputs)

    with jax.debug_nans(True):
        ad64, ad32, fd_outs = _compiled(everything, args, args32, fd_inputs)
    fd_outs = np.asarray(fd_outs, dtype=np.float64)
    half = fd_outs.shape[0] // 2
    cases = [(ad64, tuple(a[checked] for a in args), np.float64, 1e-7)]
    if entry.float32_gradients:
        cases.append((ad32, tuple(a[checked] for a in args32), np.float32, 1e-3))
    for (forward, reverse), fd_points, dtype, rtol in cases:
        outs = fd_outs[:half] if dtype == np.float64 else fd_outs[half:]
        fd = _differences(entry, fd_points, outs)
        for j in list(forward) + list(reverse):  # NaN-free at every kind of point
            assert j.dtype == dtype
            assert np.all(np.isfinite(np.asarray(j))), (
                f"non-finite Jacobian of {entry.name} ({dtype.__name__})"
            )
        num = fd[0].shape[0]
        forward = [
            np.asarray(j, np.float64)[checked].reshape(num, fd[i].shape[1], -1)
            for i, j in enumerate(forward)
        ]
        reverse = [
            np.asarray(j, np.float64)[checked].reshape(num, fd[i].shape[1], -1)
            for i, j in enumerate(reverse)
        ]
        for n, label in enumerate(labels):
            scale = max(1.0, max(float(np.max(np.abs(j[n]))) for j in fd))
            fwd_err = max(
                float(np.max(np.abs(a[n] - b[n]))) for a, b in zip(forward, fd, strict=True)
            )
            rev_err = max(
                float(np.max(np.abs(a[n] - b[n]))) for a, b in zip(reverse, forward, strict=True)
            )
            where = f"{entry.name} ({dtype.__name__}) at {label}"
            assert fwd_err <= rtol * scale, (
                f"{where}: jacfwd vs FD {fwd_err:.2e} (scale {scale:.1e})"
            )
            assert rev_err <= rtol * scale, (
                f"{where}: jacrev vs jacfwd {rev_err:.2e} (scale {scale:.1e})"
            )
