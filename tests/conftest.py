"""Shared pytest configuration: float64 on, rank promotion raises, one XLA compilation cache for the
run, a seeded key fixture."""

import os
import shutil
import tempfile

import jax
import pytest

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
