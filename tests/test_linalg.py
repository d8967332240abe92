"""`_fit/linalg.py`: the fit's small decompositions in plain JAX, against numpy's LAPACK, and no
LAPACK call left in the compiled statistics of a fit (the thread-pool hang they replace)."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jaxdof._fit.adequacy import adequacy
from jaxdof._fit.linalg import pinv, symmetric_eigh, thin_svd
from jaxdof._fit.lm import relative_offset


# (rows, columns, rank-deficient): tall, a column, square, wide, and the sizes a fit meets.
SHAPES = [
    (50, 1, False),
    (60, 2, False),
    (400, 5, True),
    (7, 7, False),
    (3, 6, False),
    (90, 12, True),
]


def _matrix(m, n, deficient, dtype, seed=0):
    a = np.random.default_rng(seed).normal(size=(m, n))
    if deficient:
        a[:, 1] = 2 * a[:, 0]  # exactly dependent columns: a zero singular value
    a[:, -1] *= 1e-3  # and a small one, which must keep its relative accuracy
    return a.astype(dtype)


@pytest.mark.parametrize("dtype", [np.float32, np.float64])
@pytest.mark.parametrize("m,n,deficient", SHAPES)
def test_thin_svd_matches_lapack(m, n, deficient, dtype):
    a = _matrix(m, n, deficient, dtype)
    u, s, vt = map(np.asarray, thin_svd(jnp.asarray(a)))
    k = min(m, n)
    assert u.shape == (m, k) and s.shape == (k,) and vt.shape == (k, n)
    eps = np.finfo(dtype).eps
    s_ref = np.linalg.svd(a.astype(np.float64), compute_uv=False)
    assert np.all(np.diff(s) <= 0)  # descending
    assert np.max(np.abs(s - s_ref)) <= 30 * eps * s_ref[0]
    # The small (nonzero) singular value to relative accuracy, not only relative to the largest.
    nonzero = s_ref > 1e3 * eps * s_ref[0]
    assert np.max(np.abs(s[nonzero] / s_ref[nonzero] - 1)) <= 300 * eps
    np.testing.assert_allclose(vt @ vt.T, np.eye(k), atol=30 * eps)
    np.testing.assert_allclose((u * s) @ vt, a, atol=30 * eps * s_ref[0] * np.sqrt(m))
    ranked = u[:, nonzero]
    np.testing.assert_allclose(ranked.T @ ranked, np.eye(int(nonzero.sum())), atol=100 * eps)


def test_thin_svd_batches_and_jits():
    a = np.stack([_matrix(40, 3, False, np.float64, seed) for seed in range(4)])
    s = jax.jit(thin_svd)(jnp.asarray(a))[1]
    np.testing.assert_allclose(s, np.linalg.svd(a, compute_uv=False), rtol=1e-12)


@pytest.mark.parametrize("dtype", [np.float32, np.float64])
def test_symmetric_eigh_and_pinv_match_lapack(dtype):
    rng = np.random.default_rng(1)
    b = rng.normal(size=(6, 6))
    b = (b + b.T).astype(dtype)
    w, v = map(np.asarray, symmetric_eigh(jnp.asarray(b)))
    eps = np.finfo(dtype).eps
    scale = np.abs(b).max()
    np.testing.assert_allclose(w, np.linalg.eigvalsh(b.astype(np.float64)), atol=50 * eps * scale)
    np.testing.assert_allclose((v * w) @ v.T, b, atol=50 * eps * scale)
    a = rng.normal(size=(30, 4)).astype(dtype)
    np.testing.assert_allclose(pinv(jnp.asarray(a)), np.linalg.pinv(a), atol=50 * eps)


def _lapack_calls(fn, *args) -> list[str]:
    text = jax.jit(fn).lower(*args).as_text()
    return [line for line in text.splitlines() if "lapack" in line.lower()]


def test_the_fit_statistics_call_no_lapack():
    """The relative offset (every LM step) and the adequacy test (every fit's end) compile to
    plain XLA: no LAPACK kernel that could wait on the thread pool beside the solver's QR."""
    rng = np.random.default_rng(2)
    jac = jnp.asarray(rng.normal(size=(2 * 16 * 16, 3)), jnp.float32)
    res = jnp.asarray(rng.normal(size=(2 * 16 * 16,)), jnp.float32)
    assert _lapack_calls(lambda r, j: relative_offset(r, j, 1e-5), res, jac) == []
    extra = jnp.asarray(rng.normal(size=(2 * 16 * 16, 2)), jnp.float32)

    def check(r, j, x):
        return adequacy(r, j, (2, 16, 16), extra=x, grid=(2, 2))["p_value"]

    assert _lapack_calls(check, res, jac, extra) == []
