"""The default solver's extra stopping rule (`jaxdof/_fit/lm.py`): Bates & Watts' relative
offset, on a linear problem where it is exact."""

import jax.numpy as jnp
import numpy as np

from jaxdof._fit.lm import relative_offset


def test_relative_offset_is_the_gauss_newton_step_in_standard_errors():
    """For `r = J delta + e` (a point `delta` away from the least-squares solution of `e`, whose
    residual is orthogonal to `J`): `RO sqrt(p) = ||J delta|| / sigma`, `sigma^2` the residual
    variance `||Q_2^T r||^2 / (n - p)`; 0 at the solution; `inf` without a residual left over."""
    rng = np.random.default_rng(0)
    n, p = 200, 3
    jac = rng.standard_normal((n, p))
    e = rng.standard_normal(n)
    e = e - jac @ np.linalg.lstsq(jac, e, rcond=None)[0]  # the residual at the solution
    delta = np.array([0.01, -0.02, 0.005])
    r = jac @ delta + e
    sigma = np.sqrt(e @ e / (n - p))
    got = float(relative_offset(jnp.asarray(r), jnp.asarray(jac), 1e-12))
    np.testing.assert_allclose(got * np.sqrt(p), np.linalg.norm(jac @ delta) / sigma, rtol=1e-10)
    assert float(relative_offset(jnp.asarray(e), jnp.asarray(jac), 1e-12)) < 1e-12
    assert np.isinf(float(relative_offset(jnp.asarray(jac @ delta), jnp.asarray(jac), 1e-12)))
    # Zero-weight rows (a border band: zero residual and Jacobian row) do not count in n.
    pad = jnp.zeros((50,))
    r2 = jnp.concatenate([jnp.asarray(r), pad])
    j2 = jnp.concatenate([jnp.asarray(jac), jnp.zeros((50, p))])
    np.testing.assert_allclose(float(relative_offset(r2, j2, 1e-12)), got, rtol=1e-12)
