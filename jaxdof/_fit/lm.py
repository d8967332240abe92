r"""`fit_lens`'s default solver: optimistix's Levenberg-Marquardt that also stops when its next
step would move the fit by a negligible fraction of its own standard error.

**Why.** At a fit's solution the residual is the photo's noise, not 0, so the Gauss-Newton matrix
`J^T J` misses the term `S = sum_i r_i Hess(r_i)` of the Hessian, and Levenberg-Marquardt
converges only linearly, at the rate of `(J^T J)^{-1} S` (Dennis & Schnabel, *Numerical Methods
for Unconstrained Optimization*, 1983, sec. 10.2). The render's curvature is singular where a
circle grows past half a pixel (the light it moves into the neighbouring pixels grows as
`(r - 1/2)^{3/2}`, so `d^2/dr^2 ~ (r - 1/2)^{-1/2}`), and when a photo's focus plane lies inside
the fitted region, noise makes `S` large along the focus coordinate: 0.7 to 8 times `J^T J` on
the `slant` scene of `fits/recover.py` at sigma = 0.03 (12 x 12 pixels fitted), 0.3 times at
sigma = 0.01. optimistix's own test (the last step, in `y` and in every residual, under
`atol + rtol |.|` = 1e-8) then takes 110 to 600 steps at rates of 0.93 to 0.996 per step, of
which the first 40 to 90 % already bring the fit within a thousandth of a standard error.

**The stopping rule.** The solve also stops at an accepted point whose *relative offset*
(Bates & Watts 1981) is under `offset_tol`:

$$\mathrm{RO} = \frac{\lVert Q_1^T r \rVert / \sqrt{p}}{\lVert Q_2^T r \rVert / \sqrt{n - p}},$$

`Q_1` an orthonormal basis of the columns of `J` (rank `p`), `Q_2` its complement, `n` the
residuals with non-zero weight. `RO sqrt(p)` is the length of the Gauss-Newton step in standard
errors (`||J delta|| / sigma`), so the rule is scale-free and relative to the noise: a fit stops
when its next step could move it by less than `offset_tol sqrt(p)` of its error bar. On data
without noise (`Q_2^T r -> 0`) the offset does not fall and optimistix's test stops the solve
as before. Bates, D. M. & Watts, D. G. (1981), "A relative offset orthogonality convergence
criterion for nonlinear least squares", *Technometrics* 23(2), 179-183; their book (*Nonlinear
Regression Analysis and Its Applications*, 1988, sec. 2.2.3) recommends 0.001.

`y` and the residual are flat arrays (`residual._Model`'s); `J` is materialised (`P` columns).
"""

from __future__ import annotations

from collections.abc import Callable

import equinox as eqx
import jax.numpy as jnp
import optimistix as optx
from jaxtyping import Array, PyTree, Scalar

from .linalg import thin_svd


def relative_offset(residual: Array, jac: Array, rank_tol: float) -> Array:
    """Bates & Watts' relative offset (module docstring) at a point with residual `(n,)` and
    Jacobian `(n, P)`; columns whose singular value is under `rank_tol` times the largest (unread
    slots, a degenerate pair) do not count. `inf` where it is undefined (no column, no residual
    left over)."""
    u, s, _ = thin_svd(jac)
    keep = s > rank_tol * s[0]
    q1 = jnp.where(keep, u.T @ residual, 0)
    p = jnp.sum(keep).astype(residual.dtype)
    # Residuals with zero weight (the border band) are exactly 0 with a zero Jacobian row.
    n = jnp.sum((residual != 0) | jnp.any(jac != 0, axis=1)).astype(residual.dtype)
    explained = q1 @ q1
    total = residual @ residual
    rest = total - explained
    # `rest` is a difference of sums of squares: below their rounding (~ sqrt(n) eps |r|^2) it is
    # no residual left over at all.
    rounding = 10 * jnp.sqrt(n) * jnp.finfo(residual.dtype).eps * total
    ok = (p > 0) & (n > p) & (rest > rounding)
    per_param = explained / jnp.maximum(p, 1.0)
    per_residual = jnp.where(ok, rest / jnp.maximum(n - p, 1.0), 1.0)
    return jnp.where(ok, jnp.sqrt(per_param / per_residual), jnp.inf)


class LevenbergMarquardt(optx.AbstractGaussNewton):
    """`optx.LevenbergMarquardt` (its damped step, trust region, `rtol`/`atol` test and `verbose`)
    that also stops once Bates & Watts' relative offset is under `offset_tol` (module docstring)."""

    rtol: float
    atol: float
    offset_tol: float
    rank_tol: float
    norm: Callable[[PyTree], Scalar]
    descent: optx.DampedNewtonDescent
    search: optx.ClassicalTrustRegion
    verbose: Callable[..., None]

    def __init__(
        self,
        rtol: float,
        atol: float,
        *,
        offset_tol: float,
        rank_tol: float,
        verbose: bool | Callable[..., None] = False,
    ):
        base = optx.LevenbergMarquardt(rtol=rtol, atol=atol, verbose=verbose)
        self.rtol, self.atol, self.norm = rtol, atol, base.norm
        self.offset_tol, self.rank_tol = offset_tol, rank_tol
        self.descent, self.search, self.verbose = base.descent, base.search, base.verbose

    def step(self, fn, y, args, options, state, tags):
        y, state, aux = super().step(fn, y, args, options, state, tags)
        # Tested at every newly accepted point (the first, `y0`, included).
        accepted = state.num_steps_since_acceptance == 0
        f_info = state.f_info
        ro = relative_offset(f_info.residual, f_info.jac.as_matrix(), self.rank_tol)
        stop = state.terminate | (accepted & (ro < self.offset_tol))
        return y, eqx.tree_at(lambda s: s.terminate, state, stop), aux
