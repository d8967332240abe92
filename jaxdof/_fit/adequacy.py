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

import functools
import math
from collections.abc import Sequence
from typing import NamedTuple

import jax
import jax.numpy as jnp
import jax.scipy.special as jsp
import numpy as np
from jaxtyping import Array, Float

from .._custom_types import AnyFloatLike, ScalarLike
from .linalg import pinv, symmetric_eigh, thin_svd


#: The nominal false-alarm rate of the test (its significance level).
ALPHA = 0.01
#: Noise degrees of freedom above which a float32 F test uses its chi-square limit (`_p_value`).
_F_LIMIT_FLOAT32 = 1e4
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


def _nonzero(mask: AnyFloatLike) -> Array:
    """`mask != 0` as a boolean array (a boolean mask as it is: no bool/int promotion)."""
    mask = jnp.asarray(mask)
    return mask if mask.dtype == bool else mask != 0


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
    keep = jnp.ones(targets.shape, bool) if mask is None else _nonzero(mask)
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


class _Factors(NamedTuple):
    """The tiles' SVD factors and the global problem formed from them (`J^T J = M^T M`)."""

    s: Array  # (K, k) the tiles' singular values
    vt: Array  # (K, k, p) their right singular vectors
    cproj: Array  # (K, k) U_k^T r_k: b_k^T A_k^+ b_k = |c_k|^2
    big_m: Array  # (K k, p) the stacked S_k V_k^T
    sm: Array  # (r,) the global singular values
    vtm: Array  # (r, p) the global right singular vectors
    tol: Array  # the rank threshold, sqrt(eps) times the largest global singular value
    good: Array  # (r,) the global directions that count
    kept: Array  # (K, k) the tiles' directions that count
    q_global: Array  # b^T A^+ b
    rank: Array  # rank(A)
    informative: Array  # tiles with rank >= 1


def _check_layout(
    residual: Array,
    jac: Array,
    shape: Sequence[int],
    used: Sequence[int] | None,
    grid: tuple[int, int] | None,
    band: int,
) -> tuple[tuple[int, ...], int, tuple[int, ...], tuple[int, int], int]:
    """Check the static arguments: `(shape, C, free columns, (ty, tx), band)`."""
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
    return shape, c, cols, (ty, tx), band


def _unit_columns(x: Array) -> Array:
    """Scale the last axis's columns of `(T, H, W, C, q)` to unit norm over the whole image (so
    the ranks do not depend on units); zero columns stay zero."""
    scale = jnp.sqrt(jnp.sum(x * x, axis=(0, 1, 2, 3)))
    return x / jnp.where(scale > 0, scale, 1)[None, None, None, None, :]


def _gather_tiles(x: Array, ri: np.ndarray, ci: np.ndarray) -> Array:
    """Gather `(T, H, W, ...)` into `(K, m, ...)`: every target and channel of a tile together."""
    ty, tx = ri.shape[0], ci.shape[0]
    x = jnp.pad(x, [(0, 0), (0, 1), (0, 1)] + [(0, 0)] * (x.ndim - 3))  # the zero row/col
    x = x[:, ri[:, :, None, None], ci[None, None, :, :]]  # (T, ty, hs, tx, ws, ...)
    x = jnp.moveaxis(x, (1, 3), (0, 1))  # (ty, tx, T, hs, ws, ...)
    return x.reshape((ty * tx, -1) + x.shape[6:])


def _tiled(
    residual: Array,
    jac: Array,
    shape: Sequence[int],
    mask: AnyFloatLike | None,
    used: Sequence[int] | None,
    extra: Array | None,
    grid: tuple[int, int] | None,
    band: int,
) -> tuple[Array, Array, Array, Array, Array | None] | None:
    """Check the inputs and tile them: `(n, ssr, r_t (K, m), J_t (K, m, p), X_t (K, m, E) or
    None)`, the Jacobian's and `extra`'s columns at unit norm; `None` when no column is free."""
    shape, c, cols, (ty, tx), band = _check_layout(residual, jac, shape, used, grid, band)
    t, h, w = shape[:3]
    dtype = residual.dtype
    keep = jnp.ones(shape, bool) if mask is None else _nonzero(mask)
    keep = jnp.broadcast_to(keep, shape).reshape(t, h, w, c)
    r = jnp.where(keep, residual.reshape(t, h, w, c), 0)
    p = len(cols)
    if p == 0:
        return None
    jac = jac[:, jnp.asarray(cols, jnp.int32)].astype(dtype)
    jac = jnp.where(keep[..., None], jac.reshape(t, h, w, c, p), 0)
    n = jnp.sum(keep).astype(dtype)
    ssr = jnp.sum(r * r)
    ri, ci = _tile_index(h, ty, band), _tile_index(w, tx, band)
    jt = _gather_tiles(_unit_columns(jac), ri, ci)  # (K, m, p)
    rt = _gather_tiles(r, ri, ci)  # (K, m)
    if extra is None:
        return n, ssr, rt, jt, None
    x = jnp.where(keep[..., None], extra.astype(dtype).reshape(t, h, w, c, extra.shape[1]), 0)
    return n, ssr, rt, jt, _gather_tiles(_unit_columns(x), ri, ci)


def _factors(jt: Array, rt: Array) -> _Factors:
    """The tiles' SVD factors, the global problem from them (no squaring of `J`), the ranks and
    the pooled term `b^T A^+ b` of the statistic."""
    dtype = jt.dtype
    p = jt.shape[2]
    u, s, vt = thin_svd(jt)  # (K, m, k), (K, k), (K, k, p)
    cproj = jnp.einsum("kmi,km->ki", u, rt)  # U_k^T r_k: b_k^T A_k^+ b_k = |c_k|^2
    # The global problem from the tiles' factors: J^T J = M^T M, J^T r = M^T c (no squaring).
    big_m = (s[:, :, None] * vt).reshape(-1, p)
    um, sm, vtm = thin_svd(big_m)
    tol = math.sqrt(float(jnp.finfo(dtype).eps)) * sm[0]
    good = sm > tol
    kept = s > tol
    cg = um.T @ cproj.reshape(-1)
    q_global = jnp.sum(jnp.where(good, cg * cg, 0))
    rank = jnp.sum(good).astype(dtype)
    informative = jnp.sum(jnp.any(kept, axis=1))
    return _Factors(s, vt, cproj, big_m, sm, vtm, tol, good, kept, q_global, rank, informative)


def _tile_sums(f: _Factors, jt: Array, rt: Array, xt: Array | None) -> tuple[Array, Array]:
    """`(sum_k b_k^T A_k^+ b_k, sum_k rank_k)` of the unrestricted model: each tile its own lens
    and, with `xt`, its own `extra` columns."""
    dtype = jt.dtype
    if xt is None:
        q_tiles = jnp.sum(jnp.where(f.kept, f.cproj * f.cproj, 0))
        return q_tiles, jnp.sum(f.kept).astype(dtype)
    ua, sa, _ = thin_svd(jnp.concatenate([jt, xt], axis=2))
    ca = jnp.einsum("kmi,km->ki", ua, rt)
    kept_a = sa > f.tol
    return jnp.sum(jnp.where(kept_a, ca * ca, 0)), jnp.sum(kept_a).astype(dtype)


def _exposure_shift(f: _Factors, jt: Array, rt: Array, xt: Array | None) -> Array:
    """`(p,)`: how far the lens moves when every tile has its own `extra` columns (exposure) and
    all share one lens, one Gauss-Newton step from the pooled solution (unit-column coordinates):
    `d = -(sum_k P_k)^+ sum_k s_k`, with `P_k`, `s_k` the tile's information and score after
    projecting out its own `extra` columns. Photometric model error that is a smooth gain over the
    photo (vignetting) biases the pooled lens while each tile, with its own gain, is nearly
    unbiased: `d` is then the bias itself. Zeros without `extra`."""
    p = jt.shape[2]
    if xt is None:
        return jnp.zeros((p,), jt.dtype)
    ux, sx, _ = thin_svd(xt)  # (K, m, E)
    ux = jnp.where((sx > f.tol)[:, None, :], ux, 0)
    jp = jt - jnp.einsum("kme,ken->kmn", ux, jnp.einsum("kme,kmn->ken", ux, jt))
    rp = rt - jnp.einsum("kme,ke->km", ux, jnp.einsum("kme,km->ke", ux, rt))
    # The stacked projected tiles: their SVD gives (sum_k P_k)^+ without squaring them.
    u, s, vt = thin_svd(jp.reshape(-1, p))
    inv = jnp.where(s > f.tol, 1 / jnp.where(s > f.tol, s, 1), 0)
    return -(vt.T * inv[None, :]) @ (u.T @ rp.reshape(-1))


def _noise_variance(
    ssr: Array,
    q_tiles: Array,
    dof_noise: Array,
    sigma2: ScalarLike | None,
    noise_floor: ScalarLike,
) -> Array:
    """The noise variance: `sigma2`, or within tiles `SSR_u / (n - sum_k rank_k)`; at least
    `noise_floor^2`."""
    dtype = ssr.dtype
    if sigma2 is None:
        var = jnp.maximum(ssr - q_tiles, 0) / jnp.maximum(dof_noise, 1)
    else:
        var = jnp.asarray(sigma2, dtype)
    floor = jnp.asarray(noise_floor, dtype)
    return jnp.maximum(var, floor * floor)


def _p_value(chi2: Array, dof: Array, dof_noise: Array, *, known: bool) -> Array:
    """The survival of `chi2`: `F(dof, dof_noise)` (estimated variance) or `chi^2(dof)`
    (`known`); 1 where there are too few degrees of freedom to test."""
    safe_dof = jnp.maximum(dof, 1)
    chi2_survival = jsp.gammaincc(safe_dof / 2, chi2 / 2)
    if not known:
        d2 = jnp.maximum(dof_noise, 1)
        # F(dof, d2) survival: I_{d2 / (d2 + dof F)}(d2 / 2, dof / 2), with dof F = chi2. In
        # float32 `betainc` loses the value for large d2 (against scipy, F = 0.97: off by 0.003
        # at d2 = 1e4, 0.2 at 1e6, and -2.9 from a 6 MP fit on 2^20 pixels, d2 = 3e6, which then
        # "failed" the test); there the F distribution is its d2 -> inf limit, chi^2(dof) / dof,
        # to 0.0015 for dof <= 300 (the survival of `chi2` under chi^2(dof)). float64 stays exact.
        if jnp.dtype(chi2.dtype) == jnp.float32:
            safe_d2 = jnp.minimum(d2, _F_LIMIT_FLOAT32)
            beta = jsp.betainc(safe_d2 / 2, safe_dof / 2, safe_d2 / (safe_d2 + chi2))
            p_value = jnp.where(d2 > _F_LIMIT_FLOAT32, chi2_survival, beta)
        else:
            p_value = jsp.betainc(d2 / 2, safe_dof / 2, d2 / (d2 + chi2))
    else:
        p_value = chi2_survival
    p_value = jnp.clip(p_value, 0, 1)
    testable = (dof >= 1) & (dof_noise >= 1)
    return jnp.where(testable, p_value, 1)


def _spread(
    f: _Factors,
    var: Array,
    ssr: Array,
    n: Array,
    chi2_num: Array,
    safe_dof: Array,
    shift: Array,
) -> Array:
    """The tile-spread factor `s >= 1`: `s^2 V_fit >= V_fit + Omega + d d^T` in every direction
    (`d` the exposure `shift`), and at least the Birge ratio; 1 with fewer than 2 informative
    tiles or a zero residual."""
    dtype = ssr.dtype
    p = f.vt.shape[2]
    # The tile spread. Tile scores at the linearised exact solution: g_k = b_k - A_k A^+ b.
    inv_s = jnp.where(f.good, 1 / jnp.where(f.good, f.sm, 1), 0)
    a_pinv = (f.vtm.T * (inv_s * inv_s)[None, :]) @ f.vtm
    a_all = f.big_m.T @ f.big_m
    a_k = jnp.einsum("kij,ki,kil->kjl", f.vt, f.s * f.s, f.vt)  # (K, p, p)
    scores = jnp.einsum("kij,ki->kj", f.vt, f.s * f.cproj)  # J_k^T r_k
    scores = scores - jnp.einsum("kij,j->ki", a_k, a_pinv @ (f.big_m.T @ f.cproj.reshape(-1)))
    k_eff = f.informative.astype(dtype)
    small = k_eff / jnp.maximum(k_eff - 1, 1)  # the K / (K - 1) of a mean estimated from K
    # Omega, the covariance of the tiles' lenses about their mean beyond the noise, by moments:
    # E sum_k g_k g_k^T = sum_k A_k Omega A_k + var (A - sum_k A_k A^+ A_k), solved for Omega
    # (p^2 unknowns) and clipped to be positive semi-definite.
    noise = var * (a_all - jnp.einsum("kij,jl,klm->im", a_k, a_pinv, a_k))
    rhs = small * (scores.T @ scores - noise)
    kron = jnp.einsum("kab,kcd->acbd", a_k, a_k).reshape(p * p, p * p)
    omega = (pinv(kron, 10 * p * p * float(jnp.finfo(dtype).eps)) @ rhs.reshape(-1)).reshape(p, p)
    ev, evec = symmetric_eigh(0.5 * (omega + omega.T))
    omega = (evec * jnp.maximum(ev, 0)[None, :]) @ evec.T + jnp.outer(shift, shift)
    # V_fit = var_fit A^+ (what the fit reports). The largest eigenvalue of
    # V_fit^{-1/2} Omega V_fit^{-1/2}, in the basis of A's singular vectors: S V^T Omega V S.
    var_fit = ssr / jnp.maximum(n - f.rank, 1)
    safe_var = jnp.where(var_fit > 0, var_fit, 1)
    sv = f.sm[:, None] * (f.vtm @ omega @ f.vtm.T) * f.sm[None, :]
    sv = jnp.where(f.good[:, None] & f.good[None, :], sv, 0)
    tiles_ratio = 1 + symmetric_eigh(sv)[0][-1] / safe_var
    birge = chi2_num / safe_dof / safe_var
    spread = jnp.sqrt(jnp.maximum(jnp.maximum(tiles_ratio, birge), 1))
    return jnp.where((k_eff >= 2) & (var_fit > 0), spread, 1)


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
    function of arrays, compiled once per layout (`shape`, `used`, `grid`, `band` and `alpha` are
    static Python values; whether `extra`, `mask` and `sigma2` are given is structure too); it
    composes with `jit` and `vmap` (over fits).

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
    return _adequacy(
        residual,
        jac,
        mask,
        extra,
        sigma2,
        noise_floor,
        shape=tuple(int(k) for k in shape),
        used=None if used is None else tuple(int(k) for k in used),
        grid=None if grid is None else (int(grid[0]), int(grid[1])),
        band=int(band),
        alpha=float(alpha),
    )


# One compiled program per layout: called eagerly (a study, a test, a user's own check), the
# statistic's Jacobi loops and tile sums would otherwise be dispatched and compiled op by op
# (16 x 16 px, 3 columns, XLA level 0: 32 s cold and 4.7 s every later call, against 7-10 s
# once and 7 ms after).
@functools.partial(jax.jit, static_argnames=("shape", "used", "grid", "band", "alpha"))
def _adequacy(residual, jac, mask, extra, sigma2, noise_floor, *, shape, used, grid, band, alpha):
    one = jnp.ones((), residual.dtype)
    data = _tiled(residual, jac, shape, mask, used, extra, grid, band)
    if data is None:  # nothing free: nothing to test
        return dict(
            chi2=0 * one,
            dof=0 * one,
            p_value=one,
            tiles=jnp.zeros((), jnp.int32),
            inflation=one,
            spread=one,
            adequate=jnp.ones((), bool),
        )
    n, ssr, rt, jt, xt = data
    f = _factors(jt, rt)
    q_tiles, rank_tiles = _tile_sums(f, jt, rt, xt)
    dof = rank_tiles - f.rank
    dof_noise = n - rank_tiles
    chi2_num = jnp.maximum(q_tiles - f.q_global, 0)
    var = _noise_variance(ssr, q_tiles, dof_noise, sigma2, noise_floor)
    chi2 = jnp.where(var > 0, chi2_num / jnp.where(var > 0, var, 1), 0)
    p_value = _p_value(chi2, dof, dof_noise, known=sigma2 is not None)
    adequate = p_value >= alpha
    shift = _exposure_shift(f, jt, rt, xt)
    spread = _spread(f, var, ssr, n, chi2_num, jnp.maximum(dof, 1), shift)
    return dict(
        chi2=chi2,
        dof=dof,
        p_value=p_value,
        tiles=f.informative.astype(jnp.int32),
        inflation=jnp.where(adequate, one, spread),
        spread=spread,
        adequate=adequate,
    )
