"""`fit_lens`'s multi-start driver (`jaxdof/_fit/race.py`): a start that cannot catch up with a
converged one is stopped, and nothing else about the solve changes.

The toy problem has the shape of the run-away measured on the ray-traced `texture` scene: a
basin at `y = 1`, and beyond it a plateau whose loss still falls towards `+inf`, where
Levenberg-Marquardt takes steps of ~20 for ever without meeting its step test.
"""

import jax.numpy as jnp
import numpy as np
import optimistix as optx

from jaxdof._fit.race import cannot_catch_up, race, tie_margin


def model(y, args):
    del args
    (x,) = y
    return jnp.stack([1 - jnp.exp(-((x - 1) ** 2)), 0.1 * jnp.exp(-0.05 * x)])


SOLVER = optx.LevenbergMarquardt(rtol=1e-8, atol=1e-8)
MAX_STEPS = 100


def _tie(n=2.0, p=1):
    return jnp.asarray(n), p, jnp.asarray(0.0)


def _alone(y0):
    sol = optx.least_squares(model, SOLVER, y0, None, max_steps=MAX_STEPS, throw=False)
    return sol.value, sol.result, int(sol.stats["num_steps"])


def test_a_start_that_cannot_catch_up_is_stopped_and_the_others_are_unchanged():
    y0s = jnp.array([[3.0], [6.0], [0.7]])
    ys, result, steps, _, stopped = race(model, SOLVER, y0s, None, MAX_STEPS, _tie())
    # Alone, the plateau start runs out of steps, far above the basin's loss.
    y_run, r_run, k_run = _alone(y0s[1])
    assert r_run == optx.RESULTS.nonlinear_max_steps_reached and k_run == MAX_STEPS
    assert float(0.5 * jnp.sum(model(y_run, None) ** 2)) > 0.4
    # In the race it is stopped soon after the first start converges, as out of steps.
    np.testing.assert_array_equal(np.asarray(stopped), [False, True, False])
    maxed = np.asarray(result == optx.RESULTS.nonlinear_max_steps_reached)
    ok = np.asarray(result == optx.RESULTS.successful)
    np.testing.assert_array_equal(maxed, [False, True, False])
    converged_at = min(int(steps[0]), int(steps[2]))
    assert int(steps[1]) <= max(converged_at, 10) + 1 < MAX_STEPS
    # The starts that converge do so exactly as alone: same point, same steps.
    for i in (0, 2):
        y_i, r_i, k_i = _alone(y0s[i])
        assert ok[i] and r_i == optx.RESULTS.successful
        np.testing.assert_array_equal(np.asarray(ys[i]), np.asarray(y_i))
        assert int(steps[i]) == k_i


def test_no_start_is_stopped_before_one_has_converged():
    """Two plateau starts: neither converges, so neither is stopped, and both run the whole
    budget as they do alone."""
    y0s = jnp.array([[6.0], [9.0]])
    ys, result, steps, _, stopped = race(model, SOLVER, y0s, None, MAX_STEPS, _tie())
    assert not np.any(np.asarray(stopped))
    np.testing.assert_array_equal(np.asarray(steps), [MAX_STEPS, MAX_STEPS])
    assert np.all(np.asarray(result == optx.RESULTS.nonlinear_max_steps_reached))
    for i in range(2):
        y_i, r_i, _ = _alone(y0s[i])
        assert r_i == optx.RESULTS.nonlinear_max_steps_reached
        np.testing.assert_allclose(np.asarray(ys[i]), np.asarray(y_i), rtol=1e-12)


def test_the_pace_rule_projects_a_straight_line_over_the_steps_left():
    """Loss 10 after 12 ten steps before (0.2 a step): 40 steps more reach 2, so a start is on
    pace against a converged loss of 3 and behind one of 1; a start that gained nothing is behind
    anything lower; a rising loss (a rejected step cannot raise it) would be behind too."""
    assert not bool(cannot_catch_up(12.0, 10.0, 40, 10, 3.0))
    assert bool(cannot_catch_up(12.0, 10.0, 40, 10, 1.0))
    assert not bool(cannot_catch_up(12.0, 10.0, 40, 10, 2.0 + 1e-9))
    assert bool(cannot_catch_up(10.0, 10.0, 1000, 10, 9.99))
    assert bool(cannot_catch_up(9.0, 10.0, 40, 10, 9.99))
    # Before `window` steps of history the past loss is `inf`: never behind.
    assert not bool(cannot_catch_up(jnp.inf, 10.0, 40, 10, 1.0))


def test_tie_margin_is_two_sigma_squared_per_parameter():
    lowest, n, p = 3.0, 103.0, 3
    sigma2 = 2 * lowest / (n - p)
    np.testing.assert_allclose(float(tie_margin(lowest, n, p, 0.5)), 2 * sigma2 * p + 0.5)


def test_padding_rows_are_never_evaluated_and_change_nothing():
    """A batch padded to a compiled size (`live`, `path.padded_starts`): the padding rows are not
    stepped (0 steps, diverged, never stopped) and cannot stop a start; the starts come out as
    the unpadded race's, bit for bit."""
    y0s = jnp.array([[3.0], [6.0], [0.7]])
    padded = jnp.concatenate([y0s, jnp.repeat(y0s[:1], 5, axis=0)])
    live = jnp.arange(8) < 3
    ys, result, steps, _, stopped = race(model, SOLVER, y0s, None, MAX_STEPS, _tie())
    ys_p, result_p, steps_p, _, stopped_p = race(
        model, SOLVER, padded, None, MAX_STEPS, _tie(), live=live
    )
    np.testing.assert_array_equal(np.asarray(ys_p[:3]), np.asarray(ys))
    codes, codes_p = np.asarray(result._value), np.asarray(result_p._value)
    np.testing.assert_array_equal(codes_p[:3], codes)
    np.testing.assert_array_equal(np.asarray(steps_p), [*np.asarray(steps), 0, 0, 0, 0, 0])
    np.testing.assert_array_equal(np.asarray(stopped_p), [*np.asarray(stopped), *[False] * 5])
    assert np.all(np.asarray(result_p == optx.RESULTS.nonlinear_divergence)[3:])
