r"""Does the model explain the photo? A between-tile consistency test from the fit's Jacobian.

A lens fit assumes that every part of the photo is rendered by one lens plus independent noise.
When the forward model is wrong (another aperture shape, vignetting, occlusion that the model does
not render, a border left in), parts of the photo pull the fit towards different lenses, and the
Gauss-Newton standard errors, which only know the pixel noise, understate the real error. This
module tests that assumption at the solution, from the Jacobian that the fit has already
materialised (no extra solves), and gives standard errors that follow the tile spread when the
test fails.

**The test** (Chow 1960, in its score form). Split the residual pixels into `K` spatial tiles
(every target and channel of a tile together, so that each tile is a small copy of the whole
problem). With `J_k`, `r_k` the rows of the weighted Jacobian and residual in tile `k`,
`A_k = J_k^T J_k`, `b_k = J_k^T r_k`, the tile's one-step (Gauss-Newton) estimate relative to the
global solution is `delta_k = -A_k^+ b_k`, with covariance `sigma^2 A_k^+`. The statistic

$$\chi^2 = \frac{1}{\sigma^2}\Big(\sum_k b_k^T A_k^+ b_k \;-\; b^T A^+ b\Big),\qquad
  b = \sum_k b_k,\ A = \sum_k A_k,$$

is the drop in the (linearised) sum of squares when every tile gets its own lens: Chow's test of
equality between sets of coefficients, evaluated as Rao's score (Lagrange multiplier) test at the
pooled estimate, so no tile is solved. For a linear model with Gaussian noise it is exactly
`chi^2` distributed (asymptotically for the fit), with `dof = sum_k rank(A_k) - rank(A)`. At an
exact least-squares solution `b = 0`; the `b^T A^+ b` term removes the solver's stopping error to
first order (the loss one more Gauss-Newton step would remove), so the test does not depend on
the tolerance. Optional `extra` columns (a tile's own exposure: gain and offset) join each tile's
lens in the unrestricted model, so that photometric model error (vignetting, a wrong exposure)
shows too; `dof` counts them.

**The noise variance.** `sigma^2` is unknown in a photo: by default it is estimated within the
tiles, `SSR_u / (n - sum_k rank_k)` with `SSR_u = SSR - sum_k b_k^T A_k^+ b_k` (the unrestricted
model's residual, which model error inflates less than the pooled one), and then
`chi^2 / dof ~ F(dof, n - sum_k rank_k)` exactly (linear model, Gaussian noise: the classical
Chow F test). A known noise variance (`sigma2=`) gives the `chi^2(dof)` test. `n` counts only
residuals with non-zero weight. A noise-free target leaves residuals at the rounding level, whose
structure is no noise model: `noise_floor` (`rounding_noise(targets)`) keeps `sigma` above it.

**Ranks.** Columns are scaled to unit norm over the whole image (the test is invariant to a
reparametrisation; the scaling makes the ranks so too), and a direction of a tile counts when
its singular value exceeds `sqrt(eps)` times the global largest one. A tile of one depth plane
determines only the blur radius there (rank 1 in `(N, d_f)`); a textureless or in-focus tile
nothing (rank 0: not counted in `tiles`). Truncating a tile's weak directions makes the test
slightly conservative and keeps rounding out of it. The sums of squares are formed from the
tiles' SVD factors (`J^T J = M^T M` with `M` the stacked `S_k V_k^T`), never by squaring `J`.

**Tiles.** A `ty x tx` grid of near-equal rectangles over the region inside the fit's border band
(`tile_grid`): `L // 8` tiles along an axis of `L` pixels, at least 3 where `L >= 12`, at most 8.
8 x 8 px tiles hold 64 pixels per target and channel for a handful of parameters; 64 tiles give
the spread estimate below 63 degrees of freedom. Tiles partition the residuals, not the scene:
that a circle reaches into a tile from outside does not matter, since the noise of distinct
pixels is independent.

**The honest standard errors** when the test fires. `Omega`, the covariance of the tiles' lenses
about their mean beyond the noise, estimated by moments from the tile scores at the linearised
exact solution, `g_k = b_k - A_k A^+ b`:

$$\tfrac{K}{K-1}\sum_k g_k g_k^T = \sum_k A_k\,\Omega\,A_k
  + \sigma^2\Big(A - \sum_k A_k A^+ A_k\Big)$$

(solved for `Omega`, clipped to be positive semi-definite): the between-study variance of a
random-effects meta-analysis (DerSimonian and Laird 1986), with tiles as studies. Model error
moves the whole photo's lens by an amount of the order of that by which it moves the tiles'
lenses apart, not by their standard error of the mean: so the reported uncertainty is that of
the prediction interval of a random-effects analysis (Higgins, Thompson and Spiegelhalter 2009),
`V_fit + Omega`, with `V_fit = SSR / (n - p) A^+` the covariance the fit reports. The
`inflation` `s >= 1` is the smallest factor with `s^2 V_fit >= V_fit + Omega` in every direction
(the largest generalised eigenvalue, so it holds for every field and every derived quantity such
as `K`), and at least the Birge ratio `sqrt(chi^2 / dof)` measured against `V_fit`'s variance.
Multiply the fit's standard errors by it and its covariance by its square, in any coordinates.
It is 1 where the test does not fire. It cannot see a model error that every tile shares (a
pentagonal aperture blurs like a smaller disc everywhere: the fit's f-number is that of the disc
of equal area, `fits/results/adequacy.md`).

Sources: G. C. Chow, "Tests of equality between sets of coefficients in two linear regressions",
Econometrica 28 (1960) 591-605; C. R. Rao, "Large sample tests of statistical hypotheses
concerning several parameters", Proc. Camb. Phil. Soc. 44 (1948) 50-57; R. DerSimonian and
N. Laird, "Meta-analysis in clinical trials", Controlled Clinical Trials 7 (1986) 177-188;
J. P. T. Higgins, S. G. Thompson and D. J. Spiegelhalter, "A re-evaluation of random-effects
meta-analysis", J. R. Stat. Soc. A 172 (2009) 137-159; R. T. Birge, "The calculation of errors
by the method of least squares", Phys. Rev. 40 (1932) 207-227.
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import jax.numpy as jnp
import jax.scipy.special as jsp
import numpy as np
from jaxtyping import Array, Float

from .._custom_types import AnyFloatLike, ScalarLike


#: The nominal false-alarm rate of the test (its significance level).
ALPHA = 0.01
#: The preferred tile side (pixels) and the most tiles per axis (`tile_grid`).
TILE_SIDE = 8
MAX_TILES = 8
#: `rounding_noise`'s multiple of `eps * rms(targets)`. Measured (`fits/adequacy.py`'s scenes,
#: noise-free targets, fits at the rounding floor): residuals of 0.8-23 eps rms(targets) in float64
#: and 0.8-1.5 in float32 once the global Gauss-Newton step is taken out (the solver's stopping
#: error, up to 3000 eps in float64, is, see the module docstring); without a floor the check fired
#: on 5 of 24 such fits, with 64 on none (chi^2 <= 0.015 with 13-16 dof). In float32 the floor is
#: 7.6e-6 of the signal, far under the noise of any photo.
ROUNDING_FACTOR = 64.0


def tile_grid(
    photo: tuple[int, int], *, side: int = TILE_SIDE, most: int = MAX_TILES
) -> tuple[int, int]:
    """The default grid `(ty, tx)` for a tiled region of `(H, W)` pixels: along an axis of `L`
    pixels, `L // side` tiles, but at least 3 (of at least 4 pixels) where `L >= 12`, so that a
    small region is still tested; at most `most`, at least 1."""
    ty, tx = (int(min(max(n // side, min(3, n // 4), 1), most)) for n in photo)
    return ty, tx


def rounding_noise(targets: AnyFloatLike, mask: AnyFloatLike | None = None) -> Array:
    """A floor for the noise standard deviation at the rounding level of the targets.

    `ROUNDING_FACTOR * eps * rms(targets)` over the pixels with `mask` (non-zero weight), `eps`
    the targets' machine epsilon. A noise-free target rendered by the model leaves residuals of
    a few `eps` relative (the render's own rounding); the factor keeps the estimated noise
    above that, so the test does not fire on rounding. Real noise (1e-3 of the signal in a
    good photo) is far above it in float32 (`64 eps = 8e-6`) and in float64.
    """
    targets = jnp.asarray(targets)
    if not jnp.issubdtype(targets.dtype, jnp.floating):
        targets = targets.astype(float)
    keep = jnp.ones(targets.shape, bool) if mask is None else jnp.asarray(mask) != 0
    keep = jnp.broadcast_to(keep, targets.shape)
    count = jnp.maximum(jnp.sum(keep), 1).astype(targets.dtype)
    rms = jnp.sqrt(jnp.sum(jnp.where(keep, targets * targets, 0)) / count)
    return ROUNDING_FACTOR * float(jnp.finfo(targets.dtype).eps) * rms


def _tile_index(n: int, tiles: int, band: int) -> np.ndarray:
    """`(tiles, size)` pixel indices of near-equal runs covering `band .. n - band - 1`, the first
    and last runs extended over the band (pixels there are zero-weight in a fit with that border,
    but they must belong to some tile), padded with `n` (a zero row appended by the caller)."""
    edges = np.round(np.linspace(band, n - band, tiles + 1)).astype(int)
    edges[0], edges[-1] = 0, n
    size = int(np.max(np.diff(edges)))
    out = np.full((tiles, size), n, np.int32)
    for i in range(tiles):
        out[i, : edges[i + 1] - edges[i]] = np.arange(edges[i], edges[i + 1])
    return out


def adequacy(
    residual: Float[Array, " n"],
    jac: Float[Array, "n P"],
    shape: Sequence[int],
    mask: AnyFloatLike | None = None,
    *,
    used: Sequence[int] | None = None,
    extra: Float[Array, "n E"] | None = None,
    sigma2: ScalarLike | None = None,
    noise_floor: ScalarLike = 0.0,
    grid: tuple[int, int] | None = None,
    band: int = 0,
    alpha: float = ALPHA,
) -> dict[str, Array]:
    """Test whether one lens explains every tile of the photos; the honest inflation if not.

    See the module docstring for the statistic, its distribution and the sources. A pure
    function of arrays: `jit` it with `shape`, `used`, `grid`, `band` and `alpha` static (Python
    values; whether `extra`, `mask` and `sigma2` are given is structure too), `vmap` it over fits.

    **Arguments:**

    - `residual`: the weighted residuals at the solution, `(n,)`, `sqrt(w) (model - target)`
      flattened from `shape`.
    - `jac`: d residual / d y at the solution, `(n, P)`, in any coordinates (the solver's).
    - `shape`: the layout of the residuals, `(T, H, W)` or `(T, H, W, C)` (the targets' shape).
    - `mask`: the residuals that are data (non-zero weight), broadcastable to `shape` (e.g. the
      fit's `sqrt_w > 0`); `None`: all. Only these count in `n`; others must be zero in
      `residual` and `jac` (they are zeroed here too).
    - `used`: the columns of `jac` that are free parameters (`_Spec.used`); `None`: all.
    - `extra`: optional columns `(n, E)` that every tile may add to its own lens in the
      unrestricted model: a tile's own exposure, `sqrt_w * prediction` (gain) and `sqrt_w`
      (offset), makes the test see photometric model error (vignetting, a wrong exposure) as
      well as blur that no one lens explains. `None`: the lens only.
    - `sigma2`: a known noise variance of the weighted residuals (chi-square test); `None`
      (default): estimated within tiles (F test).
    - `noise_floor`: a floor for the noise standard deviation, e.g. `rounding_noise(targets)`.
    - `grid`: `(ty, tx)` tiles; `None`: `tile_grid` of the region inside the band.
    - `band`: the width (pixels) of the border band that the fit left out (`FitResult.border`):
      the tiles split the region inside it (pixels in the band join the nearest tile).
    - `alpha`: the significance level (default `ALPHA = 0.01`).

    **Returns:** a dict of arrays: `chi2` (the statistic in units of the noise variance), `dof`,
    `p_value` (`chi^2` or `F` survival), `tiles` (tiles with information), `inflation` (`>= 1`;
    1 unless the test fires: multiply the fit's standard errors by it, its covariance by its
    square), `spread` (the tile-spread factor whether or not the test fires, for diagnostics),
    `adequate` (`p_value >= alpha`, or too few degrees of freedom to test).
    """
    shape = tuple(int(s) for s in shape)
    if len(shape) not in (3, 4):
        raise ValueError(f"shape must be (T, H, W) or (T, H, W, C), got {shape}")
    t, h, w = shape[:3]
    c = shape[3] if len(shape) == 4 else 1
    n_res = t * h * w * c
    if residual.shape != (n_res,) or jac.ndim != 2 or jac.shape[0] != n_res:
        raise ValueError(
            f"residual {residual.shape} and jac {jac.shape} must be (n,) and (n, P) with "
            f"n = prod(shape) = {n_res}"
        )
    cols = tuple(range(jac.shape[1])) if used is None else tuple(int(i) for i in used)
    band = int(band)
    if not 0 <= 2 * band < min(h, w):
        raise ValueError(f"band={band} must be >= 0 and leave pixels inside a {h} x {w} photo")
    inner = (h - 2 * band, w - 2 * band)
    ty, tx = tile_grid(inner) if grid is None else (int(grid[0]), int(grid[1]))
    if not (1 <= ty <= inner[0] and 1 <= tx <= inner[1]):
        raise ValueError(f"grid {(ty, tx)} must have 1..{inner[0]} x 1..{inner[1]} tiles")
    dtype = residual.dtype
    keep = jnp.ones(shape, bool) if mask is None else jnp.asarray(mask) != 0
    keep = jnp.broadcast_to(keep, shape).reshape(t, h, w, c)
    r = jnp.where(keep, residual.reshape(t, h, w, c), 0)
    p = len(cols)
    jac = jac[:, jnp.asarray(cols, jnp.int32)].astype(dtype) if p else jac[:, :0].astype(dtype)
    jac = jnp.where(keep[..., None], jac.reshape(t, h, w, c, p), 0)
    n = jnp.sum(keep).astype(dtype)
    ssr = jnp.sum(r * r)
    one = jnp.ones((), dtype)
    if p == 0:  # nothing free: nothing to test
        return dict(
            chi2=0 * one,
            dof=0 * one,
            p_value=one,
            tiles=jnp.zeros((), jnp.int32),
            inflation=one,
            spread=one,
            adequate=jnp.ones((), bool),
        )

    # Column scaling: unit columns over the whole image, so the ranks do not depend on units.
    scale = jnp.sqrt(jnp.sum(jac * jac, axis=(0, 1, 2, 3)))
    jac = jac / jnp.where(scale > 0, scale, 1)[None, None, None, None, :]

    # Gather (T, H, W, C, ...) into (K, m, ...): every target and channel of a tile together.
    ri, ci = _tile_index(h, ty, band), _tile_index(w, tx, band)

    def tiles(x):
        x = jnp.pad(x, [(0, 0), (0, 1), (0, 1)] + [(0, 0)] * (x.ndim - 3))  # the zero row/col
        x = x[:, ri[:, :, None, None], ci[None, None, :, :]]  # (T, ty, hs, tx, ws, ...)
        x = jnp.moveaxis(x, (1, 3), (0, 1))  # (ty, tx, T, hs, ws, ...)
        return x.reshape((ty * tx, -1) + x.shape[6:])

    jt = tiles(jac)  # (K, m, p)
    rt = tiles(r)  # (K, m)

    u, s, vt = jnp.linalg.svd(jt, full_matrices=False)  # (K, m, k), (K, k), (K, k, p)
    cproj = jnp.einsum("kmi,km->ki", u, rt)  # U_k^T r_k: b_k^T A_k^+ b_k = |c_k|^2
    # The global problem from the tiles' factors: J^T J = M^T M, J^T r = M^T c (no squaring).
    big_m = (s[:, :, None] * vt).reshape(-1, p)
    um, sm, vtm = jnp.linalg.svd(big_m, full_matrices=False)
    tol = math.sqrt(float(jnp.finfo(dtype).eps)) * sm[0]
    good = sm > tol
    kept = s > tol
    cg = um.T @ cproj.reshape(-1)
    q_global = jnp.sum(jnp.where(good, cg * cg, 0))
    rank = jnp.sum(good).astype(dtype)
    informative = jnp.sum(jnp.any(kept, axis=1))
    if extra is None:
        q_tiles = jnp.sum(jnp.where(kept, cproj * cproj, 0))
        rank_tiles = jnp.sum(kept).astype(dtype)
    else:
        # The unrestricted model: each tile its own lens and its own `extra` columns.
        e = extra.shape[1]
        x = jnp.where(keep[..., None], extra.astype(dtype).reshape(t, h, w, c, e), 0)
        x_scale = jnp.sqrt(jnp.sum(x * x, axis=(0, 1, 2, 3)))
        x = x / jnp.where(x_scale > 0, x_scale, 1)[None, None, None, None, :]
        ua, sa, _ = jnp.linalg.svd(jnp.concatenate([jt, tiles(x)], axis=2), full_matrices=False)
        ca = jnp.einsum("kmi,km->ki", ua, rt)
        kept_a = sa > tol
        q_tiles = jnp.sum(jnp.where(kept_a, ca * ca, 0))
        rank_tiles = jnp.sum(kept_a).astype(dtype)

    dof = rank_tiles - rank
    dof_noise = n - rank_tiles
    chi2_num = jnp.maximum(q_tiles - q_global, 0)
    if sigma2 is None:
        var = jnp.maximum(ssr - q_tiles, 0) / jnp.maximum(dof_noise, 1)
    else:
        var = jnp.asarray(sigma2, dtype)
    floor = jnp.asarray(noise_floor, dtype)
    var = jnp.maximum(var, floor * floor)
    chi2 = jnp.where(var > 0, chi2_num / jnp.where(var > 0, var, 1), 0)
    safe_dof = jnp.maximum(dof, 1)
    if sigma2 is None:
        d2 = jnp.maximum(dof_noise, 1)
        # F(dof, d2) survival: I_{d2 / (d2 + dof F)}(d2 / 2, dof / 2), with dof F = chi2.
        p_value = jsp.betainc(d2 / 2, safe_dof / 2, d2 / (d2 + chi2))
    else:
        p_value = jsp.gammaincc(safe_dof / 2, chi2 / 2)
    testable = (dof >= 1) & (dof_noise >= 1)
    p_value = jnp.where(testable, p_value, 1)
    adequate = p_value >= alpha

    # The tile spread. Tile scores at the linearised exact solution: g_k = b_k - A_k A^+ b.
    inv_s = jnp.where(good, 1 / jnp.where(good, sm, 1), 0)
    a_pinv = (vtm.T * (inv_s * inv_s)[None, :]) @ vtm
    a_all = big_m.T @ big_m
    a_k = jnp.einsum("kij,ki,kil->kjl", vt, s * s, vt)  # (K, p, p)
    scores = jnp.einsum("kij,ki->kj", vt, s * cproj)  # J_k^T r_k
    scores = scores - jnp.einsum("kij,j->ki", a_k, a_pinv @ (big_m.T @ cproj.reshape(-1)))
    k_eff = informative.astype(dtype)
    small = k_eff / jnp.maximum(k_eff - 1, 1)  # the K / (K - 1) of a mean estimated from K
    # Omega, the covariance of the tiles' lenses about their mean beyond the noise, by moments:
    # E sum_k g_k g_k^T = sum_k A_k Omega A_k + var (A - sum_k A_k A^+ A_k), solved for Omega
    # (p^2 unknowns) and clipped to be positive semi-definite.
    noise = var * (a_all - jnp.einsum("kij,jl,klm->im", a_k, a_pinv, a_k))
    rhs = small * (scores.T @ scores - noise)
    kron = jnp.einsum("kab,kcd->acbd", a_k, a_k).reshape(p * p, p * p)
    omega = (jnp.linalg.pinv(kron) @ rhs.reshape(-1)).reshape(p, p)
    ev, evec = jnp.linalg.eigh(0.5 * (omega + omega.T))
    omega = (evec * jnp.maximum(ev, 0)[None, :]) @ evec.T
    # V_fit = var_fit A^+ (what the fit reports). The largest eigenvalue of
    # V_fit^{-1/2} Omega V_fit^{-1/2}, in the basis of A's singular vectors: S V^T Omega V S.
    var_fit = ssr / jnp.maximum(n - rank, 1)
    safe_var = jnp.where(var_fit > 0, var_fit, 1)
    sv = sm[:, None] * (vtm @ omega @ vtm.T) * sm[None, :]
    sv = jnp.where(good[:, None] & good[None, :], sv, 0)
    tiles_ratio = 1 + jnp.linalg.eigvalsh(sv)[-1] / safe_var
    birge = chi2_num / safe_dof / safe_var
    spread = jnp.sqrt(jnp.maximum(jnp.maximum(tiles_ratio, birge), 1))
    spread = jnp.where((k_eff >= 2) & (var_fit > 0), spread, 1)
    return dict(
        chi2=chi2,
        dof=dof,
        p_value=p_value,
        tiles=informative.astype(jnp.int32),
        inflation=jnp.where(adequate, one, spread),
        spread=spread,
        adequate=adequate,
    )
