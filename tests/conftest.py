"""Shared pytest configuration: float64 on, rank promotion raises, one XLA compilation cache for the
run, compiled programs released before a worker runs out of memory mappings, a seeded key fixture."""

import gc
import os
import shutil
import tempfile

import jax
import pytest
from helpers import mapping_count

jax.config.update("jax_enable_x64", True)
jax.config.update("jax_numpy_rank_promotion", "raise")

# The suite is bound by XLA compilation, and many tests, notebooks and command-line subprocesses
# compile the same programs (JAX's in-memory cache is per process and per function object; this one is
# keyed by the program itself). A fresh directory per run, made by the controlling process and passed
# to the xdist workers and every subprocess through the environment, so no run sees another's entries;
# a directory the caller set is used as it is.
_CACHE = "JAX_COMPILATION_CACHE_DIR"
_MIN_TIME = "JAX_PERSISTENT_CACHE_MIN_COMPILE_TIME_SECS"


def pytest_configure(config):
    if not hasattr(config, "workerinput") and _CACHE not in os.environ:
        os.environ[_CACHE] = tempfile.mkdtemp(prefix="jaxquat-xla-cache-")
        config._jaxquat_cache = os.environ[_CACHE]  # removed at the end of the run
    if _CACHE not in os.environ:  # (a worker of a controller that did not run this hook)
        return
    os.environ.setdefault(_MIN_TIME, "0.1")
    # This module (and so jax) is imported before this hook runs: the settings are also made directly.
    jax.config.update("jax_compilation_cache_dir", os.environ[_CACHE])
    jax.config.update("jax_persistent_cache_min_compile_time_secs", float(os.environ[_MIN_TIME]))


def pytest_unconfigure(config):
    directory = getattr(config, "_jaxquat_cache", None)
    if directory is not None:
        shutil.rmtree(directory, ignore_errors=True)
        del os.environ[_CACHE]


# Every program XLA:CPU compiles stays mapped in memory while a JIT cache holds it: about three areas
# (code, constants, data) for each of its kernels, 3-4 for a one-line `jax.jit`, ~170 for the gradient
# of an `integrate` call (measured with jax 0.10.2). Linux allows a process `vm.max_map_count` areas
# (65,530 by default), and a worker running half the suite passed that: the next compilation failed to
# map its code, and the process died unwinding the error (a segmentation fault in `_Unwind_Find_FDE`,
# the core file holding 65,199 areas; 2026-11-27, in each of seven full runs, always under the Magnus8
# gradient of `tests/test_solvers.py`, the largest program late in the run). Every `_CHECK_EVERY`
# tests the areas are counted (20 ms at 30,000), and past half the limit the in-memory compilation
# caches are dropped: later calls recompile, or load the program from the run's persistent cache.
# In a full run so instrumented, a worker passed 38,000 areas after 241 tests and dropped to 1,449;
# no test added more than 2,828.
_CHECK_EVERY = 5


def _mapping_limit() -> int:
    try:
        with open("/proc/sys/vm/max_map_count") as limit:
            return int(limit.read())
    except (OSError, ValueError):
        return 65530


_MAPPING_BUDGET = _mapping_limit() // 2
_tests_since_check = 0


@pytest.fixture(autouse=True)
def _release_compiled_programs_before_the_mapping_limit():
    yield
    global _tests_since_check
    _tests_since_check += 1
    if _tests_since_check < _CHECK_EVERY:
        return
    _tests_since_check = 0
    count = mapping_count()
    if count is not None and count > _MAPPING_BUDGET:
        jax.clear_caches()
        gc.collect()


@pytest.fixture
def key():
    """A fixed PRNG key, so every test is deterministic."""
    return jax.random.key(5678)


@pytest.fixture
def getkey():
    """A callable returning a fresh, deterministic key on each call."""
    state = {"key": jax.random.key(1234)}

    def _getkey():
        state["key"], sub = jax.random.split(state["key"])
        return sub

    return _getkey
