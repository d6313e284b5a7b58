"""The test suite's own machinery, where it rests on behaviour of JAX that could change."""

import gc

import jax
import jax.numpy as jnp
import pytest
from helpers import mapping_count

import jaxquat as jq


@pytest.mark.skipif(mapping_count() is None, reason="counts /proc/self/maps (Linux)")
def test_clearing_the_compilation_caches_releases_the_memory_areas_of_compiled_programs():
    """`tests/conftest.py` keeps each xdist worker under Linux's limit on memory areas per process
    (`vm.max_map_count`) by dropping JAX's in-memory compilation caches: a compiled program holds
    areas for its code until then, and releases them after."""
    q0 = jnp.array([1.0, 0.0, 0.0, 0.0])
    jq.integrate(q0, jnp.ones(3), 0.01, 5).block_until_ready()  # the runtime's own first areas
    jax.clear_caches()
    gc.collect()
    before = mapping_count()
    gradient = jax.jit(jax.grad(lambda w: jnp.sum(jq.integrate(q0, w, 0.01, 50)[1:])))
    gradient(jnp.array([0.2, -0.1, 0.3])).block_until_ready()
    grown = mapping_count() - before
    assert grown >= 30, grown  # a few areas per kernel (about 170 for this program with jax 0.10)
    jax.clear_caches()  # (the jitted function itself stays alive, as module-level ones in tests do)
    gc.collect()
    left = mapping_count() - before
    assert left <= grown // 5, (grown, left)
