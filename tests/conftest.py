"""Shared pytest configuration: float64 on, rank promotion raises, a seeded key fixture."""

import jax
import pytest

jax.config.update("jax_enable_x64", True)
jax.config.update("jax_numpy_rank_promotion", "raise")


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
