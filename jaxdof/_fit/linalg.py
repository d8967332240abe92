r"""Small dense decompositions in plain JAX for the fit: thin SVD, pseudo-inverse, symmetric
eigenvalues. No LAPACK call, so no thread-pool wait inside a compiled fit.

**Why not `jnp.linalg`.** On CPU, jaxlib's LAPACK kernels (`gesdd`, `geqrf`, `syevd`, ...) split a
batch of matrices over XLA's intra-op thread pool and block their own pool thread until the
pieces are done. Two such kernels that XLA runs concurrently (independent branches of one
program, as the damped-Newton QR and the relative-offset SVD of `lm.py` are) can each hold a pool
thread while waiting for work queued behind the other: with two pool threads (a 2-core machine)
a 1.5 MP `fit_lens` hung forever, both threads parked in `ParallelBatchMap` under `sgesdd` and
`sgeqrf` (gdb, jaxlib 0.10.2). The fit's matrices are tall and thin (pixels x a few parameters)
or tiny (parameters x parameters), so plain JAX costs nothing here and removes the hazard.

**Algorithms.**
- `householder_qr`: Householder QR of a tall `(m, n)` matrix, `n` reflections of full length
  (masked, so the shapes stay static), `R` upper triangular (Golub & Van Loan, *Matrix
  Computations*, 4th ed., 2013, sec. 5.1.2 and 5.2.1).
- `thin_svd`: QR, then the one-sided Jacobi (Hestenes) SVD of the `(n, n)` factor `R`: cyclic
  sweeps of plane rotations that orthogonalise the columns of `R V`; the singular values are the
  final column norms. Unlike the SVD of `A^T A` it keeps the small singular values to relative
  accuracy (Demmel & Veselic, "Jacobi's method is more accurate than QR", SIAM J. Matrix Anal.
  Appl. 13, 1992), which the fit's rank tests need in float32. Convergence is quadratic; a fixed
  `_SWEEPS` keeps the function differentiable and vmappable (`lax.fori_loop`).
- `symmetric_eigh`: the cyclic two-sided Jacobi eigenvalue method (Golub & Van Loan sec. 8.5.3)
  on a small symmetric matrix.

**What stays LAPACK.** optimistix's damped Newton step (lineax's `QR`: `geqrf`, `ormqr`, `trsm`,
one after another) is then the only LAPACK chain in a fit's loop and never runs beside another.
A plain-JAX QR there measured 1.3 s per step against 0.9 s (1.5 MP, 56 tiles, two starts): the
Householder passes over 1.5 million residuals cost more than LAPACK's blocked kernel.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float


# Cyclic Jacobi reduces the off-diagonal mass quadratically once it is small; 3-4 sweeps suffice
# for n <= 16 in float32 and 5-6 in float64 (Golub & Van Loan sec. 8.5.5). 12 leaves a wide margin
# at a negligible cost on the fit's small factors.
_SWEEPS = 12


def _pairs(n: int) -> tuple[Array, Array]:
    """The cyclic-by-row order of the pairs `(i, j)`, `i < j`, as two index arrays."""
    ii, jj = np.triu_indices(n, k=1)
    return jnp.asarray(ii, jnp.int32), jnp.asarray(jj, jnp.int32)


def _rotation(alpha: Array, beta: Array, gamma: Array) -> tuple[Array, Array]:
    """`(c, s)` of the Jacobi rotation that zeroes `gamma` in the symmetric 2 x 2 matrix
    `[[alpha, gamma], [gamma, beta]]` (Golub & Van Loan alg. 8.5.1); `(1, 0)` where `gamma`
    is already negligible."""
    tiny = jnp.finfo(alpha.dtype).tiny
    small = jnp.abs(gamma) <= jnp.finfo(alpha.dtype).eps * jnp.sqrt(jnp.abs(alpha * beta)) + tiny
    safe_gamma = jnp.where(small, 1, gamma)
    tau = (beta - alpha) / (2 * safe_gamma)
    sign = jnp.where(tau >= 0, 1, -1).astype(alpha.dtype)
    t = sign / (jnp.abs(tau) + jnp.sqrt(1 + tau * tau))
    c = 1 / jnp.sqrt(1 + t * t)
    return jnp.where(small, 1, c), jnp.where(small, 0, c * t)


def _rotate_columns(x: Array, i: Array, j: Array, c: Array, s: Array) -> Array:
    xi, xj = x[:, i], x[:, j]
    return x.at[:, i].set(c * xi - s * xj).at[:, j].set(s * xi + c * xj)


def _jacobi_svd_square(r: Float[Array, "n n"]) -> tuple[Array, Array, Array]:
    """One-sided Jacobi SVD of a square matrix: `(u, s, vt)`, `s` descending."""
    n = r.shape[0]
    v0 = jnp.eye(n, dtype=r.dtype)
    if n == 1:
        s = jnp.abs(r[0])
        u = jnp.where(s[None, :] > 0, r / jnp.where(s > 0, s, 1)[None, :], 1)
        return u, s, v0
    ii, jj = _pairs(n)

    def pair(k, wv):
        w, v = wv
        i, j = ii[k % ii.shape[0]], jj[k % ii.shape[0]]
        wi, wj = w[:, i], w[:, j]
        c, s = _rotation(wi @ wi, wj @ wj, wi @ wj)
        return _rotate_columns(w, i, j, c, s), _rotate_columns(v, i, j, c, s)

    # The sweeps as one loop over `_SWEEPS` rounds of the pairs (one loop compiles faster than
    # two nested ones).
    w, v = jax.lax.fori_loop(0, _SWEEPS * ii.shape[0], pair, (r, v0))
    s = jnp.sqrt(jnp.sum(w * w, axis=0))
    order = jnp.argsort(-s)
    s, w, v = s[order], w[:, order], v[:, order]
    u = w / jnp.where(s > 0, s, 1)[None, :]
    # A zero singular value leaves a zero column of `u` (callers mask by rank, so it is unused).
    return u, s, v.T


def _reflector(x: Array, k: Array | int) -> Array:
    """The unit Householder vector `v` (zero above row `k`) with `(I - 2 v v^T) x` zero below
    row `k`; 0 when `x` is already zero from row `k` down."""
    rows = jnp.arange(x.shape[0])
    x = jnp.where(rows >= k, x, 0)
    norm = jnp.sqrt(x @ x)
    # The sign that avoids cancellation in x_k - alpha.
    alpha = -jnp.where(x[k] >= 0, 1, -1).astype(x.dtype) * norm
    v = x - jnp.where(rows == k, alpha, 0)
    vnorm = jnp.sqrt(v @ v)
    return jnp.where(vnorm > 0, v / jnp.where(vnorm > 0, vnorm, 1), 0)


@jax.jit
def householder_qr(a: Float[Array, "m n"]) -> tuple[Float[Array, "m n"], Float[Array, "n n"]]:
    """Householder QR of a tall matrix (`m >= n`): `(vs, r)`, `A = Q R` with
    `Q = H_0 H_1 ... H_{n-1}`, `H_k = I - 2 v_k v_k^T` and `v_k = vs[:, k]`."""
    n = a.shape[1]

    # A loop, not n unrolled reflections: the compiled program stays one reflection long
    # (256 x 5: 1.65 s of XLA unrolled).
    def reflect(k, avs):
        a, vs = avs
        v = _reflector(jax.lax.dynamic_index_in_dim(a, k, axis=1, keepdims=False), k)
        return a - 2 * jnp.outer(v, v @ a), vs.at[:, k].set(v)

    a, vs = jax.lax.fori_loop(0, n, reflect, (a, jnp.zeros_like(a)))
    return vs, jnp.triu(a[:n])


def apply_q(vs: Float[Array, "m n"], x: Float[Array, "m ..."]) -> Float[Array, "m ..."]:
    """`Q x` for the `Q` of `householder_qr`."""
    n = vs.shape[1]

    def reflect(i, x):
        v = jax.lax.dynamic_index_in_dim(vs, n - 1 - i, axis=1, keepdims=False)
        return x - 2 * jnp.tensordot(v, jnp.tensordot(v, x, axes=(0, 0)), axes=0)

    return jax.lax.fori_loop(0, n, reflect, x)


def _thin_svd_2d(a: Array) -> tuple[Array, Array, Array]:
    m, n = a.shape
    if m < n:
        u, s, vt = _thin_svd_2d(a.T)
        return vt.T, s, u.T
    vs, r = householder_qr(a)
    ur, s, vt = _jacobi_svd_square(r)
    u = apply_q(vs, jnp.zeros((m, n), a.dtype).at[:n].set(ur))
    return u, s, vt


@jax.jit
def thin_svd(
    a: Float[Array, "*batch m n"],
) -> tuple[Float[Array, "*batch m k"], Float[Array, "*batch k"], Float[Array, "*batch k n"]]:
    """`jnp.linalg.svd(a, full_matrices=False)` without LAPACK (module docstring): `(u, s, vt)`,
    `k = min(m, n)`, `s` descending, for the small `min(m, n)` of the fit's matrices."""
    return jnp.vectorize(_thin_svd_2d, signature="(m,n)->(m,k),(k),(k,n)")(a)


def _rotate_symmetric(a: Array, i: Array, j: Array, c: Array, s: Array) -> Array:
    a = _rotate_columns(a, i, j, c, s)
    return _rotate_columns(a.T, i, j, c, s).T


def _symmetric_eigh_2d(a: Array) -> tuple[Array, Array]:
    n = a.shape[0]
    v0 = jnp.eye(n, dtype=a.dtype)
    if n == 1:
        return a[0], v0
    ii, jj = _pairs(n)

    def pair(k, av):
        a, v = av
        i, j = ii[k % ii.shape[0]], jj[k % ii.shape[0]]
        c, s = _rotation(a[i, i], a[j, j], a[i, j])
        return _rotate_symmetric(a, i, j, c, s), _rotate_columns(v, i, j, c, s)

    a, v = jax.lax.fori_loop(0, _SWEEPS * ii.shape[0], pair, (0.5 * (a + a.T), v0))
    w = jnp.diagonal(a)
    order = jnp.argsort(w)
    return w[order], v[:, order]


@jax.jit
def symmetric_eigh(
    a: Float[Array, "*batch n n"],
) -> tuple[Float[Array, "*batch n"], Float[Array, "*batch n n"]]:
    """`jnp.linalg.eigh` of a small symmetric matrix without LAPACK: eigenvalues ascending and
    the eigenvectors as columns (cyclic Jacobi, module docstring)."""
    return jnp.vectorize(_symmetric_eigh_2d, signature="(n,n)->(n),(n,n)")(a)


def pinv(a: Float[Array, "m n"], rtol: float | None = None) -> Float[Array, "n m"]:
    """The pseudo-inverse through `thin_svd`, cutting singular values under `rtol` times the
    largest (default: `max(m, n)` machine epsilons, as `jnp.linalg.pinv`)."""
    u, s, vt = thin_svd(a)
    tol = (max(a.shape) * jnp.finfo(a.dtype).eps if rtol is None else rtol) * s[0]
    inv = jnp.where(s > tol, 1 / jnp.where(s > tol, s, 1), 0)
    return (vt.T * inv[None, :]) @ u.T
