"""Arrays sharded over a mesh of explicit axes (`jax.make_mesh`'s default, under `jax.set_mesh`).

Under explicit axes the sharding is part of an array's type: loops whose carry starts replicated (a
shared q₀) and comes back sharded, gathers by traced indices, arrays made by `jnp.zeros` beside sharded
ones and the ensemble's own sharding constraints were all errors (ShardingTypeError, "carry input and
carry output must have equal types", an assertion in `with_sharding_constraint`). Four host devices,
in a subprocess (the device count is fixed when JAX starts).
"""

from helpers import run_on_four_devices

_SCRIPT = r"""
import json
import diffrax as dfx
import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jax.sharding import NamedSharding, PartitionSpec as P

jax.config.update("jax_enable_x64", True)
jax.config.update("jax_numpy_rank_promotion", "raise")
import jaxquat as jq

assert jax.device_count() == 4, jax.devices()
mesh = jax.make_mesh((4,), ("b",))  # explicit axes: jax.make_mesh's default
assert mesh.explicit_axes == ("b",), mesh
N, T, DT = 8, 12, 0.05
rng = np.random.default_rng(0)


def unit(x):
    return x / np.linalg.norm(x, axis=-1, keepdims=True)


def shard(x, *spec):
    return jax.device_put(jnp.asarray(x), NamedSharding(mesh, P(*spec)))


q0 = unit(rng.normal(size=(N, 4)))
w = rng.normal(size=(N, 3))
samples = rng.normal(size=(T, N, 3))
inertia = np.array([1.0, 1.7, 2.4])
masses = np.array([1.0, 2.0, 1.5])
base = rng.normal(size=(3, 3))


class Shape(eqx.Module):
    base: jax.Array

    def __call__(self, t):
        return self.base * (1.0 + 0.2 * jnp.sin(t))


def solver_step(solver):
    def run(q, w):
        term = dfx.ODETerm(jq.kinematic_vector_field(w))
        state = solver.init(term, 0.0, DT, q, None)
        return solver.step(term, 0.0, DT, q, None, state, made_jump=False)[0]

    return run


a = rng.normal(size=(N, 3))
b = rng.normal(size=(N, 3))
b[0] = -2.0 * a[0]  # antiparallel: the fallback axis
cases = {}
for method in ("euler", "midpoint", "rk4", "cf4", "magnus4"):
    for save in ("final", "all"):
        cases[f"integrate_{method}_{save}_shared_q0"] = (
            lambda w, m=method, s=save: jq.integrate(jq.identity(), w, DT, T, method=m, save=s),
            [(w, ("b",))],
        )
    cases[f"integrate_{method}_sampled"] = (
        lambda s, m=method: jq.integrate(q0, jq.sampled(s, DT), DT, T, method=m, save="final"),
        [(samples, (None, "b"))],
    )
cases["grad_integrate_sampled_shared_q0"] = (
    jax.grad(lambda s: jnp.sum(jnp.sin(jq.integrate(jq.identity(), jq.sampled(s, DT), DT, T)))),
    [(samples, (None, "b"))],
)
cases["grad_integrate_sampled_sharded_q0"] = (
    jax.grad(lambda s, q: jnp.sum(jnp.sin(jq.integrate(q, jq.sampled(s, DT), DT, T))), (0, 1)),
    [(samples, (None, "b")), (q0, ("b",))],
)
cases["grad_integrate_cf4_shared_q0"] = (
    jax.grad(lambda w: jnp.sum(jnp.sin(jq.integrate(jq.identity(), w, DT, T, method="cf4")))),
    [(w, ("b",))],
)
cases["rigid_body_shared_q0"] = (
    lambda w: jq.simulate_rigid_body(jq.identity(), w, inertia, DT, T, save="final")[0],
    [(w, ("b",))],
)
cases["grad_rigid_body"] = (
    jax.grad(lambda w, q: jnp.sum(jnp.sin(jq.simulate_rigid_body(q, w, inertia, DT, T)[0])), (0, 1)),
    [(w, ("b",)), (q0, ("b",))],
)
cases["deformable_vmap"] = (
    jax.vmap(lambda q: jq.simulate_deformable_body(masses, Shape(jnp.asarray(base)), q, DT, T)),
    [(q0, ("b",))],
)
cases["from_two_vectors"] = (jq.from_two_vectors, [(a, ("b",)), (b, ("b",))])
cases["from_euler_vmap"] = (
    jax.vmap(lambda e: jq.from_euler("ZYX", e)),
    [(rng.uniform(-1, 1, size=(N, 3)), ("b",))],
)
for name in ("LieEuler", "ExpMidpoint", "RKMK45", "CF4", "Magnus4"):
    cases[f"solver_step_{name}"] = (solver_step(getattr(jq, name)()), [(q0, ("b",)), (w, ("b",))])

out = {}
for name, (fn, args) in cases.items():
    plain = jax.jit(fn)(*(jnp.asarray(x) for x, _ in args))
    try:
        with jax.set_mesh(mesh):
            sharded = jax.jit(fn)(*(shard(x, *spec) for x, spec in args))
    except Exception as e:  # reported, and the test names the case
        out[name] = dict(error=f"{type(e).__name__}: {str(e).splitlines()[0][:300]}")
        continue
    leaves = jax.tree_util.tree_leaves(sharded)
    out[name] = dict(
        error=None,
        difference=max(
            float(np.max(np.abs(np.asarray(x) - np.asarray(y)), initial=0.0))
            for x, y in zip(leaves, jax.tree_util.tree_leaves(plain), strict=True)
        ),
        specs=[str(x.sharding.spec) for x in leaves],
    )

# The ensemble lays its bodies out on a mesh of its own, whatever the caller's.
reference = jq.simulate_ensemble(q0, w, DT, T, save_every=4, statistics=True)
for name, context in (("ensemble_in_explicit_mesh", True), ("ensemble_explicit_inputs", False)):
    try:
        if context:
            with jax.set_mesh(mesh):
                result = jq.simulate_ensemble(shard(q0, "b"), shard(w, "b"), DT, T, save_every=4,
                                              statistics=True)
        else:
            result = jq.simulate_ensemble(shard(q0, "b"), shard(w, "b"), DT, T, save_every=4,
                                          statistics=True)
    except Exception as e:
        out[name] = dict(error=f"{type(e).__name__}: {str(e).splitlines()[0][:300]}")
        continue
    out[name] = dict(
        error=None,
        difference=max(
            float(np.max(np.abs(np.asarray(x) - np.asarray(y))))
            for x, y in ((result.final, reference.final), (result.saved, reference.saved),
                         (result.total_angle, reference.total_angle))
        ),
        specs=[str(result.final.sharding.spec)],
    )
print(json.dumps(out))
"""


def test_explicitly_sharded_inputs_match_unsharded_and_stay_sharded():
    out = run_on_four_devices(_SCRIPT)
    failed = {name: case["error"] for name, case in out.items() if case["error"]}
    assert not failed, failed
    for name, case in out.items():
        assert case["difference"] <= 1e-14, (name, case)
        # Every output keeps the bodies' axis sharded (the ensemble on its own "bodies" mesh).
        axis = "bodies" if name.startswith("ensemble") else "b"
        assert all(repr(axis) in spec for spec in case["specs"]), (name, case)
    assert len(out) == 30, sorted(out)
