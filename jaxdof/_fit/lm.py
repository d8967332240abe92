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

**The rounding floor.** The trust region accepts a step only when the loss falls by at least a
hundredth of what the linear model predicts, and near a solution in float32 that fall is below
the loss's own rounding: each residual carries its render's rounding, about `eps |m_i|` for a
prediction `m_i`, which moves the loss by `nu_r = eps ||r * m||`, and the sum `L = 0.5 ||r||^2`
is itself rounded in the solver's precision (float32 without `jax_enable_x64`), by up to `eps L`.
Steps are then accepted or rejected by that noise, and the solve spins near one point until a
streak of rejections shrinks the step under `rtol`/`atol`: on the ray-traced `vignette` photo
(A = 0.1 m, d_f = 3 m, 25 392 residuals) three starts came within 0.002 standard errors of their
end by step 18-22 and took 57-68 steps. So the solve also stops at an accepted point where the
full Gauss-Newton step's predicted decrease, `0.5 ||Q_1^T r||^2`, is under `_ROUNDING_MARGIN`
times the loss's rounding `nu = nu_r + eps L / 4` (`loss_rounding`; `m_i` from the caller's
`options["rounding"]`, `eps |sqrt(w) T|` in `fit_lens`; without it only the sum's part): no
step from there can be told from the noise. Measured at the solutions of the ray-traced tuning
scenes (`planes`, `slant`, `occluders` at two lenses each, float64 and float32 sums, and
`vignette`): the loss along lines through the solution scatters about its parabola by 0.46 to
1.04 times `nu`. The trust region judges a step by a *difference* of two such losses, which
scatters by up to twice that, ~2 `nu`; the margin is twice that again, 4: a step predicted to
gain less is accepted or rejected by the rounding. (With a margin of 2, the same photo's raw
init stopped at a point whose full step predicted 2.05 `nu`, and its trust region rejected that
step 16 times, shrinking it until one was accepted by the rounding at step 39, while the other
starts had stopped at steps 17 and 23: in lockstep, 16 more steps of all three.) A linear
model's predicted decrease is the loss above the minimum, so the solve stops within about
`sqrt(2 margin nu) / sigma` standard errors of it (0.04 on that photo); there, two starts that
stopped by this rule with losses within 2 `nu` of each other lay 0.17 to 0.31 standard errors
apart, so the float32 loss itself does not place the minimum closer than that.

**The step bound.** Every step is scaled down, along its direction, to at most `MAX_STEP` in
each of the solver's coordinates (`layout.py`: `log N`, a logit of `f`, the focus power scaled to
the scene): one step changes `N` by at most a factor `e` and the focus power by at most the
nearest depth's. Where the circles sit in the render's half-pixel dead zone the Jacobian is
nearly 0 and the Gauss-Newton step is unbounded: on a 64 x 96 photo with circles of 0.9-1.6 px,
started at f/5.6, the first accepted steps went to f/0.002 (circles of hundreds of pixels, a
window and a render of gigabytes). The trust region judges the scaled step as any other.

`y` and the residual are flat arrays (`residual._Model`'s); `J` is materialised (`P` columns).
"""

from __future__ import annotations

import math
from collections.abc import Callable

import equinox as eqx
import jax.numpy as jnp
import optimistix as optx
from jaxtyping import Array, PyTree, Scalar

from .linalg import thin_svd


# The loss's rounding, as a multiple of which a Gauss-Newton step's predicted decrease stops the
# solve (module docstring): the loss scattered by 0.46-1.04 times `loss_rounding` about its
# parabola at the tuning scenes' solutions, a difference of two losses (what the trust region
# tests) by up to about twice that, so 4 stops where a step is at most twice that noise.
_ROUNDING_MARGIN = 4.0


#: The largest change of any solver coordinate in one step (module docstring).
MAX_STEP = 1.0


class BoundedDampedNewtonDescent(optx.DampedNewtonDescent):
    """optimistix's damped Newton (Levenberg-Marquardt) step, scaled along its direction to at
    most `max_step` in every coordinate (module docstring)."""

    max_step: float = MAX_STEP

    def step(self, step_size, state):
        y_diff, result = super().step(step_size, state)
        if math.isinf(self.max_step):
            return y_diff, result
        size = jnp.max(jnp.abs(y_diff))
        return y_diff * (self.max_step / jnp.maximum(size, self.max_step)), result


def bounded(solver: optx.AbstractLeastSquaresSolver) -> optx.AbstractLeastSquaresSolver:
    """`solver` with its damped Newton descent bounded (`BoundedDampedNewtonDescent`); any other
    solver as it is."""
    descent = getattr(solver, "descent", None)
    if type(descent) is not optx.DampedNewtonDescent:
        return solver
    new = BoundedDampedNewtonDescent(linear_solver=descent.linear_solver)
    return eqx.tree_at(lambda s: s.descent, solver, new)


def _projection(residual: Array, jac: Array, rank_tol: float) -> tuple[Array, Array]:
    """`(||Q_1^T r||^2, p)`: the part of `||r||^2` the columns of `J` explain (twice the decrease
    of `0.5 ||r||^2` a full Gauss-Newton step predicts) and the rank `p`. Columns whose singular
    value is under `rank_tol` times the largest (unread slots, a degenerate pair) do not count."""
    u, s, _ = thin_svd(jac)
    keep = s > rank_tol * s[0]
    q1 = jnp.where(keep, u.T @ residual, 0)
    return q1 @ q1, jnp.sum(keep).astype(residual.dtype)


def loss_rounding(residual: Array, rounding: Array | None) -> Array:
    """The rounding of the loss `L = 0.5 ||r||^2` at a point (module docstring): `eps L / 4` of its
    sum in the residual's dtype, plus `||r * rounding||` where `rounding` `(n,)` is each residual's
    own rounding (e.g. `eps |m_i|` of a float32 render; None: exact residuals)."""
    loss = 0.5 * (residual @ residual)
    # A float rounds to within half its ulp, which is `eps L / 2` to `eps L`: uniform, its spread
    # is under `eps L / sqrt(12)`.
    level = jnp.finfo(residual.dtype).eps * loss / 4
    if rounding is None:
        return level
    return level + jnp.sqrt(jnp.sum(jnp.square(residual * rounding.astype(residual.dtype))))


def relative_offset(
    residual: Array, jac: Array, rank_tol: float, projected: tuple[Array, Array] | None = None
) -> Array:
    """Bates & Watts' relative offset (module docstring) at a point with residual `(n,)` and
    Jacobian `(n, P)`; columns whose singular value is under `rank_tol` times the largest (unread
    slots, a degenerate pair) do not count. `inf` where it is undefined (no column, no residual
    left over). `projected`: `_projection`'s `(||Q_1^T r||^2, p)` when already computed."""
    explained, p = _projection(residual, jac, rank_tol) if projected is None else projected
    # Residuals with zero weight (the border band) are exactly 0 with a zero Jacobian row.
    n = jnp.sum((residual != 0) | jnp.any(jac != 0, axis=1)).astype(residual.dtype)
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
    """`optx.LevenbergMarquardt` (its damped step, bounded by `MAX_STEP`, trust region,
    `rtol`/`atol` test and `verbose`) that also stops once Bates & Watts' relative offset is under `offset_tol`, or once the next
    step's predicted decrease is under the loss's rounding (module docstring; `options` may carry
    `"rounding"`, each residual's own rounding `(n,)`). `max_step=math.inf` leaves the step
    unbounded, as optimistix's."""

    rtol: float
    atol: float
    offset_tol: float
    rank_tol: float
    norm: Callable[[PyTree], Scalar]
    descent: BoundedDampedNewtonDescent
    search: optx.ClassicalTrustRegion
    verbose: Callable[..., None]

    def __init__(
        self,
        rtol: float,
        atol: float,
        *,
        offset_tol: float,
        rank_tol: float,
        max_step: float = MAX_STEP,
        verbose: bool | Callable[..., None] = False,
    ):
        base = optx.LevenbergMarquardt(rtol=rtol, atol=atol, verbose=verbose)
        self.rtol, self.atol, self.norm = rtol, atol, base.norm
        self.offset_tol, self.rank_tol = offset_tol, rank_tol
        self.search, self.verbose = base.search, base.verbose
        self.descent = BoundedDampedNewtonDescent(
            linear_solver=base.descent.linear_solver, max_step=max_step
        )

    def step(self, fn, y, args, options, state, tags):
        y, state, aux = super().step(fn, y, args, options, state, tags)
        # Tested at every newly accepted point (the first, `y0`, included).
        accepted = state.num_steps_since_acceptance == 0
        f_info = state.f_info
        r, jac = f_info.residual, f_info.jac.as_matrix()
        projected = _projection(r, jac, self.rank_tol)
        ro = relative_offset(r, jac, self.rank_tol, projected)
        rounding = None if options is None else options.get("rounding")
        unresolved = 0.5 * projected[0] <= _ROUNDING_MARGIN * loss_rounding(r, rounding)
        stop = state.terminate | (accepted & ((ro < self.offset_tol) | unresolved))
        return y, eqx.tree_at(lambda s: s.terminate, state, stop), aux
