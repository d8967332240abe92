"""The default solver's extra stopping rules (`jaxdof/_fit/lm.py`): Bates & Watts' relative
offset, on a linear problem where it is exact, and the loss's rounding floor."""

import jax
import jax.numpy as jnp
import numpy as np
import optimistix as optx

from jaxdof._fit.lm import (
    _ROUNDING_MARGIN,
    MAX_STEP,
    LevenbergMarquardt,
    loss_rounding,
    relative_offset,
)


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


def _noisy_linear(rho: float):
    """A linear least-squares problem with noise `sigma = 0.05` whose residuals also carry a
    rounding-like error of size `rho`: deterministic in `y`, changing at every step, and invisible
    to the Jacobian (as a float32 render's rounding is)."""
    rng = np.random.default_rng(1)
    n = 400
    a = jnp.asarray(rng.standard_normal((n, 2)))
    b = a @ jnp.array([0.3, -0.2]) + 0.05 * jnp.asarray(rng.standard_normal(n))

    def fn(y, args):
        smooth = a @ y - b
        return smooth + jax.lax.stop_gradient(rho * jnp.sin(1e9 * smooth + 1.0))

    y_ls = jnp.linalg.lstsq(a, b)[0]
    se = 0.05 * jnp.sqrt(jnp.diag(jnp.linalg.inv(a.T @ a)))
    return fn, y_ls, se, jnp.full((n,), rho)


def _solve(fn, options, max_step=np.inf):
    # Unbounded steps by default: the stopping rules alone (y0 is 2.7 from the solution)
    solver = LevenbergMarquardt(
        rtol=1e-8, atol=1e-8, offset_tol=1e-3, rank_tol=1.5e-8, max_step=max_step
    )
    y0 = jnp.array([3.0, 2.0])
    return optx.least_squares(fn, solver, y0, None, options, max_steps=200, throw=False)


def test_a_step_under_the_loss_rounding_stops_the_solve():
    """With residuals rounded at `rho = 2e-4` (4e-3 of the noise, so the relative offset cannot
    fall under 1e-3), optimistix's test stops only after a streak of noise-driven steps (42 here);
    told the rounding, the solve stops at the first point whose next step's predicted decrease is
    under `_ROUNDING_MARGIN` times the loss's rounding, which for a linear problem is the loss
    above the minimum, so within `sqrt(2 margin nu) / sigma` standard errors of it."""
    fn, y_ls, se, rho = _noisy_linear(2e-4)
    told = _solve(fn, dict(rounding=rho))
    blind = _solve(fn, None)
    assert told.result == optx.RESULTS.successful
    assert int(told.stats["num_steps"]) <= 5
    assert int(blind.stats["num_steps"]) > 3 * int(told.stats["num_steps"])
    nu = float(loss_rounding(fn(told.value, None), rho))
    bound = np.sqrt(2 * _ROUNDING_MARGIN * nu) / 0.05
    off = np.abs(np.asarray((told.value - y_ls) / se))
    assert np.all(off <= bound)
    assert np.all(off < 0.01)  # and in fact far inside it


def test_exact_residuals_solve_to_the_minimum():
    """Without rounding the rule never stops a solve early: told a rounding or not, the solve
    reaches the least-squares solution to the step tolerance."""
    fn, y_ls, se, rho = _noisy_linear(0.0)
    for options in (None, dict(rounding=rho)):
        sol = _solve(fn, options)
        assert sol.result == optx.RESULTS.successful
        np.testing.assert_array_less(np.abs(np.asarray((sol.value - y_ls) / se)), 1e-5)


def test_loss_rounding():
    """`eps L / 4` of the sum in the residual's dtype, plus `||r * rounding||`."""
    r = jnp.array([3.0, -4.0], jnp.float32)
    eps = float(np.finfo(np.float32).eps)
    np.testing.assert_allclose(float(loss_rounding(r, None)), eps * 12.5 / 4, rtol=1e-6)
    got = float(loss_rounding(r, jnp.array([1e-3, 2e-3])))
    np.testing.assert_allclose(got, eps * 12.5 / 4 + np.hypot(3e-3, 8e-3), rtol=1e-6)


def test_the_step_bound_keeps_every_step_within_it_and_reaches_the_same_solution():
    """`MAX_STEP`: the damped Newton step is scaled along its direction to at most `MAX_STEP` in
    every coordinate; from 2.7 away the solve takes more steps and ends at the same solution."""
    fn, y_ls, se, _ = _noisy_linear(0.0)
    solver = LevenbergMarquardt(rtol=1e-8, atol=1e-8, offset_tol=1e-3, rank_tol=1.5e-8)
    y0 = jnp.array([3.0, 2.0])
    path = [
        np.asarray(optx.least_squares(fn, solver, y0, None, {}, max_steps=k, throw=False).value)
        for k in range(1, 9)
    ]
    moves = np.abs(np.diff(np.asarray([[3.0, 2.0], *path]), axis=0))
    assert np.all(moves <= MAX_STEP * (1 + 1e-12))
    assert np.max(moves) > 0.5 * MAX_STEP  # the bound was active
    bounded = _solve(fn, None, max_step=MAX_STEP)
    np.testing.assert_allclose(
        np.asarray(bounded.value), np.asarray(y_ls), atol=1e-3 * float(se.min())
    )
