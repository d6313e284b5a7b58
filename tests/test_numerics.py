"""Safe numerics: the series-switched coefficient functions against 50-digit mpmath values (value and
derivative in θ², on both sides of the switch, in float64 and float32), the safe norm / atan2, the top
eigenvector's derivative, and the validation helpers."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import mpmath
import numpy as np
import pytest

from jaxquat import _numerics as nx

mpmath.mp.dps = 50


def _cos_half(t_sq):
    return mpmath.cos(mpmath.sqrt(t_sq) / 2)


def _sinc_half(t_sq):
    t = mpmath.sqrt(t_sq)
    return mpmath.mpf(1) / 2 if t == 0 else mpmath.sin(t / 2) / t


def _tan_half_over(t_sq):
    t = mpmath.sqrt(t_sq)
    return mpmath.mpf(1) / 2 if t == 0 else mpmath.tan(t / 2) / t


def _dexpinv(t_sq):
    t = mpmath.sqrt(t_sq)
    return mpmath.mpf(1) / 12 if t == 0 else (1 - (t / 2) * mpmath.cot(t / 2)) / t_sq


def _cos_half_minus_one(t_sq):
    return -2 * mpmath.sin(mpmath.sqrt(t_sq) / 4) ** 2


FUNCTIONS = {
    "cos_half": (nx.cos_half, _cos_half, -1 / 8),
    "sinc_half": (nx.sinc_half, _sinc_half, -1 / 48),
    "tan_half_over": (nx.tan_half_over, _tan_half_over, 1 / 24),
    "dexpinv_coeff": (nx.dexpinv_coeff, _dexpinv, 1 / 720),
    "cos_half_minus_one": (nx.cos_half_minus_one, _cos_half_minus_one, -1 / 8),
}
# θ² from 0 through the float32 (1e-2) and float64 (1e-3) switches to 9 (θ = 3, below every pole).
THETA_SQ = np.array(
    [0.0, 1e-30, 1e-16, 1e-8, 1e-5, 9.99e-4, 1e-3, 1.001e-3, 3e-3, 9.99e-3, 1e-2, 1.001e-2]
    + [0.0499, 0.0501, 0.1, 0.499, 0.501, 1.0, 4.0, 9.0]
)


def _reference(f, points):
    values = np.array([float(f(mpmath.mpf(float(x)))) for x in points])
    slopes = np.array(
        [
            float(mpmath.diff(f, mpmath.mpf(1e-25), h=mpmath.mpf(1e-25), direction=1))
            if x == 0
            else float(
                mpmath.diff(f, mpmath.mpf(float(x)), h=mpmath.mpf(float(x)) * mpmath.mpf(1e-12))
            )
            for x in points
        ]
    )
    return values, slopes


@pytest.mark.parametrize("name", list(FUNCTIONS))
def test_coefficient_functions_against_mpmath(name):
    fn, reference, slope_at_zero = FUNCTIONS[name]
    values, slopes = _reference(reference, THETA_SQ)
    assert abs(slopes[0] - slope_at_zero) < 1e-15  # the docstring's value
    both = jax.jit(jax.vmap(jax.value_and_grad(fn)))
    with jax.debug_nans(True):
        v64, d64 = both(jnp.asarray(THETA_SQ))
        v32, d32 = both(jnp.asarray(THETA_SQ, dtype=jnp.float32))
    assert v32.dtype == d32.dtype == jnp.float32
    # Relative accuracy everywhere (cos(θ/2) − 1 is tiny near 0: that is the point of it). The
    # direct form of (1 − (θ/2)cot(θ/2))/θ² cancels (~ε·12/θ²): even with its later switch it keeps
    # ~1e-14 (float64) / 1e-5 (float32) relative there.
    rtol64, rtol32 = (2e-14, 2e-5) if name == "dexpinv_coeff" else (4e-15, 1e-6)
    drtol64 = 1e-9
    np.testing.assert_allclose(v64, values, rtol=rtol64, atol=0)
    np.testing.assert_allclose(d64, slopes, rtol=drtol64, atol=1e-13 * np.max(np.abs(slopes)))
    np.testing.assert_allclose(np.asarray(v32, np.float64), values, rtol=rtol32, atol=0)
    np.testing.assert_allclose(np.asarray(d32, np.float64), slopes, rtol=3e-4, atol=1e-6)


def test_atan2_over_against_mpmath():
    """atan2(s, w)/s for w > 0 (series near s = 0), w = 0 and w < 0, value and gradient."""
    s_sq = np.array(
        [0.0, 1e-20, 1e-9, 1e-5, 9.9e-5, 1.01e-4, 1e-2, 0.5, 2.0, 1e-9, 0.5, 1e-9, 0.25]
    )
    w = np.array([1.0, 0.9, 1.0, 1.0, 1.0, 1.0, 0.7, 0.3, 1.5, -1.0, -0.2, 0.0, 0.0])

    def ref(a, b):
        s = mpmath.sqrt(a)
        return 1 / b if s == 0 else mpmath.atan2(s, b) / s

    values, d_s, d_w = [], [], []
    for a, b in zip(s_sq, w, strict=True):
        a, b = mpmath.mpf(a), mpmath.mpf(b)
        values.append(float(ref(a, b)))
        in_s = lambda x, b=b: ref(x, b)  # noqa: E731
        if a == 0:  # one-sided (s² ≥ 0), at a point a tiny step inside
            d_s.append(
                float(mpmath.diff(in_s, mpmath.mpf(1e-25), h=mpmath.mpf(1e-25), direction=1))
            )
        else:
            d_s.append(float(mpmath.diff(in_s, a, h=a * mpmath.mpf(1e-12))))
        d_w.append(float(mpmath.diff(lambda x, a=a: ref(a, x), b)))
    grads = jax.jit(jax.vmap(jax.value_and_grad(nx.atan2_over, argnums=(0, 1))))
    with jax.debug_nans(True):
        value, (g_s, g_w) = grads(jnp.asarray(s_sq), jnp.asarray(w))
    np.testing.assert_allclose(value, values, rtol=1e-14)
    np.testing.assert_allclose(g_s, d_s, rtol=1e-9)
    np.testing.assert_allclose(g_w, d_w, rtol=1e-9)
    assert abs(float(g_s[0]) - (-1 / 3)) < 1e-15  # −1/(3w³) at s = 0, w = 1
    # At s = 0, w < 0 (log(−1)): the documented finite value π.
    np.testing.assert_allclose(nx.atan2_over(0.0, -1.0), np.pi, rtol=1e-15)


def test_safe_norm_and_safe_atan2():
    x = np.array([[3.0, 4.0, 0.0], [0.0, 0.0, 0.0], [1e-100, 0.0, 0.0]])

    @jax.jit
    def everything(x):
        norm_grad = jax.vmap(jax.grad(nx.safe_norm))(x)
        atan_grad = jax.vmap(jax.grad(nx.safe_atan2, argnums=(0, 1)))(x[:, 0], x[:, 1])
        return nx.safe_norm(x), norm_grad, nx.safe_atan2(x[:, 1], x[:, 0]), atan_grad

    with jax.debug_nans(True):
        norms, norm_grad, angles, (g_y, g_x) = everything(x)
    np.testing.assert_allclose(norms, [5.0, 0.0, 1e-100], rtol=1e-15)
    np.testing.assert_allclose(norm_grad, [[0.6, 0.8, 0.0], [0, 0, 0], [1.0, 0, 0]], rtol=1e-15)
    np.testing.assert_allclose(angles, np.arctan2(x[:, 1], x[:, 0]), rtol=1e-15)
    # d atan2(y, x) = (x dy − y dx)/(x² + y²); exactly 0 at the origin.
    # (gradients taken at (y, x) = (3, 4), (0, 0) and (1e-100, 0))
    np.testing.assert_allclose(g_y, [4.0 / 25.0, 0.0, 0.0], rtol=1e-15)
    np.testing.assert_allclose(g_x, [-3.0 / 25.0, 0.0, -1e100], rtol=1e-15)
    assert nx.sum_squares(jnp.ones((2, 3)), keepdims=True).shape == (2, 1)


def test_top_eigenvector_and_its_derivative_with_degenerate_rest():
    """Eigenvalues (3, −1, −1, −1) as for Davenport's matrix of a rotation: the derivative of the top
    eigenvector involves only its own gap and matches finite differences and perturbation theory."""
    rng = np.random.default_rng(31)
    basis, _ = np.linalg.qr(rng.normal(size=(4, 4)))
    k = basis @ np.diag([3.0, -1.0, -1.0, -1.0]) @ basis.T
    dk = rng.normal(size=(4, 4))
    dk = dk + dk.T
    top = basis[:, 0]
    # Perturbation theory: dv = Σ_{i≠0} vᵢ (vᵢᵀ dK v₀)/(λ₀ − λᵢ) = (I − v₀v₀ᵀ) dK v₀ / 4 here.
    expected = (np.eye(4) - np.outer(top, top)) @ dk @ top / 4.0

    @jax.jit
    def derivatives(k, dk):
        value, tangent = jax.jvp(nx.top_eigenvector, (k,), (dk,))
        cotangent = jax.vjp(nx.top_eigenvector, k)[1](jnp.ones(4))[0]
        return value, tangent, cotangent

    with jax.debug_nans(True):
        value, tangent, cotangent = derivatives(k, dk)
        at_identity_like = jax.jit(jax.jacrev(nx.top_eigenvector))(np.diag([3.0, -1.0, -1.0, -1.0]))
    sign = np.sign(np.dot(value, top))
    np.testing.assert_allclose(sign * np.asarray(value), top, atol=1e-14)
    np.testing.assert_allclose(sign * np.asarray(tangent), expected, atol=1e-13)
    # Reverse mode is the transpose: ⟨cotangent, dK⟩ = ⟨1, dv⟩.
    np.testing.assert_allclose(np.sum(cotangent * dk), np.sum(tangent), rtol=1e-12)
    assert np.all(np.isfinite(at_identity_like))
    h = 1e-6

    # eigh's sign is arbitrary per call (and per LAPACK build): fix it to `top`'s.
    def aligned(matrix):
        v = np.asarray(nx.top_eigenvector(matrix))
        return np.sign(np.dot(v, top)) * v

    fd = (aligned(k + h * dk) - aligned(k - h * dk)) / (2 * h)
    np.testing.assert_allclose(fd, expected, atol=1e-8)


def test_validation_helpers():
    assert nx.as_float_array(np.arange(3)).dtype == jnp.float64
    assert nx.as_float_array(np.ones(3, np.float32)).dtype == jnp.float32
    with pytest.raises(ValueError, match="`z` must be real; got dtype complex"):
        nx.as_float_array(np.ones(2, complex), "z")
    with pytest.raises(ValueError, match=r"`z` must be an array of numbers; got str"):
        nx.as_float_array("abc", "z")
    with pytest.raises(ValueError, match=r"`x` must have shape \(\.\.\., 4\); got shape \(2, 3\)"):
        nx.check_trailing(np.zeros((2, 3)), 4, "x")
    with pytest.raises(ValueError, match=r"`m` must have shape \(\.\.\., 3, 3\); got shape \(3,\)"):
        nx.check_matrix(np.zeros(3), "m")
    with pytest.raises(ValueError, match=r"`method` must be one of 'a', 'b'; got 'c'"):
        nx.check_choice("c", ("a", "b"), "method")
    with pytest.raises(ValueError, match=r"`frame` must be one of 'world', 'body'; got 3"):
        nx.check_frame(3)
    assert nx.check_frame("body") == "body"
    a, b = nx.broadcast_batch((jnp.zeros((3, 1, 4)), 1), (jnp.zeros((2, 3)), 1))
    assert a.shape == (3, 2, 4) and b.shape == (3, 2, 3)
    with pytest.raises(ValueError, match="do not broadcast"):
        nx.broadcast_batch((jnp.zeros((3, 4)), 1), (jnp.zeros((2, 3)), 1))
    rng = np.random.default_rng(0)
    u, v = rng.normal(size=(5, 3)), rng.normal(size=(5, 3))
    np.testing.assert_allclose(nx.cross(u, v), np.cross(u, v), rtol=1e-15)
    assert nx.series_threshold(jnp.float32) == 1e-2 and nx.series_threshold(jnp.float64) == 1e-3


# ---------------------------------------------------------------------------------------------------
# `eager_jit`: eager calls of the public quaternion functions run as one compiled program.


def _eager_jit_cases():
    """(function, args, kwargs) of wrapped public functions, with a batch shape (13, 11) that no other
    test uses, so each first call below compiles once."""
    import jaxquat as jq

    rng = np.random.default_rng(3)
    p, q = (jnp.asarray(rng.normal(size=(13, 11, 4))) for _ in range(2))
    v, w = (jnp.asarray(rng.normal(size=(13, 11, 3))) for _ in range(2))
    m = jq.to_matrix.__wrapped__(q)  # (the function as written, called eagerly op by op)
    return [
        (jq.multiply, (p, q), {}),
        (jq.rotate, (v, q), {"center": w}),
        (jq.from_matrix, (np.asarray(m),), {}),  # a NumPy argument
        (jq.to_euler, (q, "zyx"), {}),  # a static string, positional
        (jq.from_euler, ("XYZ", w), {}),
        (jq.slerp, (p, q, 0.3), {}),  # a Python float
        (jq.to_axis_angle, (q,), {}),  # a tuple out
        (jq.step, (q, w, jnp.float32(0.1)), {"frame": "body"}),  # a static keyword
    ]


def test_eager_calls_compile_once_and_equal_the_traced_function():
    """Each eager call of a wrapped function runs its compiled program (one compilation per shape: the
    second call adds none) and gives exactly what the function traced under an outer `jax.jit` gives
    (test_transformations compares that, in turn, with op-by-op evaluation under `jax.disable_jit`),
    with the same dtypes."""
    for fn, args, kwargs in _eager_jit_cases():
        before = fn.compiled._cache_size()
        out = fn(*args, **kwargs)
        assert fn.compiled._cache_size() == before + 1, fn.__name__
        fn(*args, **kwargs)
        assert fn.compiled._cache_size() == before + 1, fn.__name__
        # Under the outer jit the arrays are tracers (strings stay Python values), so the wrapper
        # runs the function as written inside that trace.
        arrays = [a for a in args if not isinstance(a, str)]
        array_kwargs = {k: v for k, v in kwargs.items() if not isinstance(v, str)}

        def traced(arrays, array_kwargs, fn=fn, args=args, kwargs=kwargs):
            remaining = iter(arrays)
            call_args = [a if isinstance(a, str) else next(remaining) for a in args]
            return fn(*call_args, **{**kwargs, **array_kwargs})

        expected = jax.jit(traced)(arrays, array_kwargs)
        for got, want in zip(jax.tree.leaves(out), jax.tree.leaves(expected), strict=True):
            assert got.dtype == want.dtype, fn.__name__
            np.testing.assert_array_equal(got, want, err_msg=fn.__name__)


def test_traced_calls_are_the_functions_as_written():
    """Under jit, grad or vmap the functions run as written: the traced programs equal those of the
    undecorated functions (`__wrapped__`), with no nested `jit` added."""
    import jaxquat as jq

    p, q = jnp.array([0.9, 0.1, -0.3, 0.2]), jnp.array([0.5, 0.5, 0.5, 0.5])
    v = jnp.array([3.0, 0.0, 0.0])

    def loss(rotate, multiply, to_euler):
        def value(q):
            return jnp.sum(rotate(v, multiply(p, q))) + jnp.sum(to_euler(q, "xyz"))

        return value

    wrapped = loss(jq.rotate, jq.multiply, jq.to_euler)
    plain = loss(jq.rotate.__wrapped__, jq.multiply.__wrapped__, jq.to_euler.__wrapped__)
    for transform in (lambda f: f, jax.grad, jax.vmap):
        x = jnp.stack([p, q]) if transform is jax.vmap else q
        assert str(jax.make_jaxpr(transform(wrapped))(x)) == str(
            jax.make_jaxpr(transform(plain))(x)
        )


def test_bad_arguments_raise_as_without_compilation():
    """A bad argument raises the function's own `ValueError`, with the same message as op-by-op
    evaluation and no note from JAX's traceback filtering; lists and wrong static arguments take the
    uncompiled path and behave as before (the seed's example with lists)."""
    import jaxquat as jq

    q = jnp.array([0.5, 0.5, 0.5, 0.5])
    calls = [
        lambda: jq.rotate(jnp.ones(2), q),
        lambda: jq.multiply(jnp.ones((2, 4)), jnp.ones((3, 4))),
        lambda: jq.from_euler("xyw", jnp.ones(3)),
        lambda: jq.to_euler(q, 5),
        lambda: jq.slerp(q, q, "half"),
        lambda: jq.step(q, jnp.ones(3), 0.1, frame="inertial"),
        lambda: jq.angular_velocity(jnp.ones((5, 2, 4)), jnp.ones(3)),
    ]
    for call in calls:
        with pytest.raises(ValueError) as got:
            call()
        with jax.disable_jit(), pytest.raises(ValueError) as want:
            call()
        assert str(got.value) == str(want.value)
        assert not getattr(got.value, "__notes__", None), got.value.__notes__
    np.testing.assert_allclose(jq.rotate([3, 0, 0], [1, 2, 3, 4]), [-2.0, 2.0, 1.0], atol=1e-15)
    with pytest.raises(TypeError):  # Python's own error for an unknown keyword
        jq.multiply(q, q, scale=2.0)
