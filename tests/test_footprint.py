"""The opt-in pixel-footprint correction as an option of `render`, `fit_lens` and the CLI.

`footprint_prefilter` itself (its variance, its gradients, float32) is tested in
`tests/test_raytraced.py`; here: that the option is exactly that prefilter composed with the
filter, off by default, differentiable through `render` in every input, and that a fit through it
recovers the lens that rendered its targets.
"""

import equinox as eqx
import jax.numpy as jnp
import numpy as np

from jaxdof import (
    DefocusModel,
    ThinLens,
    coc_filter,
    coc_radius,
    fit_lens,
    footprint_prefilter,
    render,
)

from .helpers import EXACT
from .test_fit import STARTS, WINDOW, lens, rel_err, scene, wrong_init
from .test_gradients import LENS_ARGS, _extreme_depths, _render, check


def test_render_footprint_is_the_prefilter_then_the_filter():
    image, depth = scene()
    true = lens()
    r = coc_radius(depth, true)
    composed = coc_filter(footprint_prefilter(image, r), r, max_radius=WINDOW)
    np.testing.assert_array_equal(
        render(image, depth, true, max_radius=WINDOW, footprint=True), composed
    )
    # off by default: the plain filter, and a different image (the correction is not a no-op)
    plain = render(image, depth, true, max_radius=WINDOW)
    np.testing.assert_array_equal(plain, coc_filter(image, r, max_radius=WINDOW))
    assert float(jnp.max(jnp.abs(plain - composed))) > 1e-3


def test_render_footprint_corrects_the_clamped_radius():
    """Radii beyond `max_radius` are spread at `max_radius`: the correction is for that radius."""
    image, depth = scene()
    true = lens()
    r = coc_radius(depth, true)
    window = 0.5 * float(jnp.max(r))  # clamps the largest circles
    assert float(jnp.mean(r > window)) > 0.05
    clamped = jnp.minimum(r, window)
    composed = coc_filter(footprint_prefilter(image, clamped), r, max_radius=window)
    np.testing.assert_array_equal(
        render(image, depth, true, max_radius=window, footprint=True), composed
    )


def test_render_footprint_every_input():
    """Image, depth and every lens field (float64, forward and reverse mode), on a scene with
    depths at infinity, at the focus plane and just beyond the focal length (clamped)."""
    image, depth, inf_mask = _extreme_depths()
    f = _render(inf_mask=inf_mask, footprint=True)
    check(f, (image, depth, *LENS_ARGS), jit=True)


def test_fit_through_the_footprint_model():
    """Targets rendered with the correction are recovered by a fit through it (float64, noise-free,
    the usual wrong start), and the plain model fitted to them is biased in K: the option matters."""
    image, depth = scene()
    true = lens()
    target = render(image, depth, true, max_radius=WINDOW, footprint=True)
    free = ("f_number", "focus_distance")
    init = wrong_init(free)
    kw = dict(free=free, max_radius=WINDOW, starts=STARTS)
    # The soft render without an edge weight (the scene's depth steps would turn on the occlusion
    # render and the weight): the target's own model.
    res = fit_lens(
        image, depth, target, init, method="soft", edge_weight=False, footprint=True, **kw
    )
    assert bool(res.success), res.message
    err = rel_err(res.lens, true, ("f_number", "focus_distance"))
    assert max(err.values()) < 1e-4, err  # the fit issue's float64 target
    plain = fit_lens(image, depth, target, init, **EXACT, **kw)
    k_err = abs(float(plain.lens.blur_scale) / float(true.blur_scale) - 1)
    assert k_err > 1e-3, k_err  # the plain model cannot express the corrected blur


def test_footprint_chosen_at_run_time_is_the_static_choice():
    """`DefocusModel(footprint=<bool array>)` renders what `footprint=True/False` render, and one
    compiled program serves both values (`fit_lens` tries the correction on and off with it)."""
    image, depth = scene()
    true = lens()
    traces = []

    @eqx.filter_jit
    def photo(model, im, d):
        traces.append(1)  # runs once per trace
        return model(im, d, true, max_radius=WINDOW)

    for on in (True, False):
        static = DefocusModel(footprint=on)(image, depth, true, max_radius=WINDOW)
        chosen = photo(DefocusModel(footprint=jnp.asarray(on)), image, depth)
        np.testing.assert_allclose(chosen, static, rtol=1e-13, atol=1e-15)  # float64
    assert len(traces) == 1
    # the border band follows the value (the correction's stencils read two more pixels)
    assert DefocusModel(footprint=jnp.asarray(True)).border_band(3.0) == 5
    assert DefocusModel(footprint=jnp.asarray(False)).border_band(3.0) == 3


def test_footprint_chosen_at_run_time_gradients():
    """Image, depth and every lens field through the run-time choice (float64, both values)."""
    image, depth, inf_mask = _extreme_depths()
    for on in (True, False):
        model = DefocusModel(footprint=jnp.asarray(on))

        def f(im, d, fl, n, d_f, pitch, model=model):
            d = jnp.where(inf_mask, jnp.inf, d)
            return model(im, d, ThinLens(fl, n, d_f, pitch * 1e-5), max_radius=3.0)

        check(f, (image, depth, *LENS_ARGS), jit=True)
