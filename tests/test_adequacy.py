"""The between-tile adequacy check (`jaxdof._fit.adequacy`): its distribution on linear problems,
where it is exact, its power and inflation, the noise-free floor, masks, jit/vmap, and the check
inside `fit_lens` (status, inflated standard errors, the verdict in words)."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest
import scipy.stats

import jaxdof
from jaxdof._fit.adequacy import ALPHA, ROUNDING_FACTOR, adequacy, rounding_noise, tile_grid

from .helpers import EXACT


H = W = 16
P = 3
GRID = (4, 4)  # 4 x 4 px tiles: tile (i, j) holds rows 4i..4i+3 and columns 4j..4j+3


def linear_problem(key, tau=0.0, sigma=0.1):
    """`y = X (beta + u_tile) + noise` with `beta = 0` and per-tile `u ~ N(0, tau^2)`; returns the
    residual `X beta_hat - y` at the least-squares solution, `X`, `beta_hat` and its standard
    errors `sqrt(diag(s^2 (X^T X)^-1))`, `s^2 = SSR / (n - p)`."""
    k1, k2, k3 = jax.random.split(key, 3)
    x = jax.random.normal(k1, (H, W, P)) + jnp.array([1.0, 0.0, -0.5])[None, None, :]
    u = tau * jax.random.normal(k2, (*GRID, P))
    u = jnp.repeat(jnp.repeat(u, H // GRID[0], 0), W // GRID[1], 1)
    y = jnp.sum(x * u, axis=-1) + sigma * jax.random.normal(k3, (H, W))
    x, y = x.reshape(-1, P), y.reshape(-1)
    beta = jnp.linalg.lstsq(x, y)[0]
    r = x @ beta - y
    s2 = jnp.sum(r * r) / (H * W - P)
    se = jnp.sqrt(jnp.diag(s2 * jnp.linalg.inv(x.T @ x)))
    return r, x, beta, se


def keys(n, seed=0):
    return jax.random.split(jax.random.PRNGKey(seed), n)


def binomial_interval(n, p, tail=1e-4):
    """Counts outside this interval have probability < 2 * tail under Binomial(n, p)."""
    return scipy.stats.binom.ppf(tail, n, p), scipy.stats.binom.isf(tail, n, p)


def reference_chow(r, x, mask, grid):
    """Chow's F test written literally in numpy: the pooled least squares and one least squares
    per tile (the residual `r` at the pooled solution, so `y = X beta_hat - r`)."""
    keep = mask.reshape(-1) > 0
    beta = np.linalg.lstsq(x[keep], -r[keep], rcond=None)[0]  # any point: re-solve from it
    y = x @ beta - r
    tile = (
        np.arange(H)[:, None] // (H // grid[0]) * grid[1] + np.arange(W)[None, :] // (W // grid[1])
    ).reshape(-1)
    ssr_pooled = np.sum((x[keep] @ np.linalg.lstsq(x[keep], y[keep], rcond=None)[0] - y[keep]) ** 2)
    ssr_tiles, ranks = 0.0, 0
    for k in range(grid[0] * grid[1]):
        sel = keep & (tile == k)
        b = np.linalg.lstsq(x[sel], y[sel], rcond=None)[0]
        ssr_tiles += np.sum((x[sel] @ b - y[sel]) ** 2)
        ranks += np.linalg.matrix_rank(x[sel])
    dof, dof_noise = ranks - P, keep.sum() - ranks
    f = (ssr_pooled - ssr_tiles) / dof / (ssr_tiles / dof_noise)
    return f * dof, dof, scipy.stats.f.sf(f, dof, dof_noise)


def test_matches_the_literal_chow_test():
    r, x, _, _ = linear_problem(jax.random.PRNGKey(3), tau=0.02)
    mask = np.ones((H, W))
    mask[:3, :] = 0  # some pixels are no data, and tile (0, *) keeps one row of 4
    r = jnp.where(mask.reshape(-1) > 0, r, 0)
    x = jnp.where(mask.reshape(-1, 1) > 0, x, 0)
    out = adequacy(r, x, (1, H, W), mask[None], grid=GRID)
    chi2, dof, p = reference_chow(np.asarray(r), np.asarray(x), mask, GRID)
    # The test rank-truncates nothing here; the two agree to rounding of a few sums of squares.
    assert float(out["dof"]) == dof
    np.testing.assert_allclose(float(out["chi2"]), chi2, rtol=1e-9)
    np.testing.assert_allclose(float(out["p_value"]), p, rtol=1e-7)


@jax.jit
@jax.vmap
def _checks(r, x):
    extra = jnp.stack([x[:, 0], jnp.ones_like(x[:, 0])], axis=1)  # column 0 is also the lens's
    return dict(
        f=adequacy(r, x, (1, H, W), grid=GRID),
        chi2=adequacy(r, x, (1, H, W), grid=GRID, sigma2=0.01),
        extra=adequacy(r, x, (1, H, W), grid=GRID, extra=extra),
    )


_problems = jax.jit(jax.vmap(linear_problem))


def batch(keys, tau):
    """One linear problem per key: the F test, the chi-square test (noise known) and the F test
    with each tile's own offset and gain (`extra`), and the estimate with its standard errors.
    Two compilations serve every batch test (`tau` is traced). (One jit of both stages runs
    ~200x slower on the CPU than the two apart.)"""
    r, x, beta, se = _problems(keys, tau)
    return dict(**_checks(r, x), beta=beta, se=se)


def test_false_alarm_rate_is_alpha():
    """Under the model the p-value is uniform (exact for a linear model with Gaussian noise):
    the F test (noise estimated), the chi-square test (noise known) and the F test with each
    tile's own exposure fire at their levels over 400 problems."""
    n = 400
    out = batch(keys(n), jnp.zeros(n))
    assert float(out["extra"]["dof"][0]) == 16 * (P + 1) - P
    for test in ("f", "chi2", "extra"):
        p = np.asarray(out[test]["p_value"])
        for level in (ALPHA, 0.1):
            lo, hi = binomial_interval(n, level)
            assert lo <= np.sum(p < level) <= hi, (test, level, np.sum(p < level))


def test_independent_of_the_solvers_stopping_point():
    """Away from the exact solution by a step in the column space, the statistic is unchanged:
    the global Gauss-Newton step is taken out."""
    r, x, _, _ = linear_problem(jax.random.PRNGKey(4), tau=0.02)
    at = adequacy(r, x, (1, H, W), grid=GRID)
    off = adequacy(r + x @ jnp.array([0.3, -0.2, 0.1]), x, (1, H, W), grid=GRID)
    np.testing.assert_allclose(float(off["chi2"]), float(at["chi2"]), rtol=1e-9)


def test_fires_on_tiles_with_their_own_parameters_and_inflation_covers():
    """Tiles with different true parameters (random effects of sd 0.1, noise 0.1): the check
    fires on every problem; the fit's standard errors cover the truth (beta = 0) within 3 in
    about half of them, the inflated ones in all (they follow the spread of the tiles'
    parameters, so they are wide: the median inflation is about 11)."""
    n = 400  # the false-alarm test's batch: the same compilation
    out = batch(keys(n, 5), jnp.full(n, 0.1))
    check = out["f"]
    assert np.all(~np.asarray(check["adequate"]))
    assert np.all(np.asarray(check["p_value"]) < 1e-6)
    z = np.max(np.abs(np.asarray(out["beta"])) / np.asarray(out["se"]), axis=1)
    inflation = np.asarray(check["inflation"])
    assert np.all(inflation > 1)
    assert np.mean(z <= 3) < 0.7  # measured 0.51 with these seeds
    assert np.mean(z / inflation <= 3) >= 0.98  # measured 1.0


def test_inflation_is_one_when_the_check_passes():
    r, x, _, _ = linear_problem(jax.random.PRNGKey(6))
    out = adequacy(r, x, (1, H, W), grid=GRID)
    assert bool(out["adequate"])
    assert float(out["inflation"]) == 1.0
    assert float(out["spread"]) >= 1.0


def test_noise_free_floor():
    """Residuals at the rounding level with tile structure (what a noise-free target leaves):
    without a floor the estimated noise is rounding too and the check fires; with
    `rounding_noise` it does not. Exactly zero residuals give no NaN."""
    k1, k2 = jax.random.split(jax.random.PRNGKey(7))
    x = jax.random.normal(k1, (H * W, P))
    target = jnp.full((H, W), 0.5)
    eps = float(jnp.finfo(jnp.float64).eps)
    tile = jnp.repeat(jnp.repeat(jax.random.normal(k2, (*GRID, P)), 4, 0), 4, 1).reshape(-1, P)
    r = 0.5 * eps * jnp.sum(x * tile, axis=1)  # a different "lens" in every tile, at rounding
    r = r - x @ jnp.linalg.lstsq(x, r)[0]
    assert not bool(adequacy(r, x, (1, H, W), grid=GRID)["adequate"])
    floor = rounding_noise(target)
    np.testing.assert_allclose(float(floor), ROUNDING_FACTOR * eps * 0.5)
    out = adequacy(r, x, (1, H, W), grid=GRID, noise_floor=floor)
    assert bool(out["adequate"]) and float(out["inflation"]) == 1.0
    zero = adequacy(jnp.zeros(H * W), x, (1, H, W), grid=GRID)
    assert bool(zero["adequate"])
    assert all(np.isfinite(float(v)) for v in zero.values())


def test_zero_weight_pixels_are_not_residuals():
    """Pixels outside the mask change nothing, whatever their residual and Jacobian hold, and
    `n` counts only the others (the F test's noise degrees of freedom)."""
    r, x, _, _ = linear_problem(jax.random.PRNGKey(8), tau=0.01)
    mask = np.ones((1, H, W))
    mask[0, :, :5] = 0
    keep = mask.reshape(-1) > 0
    r0, x0 = jnp.where(keep, r, 0), jnp.where(keep[:, None], x, 0)
    clean = adequacy(r0, x0, (1, H, W), mask, grid=GRID)
    junk = adequacy(
        jnp.where(keep, r0, 1e3), jnp.where(keep[:, None], x0, -7.0), (1, H, W), mask, grid=GRID
    )
    for k in clean:
        np.testing.assert_allclose(float(junk[k]), float(clean[k]), rtol=1e-12)
    # Without the mask the zeros would count as residuals: another (wrong) noise estimate.
    unmasked = adequacy(r0, x0, (1, H, W), grid=GRID)
    assert float(unmasked["p_value"]) != pytest.approx(float(clean["p_value"]), rel=1e-6)


def test_tiles_band_and_grid():
    assert tile_grid((12, 12)) == (3, 3)
    assert tile_grid((24, 100)) == (3, 8)
    assert tile_grid((1000, 40)) == (8, 5)
    assert tile_grid((5, 9)) == (1, 2)
    r, x, _, _ = linear_problem(jax.random.PRNGKey(9))
    # A band of 2 px: the 12 x 12 inside is split 3 x 3 (the band joins the edge tiles).
    out = adequacy(r, x, (1, H, W), band=2)
    assert int(out["tiles"]) == 9 and float(out["dof"]) == 9 * P - P
    # A tile with no data is not counted.
    mask = np.ones((1, H, W))
    mask[0, :4, :4] = 0
    out = adequacy(jnp.where(mask.reshape(-1) > 0, r, 0), x, (1, H, W), mask, grid=GRID)
    assert int(out["tiles"]) == 15 and float(out["dof"]) == 15 * P - P
    with pytest.raises(ValueError, match="shape"):
        adequacy(r, x, (H, W), grid=GRID)
    with pytest.raises(ValueError, match="grid"):
        adequacy(r, x, (1, H, W), grid=(17, 1))


def test_rank_deficient_tiles_and_used_columns():
    """A column that a tile does not see (zero there) lowers that tile's rank, not the test's
    validity; `used` picks the free columns."""
    r, x, _, _ = linear_problem(jax.random.PRNGKey(10))
    x = x.at[: H * W // 2, 2].set(0.0)  # the top half does not see parameter 2
    r = r - x @ jnp.linalg.lstsq(x, r)[0]
    out = adequacy(r, x, (1, H, W), grid=GRID)
    assert float(out["dof"]) == 8 * (P - 1) + 8 * P - P
    wide = jnp.concatenate([x, jnp.zeros((H * W, 2))], axis=1)
    used = adequacy(r, wide, (1, H, W), grid=GRID, used=(0, 1, 2))
    for k in out:
        np.testing.assert_allclose(float(used[k]), float(out[k]), rtol=1e-12)


def test_jit_and_vmap_agree_with_eager():
    n = 400  # the batch tests' compilation
    ks = keys(n, 11)
    batched = batch(ks, jnp.full(n, 0.02))["extra"]
    for i in range(2):
        r, x, _, _ = linear_problem(ks[i], 0.02)
        extra = jnp.stack([x[:, 0], jnp.ones_like(x[:, 0])], axis=1)
        eager = adequacy(r, x, (1, H, W), grid=GRID, extra=extra)
        for k in eager:
            np.testing.assert_allclose(float(batched[k][i]), float(eager[k]), rtol=1e-9)


def test_float32_agrees_with_float64():
    """On float32 inputs the statistic keeps about 4 digits: its sums of squares are formed
    from tile factors, not from J^T J. The float64 reference sees the same (float32) values."""
    r, x, _, _ = linear_problem(jax.random.PRNGKey(12), tau=0.02)
    r, x = r.astype(jnp.float32), x.astype(jnp.float32)
    ref = adequacy(r.astype(jnp.float64), x.astype(jnp.float64), (1, H, W), grid=GRID)
    floor = rounding_noise(jnp.full((H, W), 0.5, jnp.float32))
    out = adequacy(r, x, (1, H, W), grid=GRID, noise_floor=floor)
    assert ref["chi2"].dtype == jnp.float64 and out["chi2"].dtype == jnp.float32
    for k in ("chi2", "p_value", "spread"):
        np.testing.assert_allclose(float(out[k]), float(ref[k]), rtol=1e-3)
    assert float(out["dof"]) == float(ref["dof"])


# ---------------------------------------------------------------------------------------------
# The check inside fit_lens, end to end.
# ---------------------------------------------------------------------------------------------

S = 24
PITCH = 8e-5
F = 0.05
WINDOW = 6.0
FREE = ("f_number", "focus_distance")


def slant_scene():
    rng = np.random.default_rng(1)
    image = 0.2 + 0.6 * rng.uniform(size=(S, S))
    image = 0.5 * image + 0.125 * (
        np.roll(image, 1, 0) + np.roll(image, 1, 1) + np.roll(image, -1, 0) + np.roll(image, -1, 1)
    )
    depth = np.broadcast_to(1.0 + 2.0 * np.arange(S) / (S - 1), (S, S)).copy()
    return image, depth, rng


def fit_from_truth(image, depth, target, truth, border=0, **options):
    """`fit_lens` from the truth, one start (the check, not the search for the basin, is under
    test), and its largest |error| / reported standard error over (N, d_f). `border=0` by
    default: every pixel, as in the study's main table (fits/results/adequacy_border0.md)."""
    kw = dict(free=FREE, max_radius=WINDOW, starts=1, border=border, **EXACT, **options)
    fit = jaxdof.fit_lens(image, depth, target, truth, **kw)
    err = np.array(
        [
            float(fit.lens.f_number) - float(truth.f_number),
            float(fit.lens.focus_distance) - float(truth.focus_distance),
        ]
    )
    se = np.array([float(fit.stderr["f_number"]), float(fit.stderr["focus_distance"])])
    return fit, float(np.max(np.abs(err) / se))


def vignetted_target(strength):
    """The slant scene's soft render darkened towards the corners by `1 - strength rho^2` (rho = 1
    in the corners: vignetting, which the model lacks), plus noise 0.003."""
    image, depth, rng = slant_scene()
    truth = jaxdof.ThinLens(F, 2.0, 1.6, PITCH)
    clean = np.asarray(jaxdof.render(image, depth, truth, max_radius=WINDOW))
    noise = rng.standard_normal(clean.shape)
    yy, xx = np.mgrid[0:S, 0:S] - (S - 1) / 2
    rho2 = (yy**2 + xx**2) / (2 * ((S - 1) / 2) ** 2)
    return image, depth, clean * (1 - strength * rho2) + 0.003 * noise, truth


def test_a_fit_the_model_explains_passes_and_vignetting_fires():
    """On a slanted plane: a noisy soft render passes the check (status successful, standard
    errors from the noise); the same render darkened towards the corners (vignetting, which the
    model does not have) fires: status `inconsistent`, the standard errors inflated to the tile
    spread (with which the lens can be used: success True), and the verdict in `message`,
    `summary` and `to_dict`."""
    image, depth, target, truth = vignetted_target(0.0)
    fit, z = fit_from_truth(image, depth, target, truth)
    assert fit.status == jaxdof.RESULTS.successful and bool(fit.success) and z < 4
    assert bool(fit.adequacy["adequate"]) and float(fit.adequacy["inflation"]) == 1.0
    assert fit.stderr_kind == "noise" and fit.to_dict()["adequacy"]["adequate"] is True
    _, _, target, _ = vignetted_target(0.5)
    bad, z_bad = fit_from_truth(image, depth, target, truth, vignetting=False)  # the model lacks it
    assert bad.status == jaxdof.RESULTS.inconsistent and bool(bad.success)
    assert not bool(bad.adequacy["adequate"]) and float(bad.adequacy["p_value"]) < 1e-4
    inflation = float(bad.adequacy["inflation"])
    assert inflation > 1 and bad.stderr_kind == "tile spread"
    # The covariance carries the inflation squared: its diagonal is the stderr squared.
    np.testing.assert_allclose(
        np.sqrt(np.diag(np.asarray(bad.covariance))),
        [float(bad.stderr["f_number"]), float(bad.stderr["focus_distance"])],
        rtol=1e-10,
    )
    assert "not fully explained by the model" in bad.message and "inflated" in bad.message
    summary = bad.to_dict()
    assert summary["status"] == "inconsistent" and summary["stderr_kind"] == "tile spread"
    assert "INCONSISTENT" in bad.summary()
    # A known gap (issue 20), pinned so that closing it is noticed: at 50 % corner darkening
    # the fit's N is about 40 % low while the tiles' spread explains a third of that, so the
    # inflated standard errors do not cover the error (|error| / stderr about 3.75, where a
    # covered error is within 3; fits/results/adequacy.md measures the coverage over scenes).
    assert z_bad > 3, f"the inflation now covers strong vignetting ({z_bad:.2f}): update issue 20"


def test_moderate_vignetting_is_flagged_and_covered():
    """Vignetting as in fits/adequacy.py (`1 - 0.3 rho^2`) that the model lacks (forced off):
    flagged, and the inflated standard errors cover the actual error (within 3). By default the
    photo asks for the vignetting: fitted, and the fit explains the photo."""
    image, depth, target, truth = vignetted_target(0.3)
    fit, z = fit_from_truth(image, depth, target, truth, vignetting=False)
    assert fit.status == jaxdof.RESULTS.inconsistent
    assert z <= 3
    fit, z = fit_from_truth(image, depth, target, truth)
    assert fit.nuisances is not None and fit.nuisances["vignetting"]["fitted"]
    assert fit.status == jaxdof.RESULTS.successful and z <= 3


@pytest.mark.parametrize("dtype", [np.float32, np.float64])
def test_p_value_with_many_noise_degrees_of_freedom(dtype):
    """A fit on a megapixel has millions of noise degrees of freedom: float32's incomplete beta
    function loses the F survival there (it gave p = -2.9 for F = 0.97 on a 6 MP fit, and the
    test fired); the chi-square limit takes over. Against scipy's F survival, in [0, 1]."""
    from jaxdof._fit.adequacy import _p_value

    for d2 in (1e2, 1e3, 1e5, 3e6):
        for dof in (2.0, 222.0):
            chi2 = 0.97 * dof
            p = float(_p_value(*(jnp.asarray(x, dtype) for x in (chi2, dof, d2)), known=False))
            ref = scipy.stats.f.sf(chi2 / dof, dof, d2)
            assert 0 <= p <= 1 and abs(p - ref) < 2e-3, (d2, dof, p, ref)
