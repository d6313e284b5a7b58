"""Loops under explicit sharding: a carry typed like what its step returns.

With a mesh of explicit axes set (`jax.set_mesh(jax.make_mesh(...))`, `jax.make_mesh`'s default axis
types since JAX 0.7), an array's sharding is part of its type, and a loop's carry must keep its type
from one iteration to the next. A carry that starts replicated (a shared q₀, the identity) and is
multiplied by a sharded ω comes back sharded, which `lax.scan` and `lax.fori_loop` reject ("carry
input and carry output must have equal types"). `settled` gives the carry, before the loop, the
sharding that one step would give it.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import jax


def explicit_mesh() -> bool:
    """Whether the mesh set by `jax.set_mesh` (if any) has explicit axes."""
    return bool(jax.sharding.get_abstract_mesh().explicit_axes)


def settled(step: Callable[[Any], Any], carry: Any) -> Any:
    """`carry`, each leaf resharded to the sharding one `step(carry)` gives it, under a mesh with
    explicit axes; otherwise `carry` itself, untouched (no trace of `step`)."""
    if not explicit_mesh():
        return carry
    out = jax.eval_shape(step, carry)

    def typed(leaf, result):
        want = getattr(result, "sharding", None)
        if want is None or jax.typeof(leaf).sharding.spec == want.spec:
            return leaf
        return jax.sharding.reshard(leaf, want.spec)

    return jax.tree_util.tree_map(typed, carry, out)
