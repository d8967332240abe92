"""The lens fits of `raytraced.py`: forward-model treatments, the fit plan, and the fits (cached).

Every fit is cached in `fits/.cache/raytraced/fit_*.json`, so a report re-run fits nothing new.
"""

from __future__ import annotations

import math
import time

import jax


jax.config.update("jax_enable_x64", True)

import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402
from _common import cached_json  # noqa: E402
from _raytraced_scenes import (  # noqa: E402
    CACHE,
    CONFIGS,
    F_PX,
    SCENES,
    load_scene,
    load_scene_fine,
    true_lens,
    z_depth,
)

import jaxdof  # noqa: E402
from jaxdof import edge_weight, fit_lens  # noqa: E402

# The study-only candidates of the pixel-footprint correction (semi-internal).
from jaxdof.internal import footprint_radius, pixel_prefilter  # noqa: E402


def interior(shape, border):
    m = np.zeros(shape, bool)
    m[border:-border, border:-border] = True
    return m


# The treatments' method names (cache keys and table rows) and their method objects.
METHODS = {"soft": jaxdof.Soft(), "occlusion": jaxdof.Occlusion()}


class FootprintRadiusModel(jaxdof.AbstractForwardModel):
    """The study's `footprint_radius` candidate as a forward model: `jaxdof.render` with the
    pixel-footprint correction on the radius instead of the image,
    `coc_filter(image, footprint_radius(coc_radius(depth, lens)), method=method)`.

    Study only: the core's correction is the image prefilter, `DefocusModel(footprint=True)`.
    Passed to `fit_lens(..., model=...)`, where a model of its own class compiles its own solve.
    The circles come from `coc_radius` (the focus distance), as in the fits cached before the
    forward models were objects; in float64 its derivative near focus at infinity is exact enough.
    """

    method: jaxdof.AbstractMethod

    @property
    def differentiable_in_lens(self) -> bool:
        # footprint_radius is differentiable (piecewise linear in r^2, then a square root)
        return self.method.differentiable_in_radius

    def __call__(self, image, depth, lens, *, max_radius):
        image = jnp.asarray(image)
        radius = footprint_radius(jaxdof.coc_radius(depth, lens)).astype(image.dtype)
        return jaxdof.coc_filter(
            image,
            radius,
            method=self.method,
            max_radius=max_radius,
            depth=depth if self.method.uses_depth else None,
        )


def forward_model(footprint, method: str, downsample: int) -> jaxdof.AbstractForwardModel:
    """The forward model of a treatment: `footprint` False (the plain render), `"prefilter"`
    (the core's correction, `DefocusModel(footprint=True)`) or `"radius"` (the study-only
    candidate, `FootprintRadiusModel`, measured at the photo's resolution only); `method` a name
    of `METHODS`."""
    if footprint == "radius":
        if downsample != 1:
            raise ValueError("the footprint-radius candidate is measured at downsample=1 only")
        return FootprintRadiusModel(METHODS[method])
    return jaxdof.DefocusModel(
        method=METHODS[method], footprint=footprint == "prefilter", downsample=downsample
    )


def fit_one(
    pin,
    z,
    target,
    a,
    d,
    weight=None,
    prefilter=False,
    starts=1,
    footprint=False,
    method="soft",
    downsample=1,
):
    """fit_lens from a start 15% off in focus distance and 30% off in f-number; returns a dict.
    With `downsample = s`, `pin` and `z` are the all-in-focus input at `s` times the target's
    resolution."""
    init = init_lens(a, d)
    image = pixel_prefilter_np(pin) if prefilter else pin
    t0 = time.perf_counter()
    f64 = lambda x: None if x is None else np.asarray(x, np.float64)
    # The forward model of the treatment (`forward_model`): the footprint-radius candidate is a
    # forward model of the study's own; the prefilter is the core's `DefocusModel(footprint=True)`.
    # Full resolution only: the coarse-to-fine pyramid came to fit_lens after most of the cached
    # fits were made; one setting for every treatment keeps the table a comparison of forward models.
    res = fit_lens(
        f64(image),
        f64(z),
        f64(target),
        init,
        weight=f64(weight),
        starts=starts,
        model=forward_model(footprint, method, downsample),
        pyramid=1,
    )
    jax.block_until_ready(res.lenses.focus_distance)
    dt = time.perf_counter() - t0
    fl = res.lens
    k_true = a * F_PX / d
    return dict(
        d_f=float(fl.focus_distance),
        d_f_se=float(np.asarray(res.stderr["focus_distance"]).ravel()[0]),
        K=float(fl.blur_scale),
        K_true=k_true,
        d_f_err=float(fl.focus_distance) / d - 1,
        K_err=float(fl.blur_scale) / k_true - 1,
        K_se=float(fl.blur_scale)
        * float(np.asarray(res.stderr["f_number"]).ravel()[0])
        / float(fl.f_number),
        success=bool(res.success),
        seconds=dt,
        message=res.message,
    )


def pixel_prefilter_np(image):
    return np.asarray(pixel_prefilter(image))


def init_lens(a, d):
    """The fit's start: 15% off in focus distance, 30% off in f-number (same f and pitch)."""
    lens = true_lens(a, d)
    return jaxdof.ThinLens(
        lens.focal_length, lens.f_number * 1.3, lens.focus_distance * 1.15, lens.pixel_pitch
    )


def fit_weight(z, a, d, edges: bool):
    """Interior mask (the model cannot know the scene outside the frame) times the edge weight.

    Both widths come from the starting lens, as a user would have them: the border is 1.6x its
    largest circle (+2 px), the edge width its largest circle (+1 px).
    """
    r0 = float(np.max(np.asarray(jaxdof.coc_radius(z, init_lens(a, d)))))
    w = interior(z.shape, int(math.ceil(1.6 * r0)) + 2).astype(np.float64)
    if edges:
        w = w * edge_weight(z, width=r0 + 1.0)
    return w


def fit_cached(
    name, a, d, edges=False, prefilter=False, starts=1, footprint=False, method="soft", scale=1
):
    key = (
        f"fit_{name}_A{a}_df{d}_e{int(edges)}_p{int(prefilter)}_s{starts}"
        + {False: "", "radius": "_fp", "prefilter": "_fpre"}[footprint]
        + ("" if method == "soft" else f"_{method}")
        + ("" if scale == 1 else f"_x{scale}")
    )

    def fit():
        pin, dist, thin, _ = load_scene(name)
        z = z_depth(dist)  # the weights are on the photo's pixels
        pin_in, z_in = (pin, z) if scale == 1 else load_scene_fine(name, scale)
        return fit_one(
            pin_in,
            z_in,
            thin[(a, d)],
            a,
            d,
            weight=fit_weight(z, a, d, edges),
            prefilter=prefilter,
            starts=starts,
            footprint=footprint,
            method=method,
            downsample=scale,
        )

    out, computed = cached_json(CACHE / f"{key}.json", fit)
    if computed:
        print(
            f"  {key}: d_f {out['d_f_err']:+.2%}, K {out['K_err']:+.2%}, {out['seconds']:.0f} s",
            flush=True,
        )
    return out


TREATMENTS = {
    "plain": (False, False, False, "soft", 1),
    "edge weight": (True, False, False, "soft", 1),
    "prefilter": (False, True, False, "soft", 1),
    "footprint": (False, False, "radius", "soft", 1),
    "edge + footprint": (True, False, "radius", "soft", 1),
    "fp prefilter": (False, False, "prefilter", "soft", 1),
    "edge + fp prefilter": (True, False, "prefilter", "soft", 1),
    "2x input": (False, False, False, "soft", 2),
    "2x + fp prefilter": (False, False, "prefilter", "soft", 2),
    "2x + edge + fp prefilter": (True, False, "prefilter", "soft", 2),
    "occlusion": (False, False, False, "occlusion", 1),
    "occlusion + footprint": (False, False, "radius", "occlusion", 1),
    "occlusion + edge + footprint": (True, False, "radius", "occlusion", 1),
    "occlusion + fp prefilter": (False, False, "prefilter", "occlusion", 1),
    "occlusion + edge + fp prefilter": (True, False, "prefilter", "occlusion", 1),
    "2x + occlusion + fp prefilter": (False, False, "prefilter", "occlusion", 2),
    "2x + occlusion + edge + fp prefilter": (True, False, "prefilter", "occlusion", 2),
}


def fit_plan():
    """(scene, A, d_f, treatment): every scene and lens plain and with the footprint radius; the edge
    weight where there are edges; the image prefilter on the slant's small circles (A = 0.03 m)."""
    plan = [(n, a, d, "plain") for n in SCENES for a, d in CONFIGS]
    plan += [(n, a, d, "edge weight") for n in ("planes", "occluders") for a, d in CONFIGS]
    plan += [(n, a, d, "prefilter") for n in ("slant",) for a, d in CONFIGS if a == 0.03]
    plan += [(n, a, d, "footprint") for n in SCENES for a, d in CONFIGS]
    plan += [(n, a, d, "edge + footprint") for n in ("occluders",) for a, d in CONFIGS]
    # the occlusion-aware render is exactly "soft" on slant (one layer): fitted where edges exist
    plan += [(n, a, d, "occlusion") for n in ("planes", "occluders") for a, d in CONFIGS]
    plan += [
        (n, a, d, "occlusion + footprint") for n in ("planes", "occluders") for a, d in CONFIGS
    ]
    plan += [(n, a, d, "occlusion + edge + footprint") for n in ("occluders",) for a, d in CONFIGS]
    # the radius-aware image prefilter (item 6), alone and with each edge treatment
    plan += [(n, a, d, "fp prefilter") for n in SCENES for a, d in CONFIGS]
    plan += [(n, a, d, "edge + fp prefilter") for n in ("planes", "occluders") for a, d in CONFIGS]
    plan += [
        (n, a, d, "occlusion + fp prefilter") for n in ("planes", "occluders") for a, d in CONFIGS
    ]
    plan += [
        (n, a, d, "occlusion + edge + fp prefilter") for n in ("occluders",) for a, d in CONFIGS
    ]
    # the all-in-focus input at twice the photo's resolution (the detail inside each photo pixel)
    plan += [(n, a, d, "2x + fp prefilter") for n in SCENES for a, d in CONFIGS]
    plan += [
        (n, a, d, "2x + edge + fp prefilter") for n in ("planes", "occluders") for a, d in CONFIGS
    ]
    plan += [
        (n, a, d, "2x + occlusion + edge + fp prefilter")
        for n in ("occluders",)
        for a, d in CONFIGS
    ]
    plan += [
        (n, a, d, "2x + occlusion + fp prefilter")
        for n in ("planes", "occluders")
        for a, d in CONFIGS
    ]
    plan += [(n, a, d, "2x input") for n in ("slant",) for a, d in CONFIGS]
    return plan


def run_fits(only=None):
    """Every fit of `fit_plan` (cached), or only those of the treatments in `only`."""
    out = {}
    for n, a, d, t in fit_plan():
        if only is not None and t not in only:
            continue
        e, p, fp, meth, sc = TREATMENTS[t]
        out[(n, a, d, t)] = fit_cached(
            n, a, d, edges=e, prefilter=p, footprint=fp, method=meth, scale=sc
        )
    return out
