"""Shared references and scenes for the tests: slow, obviously-correct float64 numpy code."""

import importlib.util
import pathlib

import jax.random as jr
import mpmath
import numpy as np

import jaxdof


def fits_module(name: str):
    """A self-contained module of the studies (`fits/<name>.py`: study-only code that the tests
    check, e.g. the candidates that lost), loaded from its file."""
    path = pathlib.Path(__file__).parents[1] / "fits" / f"{name}.py"
    spec = importlib.util.spec_from_file_location(f"fits_{name}", path)
    assert spec is not None and spec.loader is not None
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


# The model the synthetic targets here are rendered with (`jaxdof.render`'s default): these tests
# check the solve, so they fit exactly that model instead of the treatment `fit_lens` would choose
# for a real photo (occlusion, edge weight, footprint; tests/test_treatment.py), and no nuisance
# the photo might ask for (exposure; tests/test_nuisances.py).
EXACT = dict(method="soft", footprint=False, edge_weight=False, exposure=False)


def overlap_by_integration(dx: float, dy: float, r: float) -> float:
    """Area of disc(0, r) ∩ unit square at (dx, dy) by 30-digit quadrature of the column heights.

    Independent of the library: integrates `len({y in [y0, y1] : x^2 + y^2 <= r^2})` over x with
    mpmath's tanh-sinh rule, split at the kinks where the circle crosses y0 and y1.
    """
    with mpmath.workdps(30):
        dx, dy, r = mpmath.mpf(dx), mpmath.mpf(dy), mpmath.mpf(r)
        x0, x1 = max(dx - 0.5, -r), min(dx + 0.5, r)
        if x1 <= x0:
            return 0.0
        y0, y1 = dy - 0.5, dy + 0.5

        def column(x):
            h = mpmath.sqrt(max(r * r - x * x, 0))
            return max(min(y1, h) - max(y0, -h), 0)

        kinks = []
        for y in (y0, y1):
            if abs(y) < r:
                xm = mpmath.sqrt(r * r - y * y)
                kinks += [k for k in (-xm, xm) if x0 < k < x1]
        return float(mpmath.quad(column, [x0, *sorted(set(kinks)), x1]))


def scatter_reference(image: np.ndarray, radius: np.ndarray, overlap) -> np.ndarray:
    """The scatter written literally, as a dense (pixels x pixels) matrix in float64.

    `M[p, q] = overlap(p - q, r_q) / (pi r_q^2)` (the identity column where `r_q <= 1/2`) and
    `out = M @ image`: every source spreads over every output pixel, with no window and no
    clamping. `overlap(dx, dy, r)` is a vectorised float64 area function.
    """
    image = np.asarray(image, np.float64)
    squeeze = image.ndim == 2
    if squeeze:
        image = image[..., None]
    h, w, c = image.shape
    yy, xx = (g.ravel() for g in np.mgrid[0:h, 0:w].astype(np.float64))
    r = np.asarray(radius, np.float64).ravel()
    dx, dy = xx[:, None] - xx[None, :], yy[:, None] - yy[None, :]
    area = np.asarray(overlap(dx, dy, np.broadcast_to(r[None, :], dx.shape)))
    big = r > 0.5
    m = np.where(big[None, :], area / (np.pi * np.where(big, r, 1.0) ** 2)[None, :], np.eye(h * w))
    out = (m @ image.reshape(h * w, c)).reshape(h, w, c)
    return out[..., 0] if squeeze else out


def step_scene(h: int = 24, w: int = 28, seed: int = 0):
    """A random texture with a radius map of depth steps (0 .. 20 px) and a smooth ramp."""
    rng = np.random.default_rng(seed)
    image = rng.uniform(size=(h, w, 3))
    radius = np.where(np.arange(w)[None, :] < w // 2, 0.0, 7.3) + np.zeros((h, 1))
    radius[h // 2 :, :] = np.linspace(0.0, 20.0, w)[None, :]
    return image, radius


# The catalogue of methods: one configured object per built-in method, shared by the tests, so that
# the same objects (and their static options) meet the same shapes and compile once. The default
# options, and a fixed key for the one method that needs one.
CATALOGUE: dict[str, jaxdof.AbstractMethod] = {
    "soft": jaxdof.Soft(),
    "hard": jaxdof.Hard(),
    "supersample": jaxdof.Supersample(),
    "jitter": jaxdof.Jitter(key=jr.PRNGKey(0)),
    "aperture": jaxdof.Aperture(),
    "layered": jaxdof.Layered(),
    "auto": jaxdof.Auto(),
    "occlusion": jaxdof.Occlusion(),
    "local_occlusion": jaxdof.LocalOcclusion(),
}
METHODS = tuple(CATALOGUE.values())
#: The methods whose radius derivative is that of their own forward model (a lens can be fitted).
RADIUS_METHODS = tuple(m for m in METHODS if m.differentiable_in_radius)


def method_id(method) -> str:
    """A test id for a method object: its class name."""
    return type(method).__name__
