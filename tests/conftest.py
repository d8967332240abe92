import jax
import jax.random as jr
import pytest


jax.config.update("jax_enable_x64", True)
jax.config.update("jax_numpy_rank_promotion", "raise")
jax.config.update("jax_numpy_dtype_promotion", "strict")


@pytest.fixture
def getkey():
    """A fresh, deterministic PRNG key per call."""
    keys = iter(jr.split(jr.PRNGKey(5678), 1000))
    return lambda: next(keys)


@pytest.fixture
def float32():
    """Run a test with JAX's default dtype at float32 (x64 off), restoring x64 afterwards."""
    jax.config.update("jax_enable_x64", False)
    try:
        yield
    finally:
        jax.config.update("jax_enable_x64", True)
