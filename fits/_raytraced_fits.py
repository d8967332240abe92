"""The lens fits of `raytraced.py`: forward-model treatments, the fit plan, and the fits (cached).

Every fit is cached in `fits/.cache/raytraced/fit_*.json`, so a report re-run fits nothing new;
the default-call study's fits (`run_default`) under `default/<fingerprint>_<precision>/`.
"""

from __future__ import annotations

import hashlib
import math
import pathlib
import re
import time
import traceback

import jax


jax.config.update("jax_enable_x64", True)

import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402
from _common import FITS, cached_json  # noqa: E402

# The study-only candidates of the pixel-footprint correction (semi-internal).
from _footprint_candidates import footprint_radius, pixel_prefilter  # noqa: E402
from _raytraced_scenes import (  # noqa: E402
    CACHE,
    CONFIGS,
    F_PX,
    LANDSCAPE_INIT_FOCUS,
    SCENES,
    default_inputs,
    default_lenses,
    load_scene,
    load_scene_fine,
    true_lens,
    z_depth,
)

import jaxdof  # noqa: E402
from jaxdof import edge_weight, fit_lens  # noqa: E402
from jaxdof.internal import (  # noqa: E402
    release_compiled_code,
)


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
        release_compiled_code()  # a long study would reach the kernel's limit of memory maps
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


# ----------------------------------------------------------------------------- the default call
# `raytraced_default.py`: `fit_lens(image, depth, photo, init)` with every default, on every scene
# and lens of `DEFAULT_SCENES`, each fit cached under a fingerprint of the library's source.

FOCUS_TOL, K_TOL = 0.02, 0.05  # the goal: focus distance within 2 %, blur scale K within 5 %
SIGMAS = 3.0  # a miss more than this many reported standard errors off, with success, is silent


def default_init(a, d):
    """The default-call study's start: f-number 1.5x the truth's and focus 20 % short
    (`LANDSCAPE_INIT_FOCUS` for a lens focused at infinity); f and pixel pitch the truth's."""
    lens = true_lens(a, d)
    focus = LANDSCAPE_INIT_FOCUS if math.isinf(d) else 0.8 * d
    return jaxdof.ThinLens(lens.focal_length, lens.f_number * 1.5, focus, lens.pixel_pitch)


def library_dir() -> pathlib.Path:
    """The folder of the `jaxdof` package imported (this checkout's, or a copy's)."""
    return pathlib.Path(jaxdof.__file__).resolve().parent


def fingerprint() -> str:
    """12 hex digits of the imported library's source and this study's scene and fit code: the
    default fits are cached per fingerprint, so a re-run with the same code fits nothing again."""
    h = hashlib.sha256()
    lib = library_dir()
    named = [(f.relative_to(lib.parent), f) for f in sorted(lib.rglob("*.py"))]
    named += [(f, FITS / f) for f in ("_raytraced_scenes.py", "_raytraced_fits.py")]
    for name, f in named:
        h.update(str(name).encode() + b"\0" + f.read_bytes())
    return h.hexdigest()[:12]


def _first(x) -> float:
    return float(np.asarray(x, np.float64).reshape(-1)[0])


def _status(res) -> tuple[str, dict | None]:
    """The status's name and `res.to_dict()` (None if it fails)."""
    try:
        out = res.to_dict()
        return str(out["status"]), out
    except Exception as err:  # a result the report cannot read is itself a finding
        return f"unreadable ({type(err).__name__})", None


def _log_stderr(res, lens, x_u: float) -> float:
    """Relative standard error of a blur measure `X(N, u)` with `d ln X / d ln N = -1` and
    `d ln X / du = x_u` (u = 1 / d_f): from the reported `stderr` of the f-number and of the
    focus power, with their correlation from `covariance` (a correlation is unchanged by any
    inflation of the standard errors); their worst case (|a| + |b|) where it is not finite."""
    n = float(lens.f_number)
    a = _first(res.stderr["f_number"]) / n
    b = x_u * _first(res.focus_power_stderr)
    names, cov = list(res.names), np.asarray(res.covariance, np.float64)
    rho = np.nan
    if "f_number" in names and "focus_distance" in names:
        i, j = names.index("f_number"), names.index("focus_distance")
        with np.errstate(divide="ignore", invalid="ignore"):
            rho = -cov[i, j] / np.sqrt(cov[i, i] * cov[j, j])  # u falls as d_f grows
    if not np.isfinite(rho):
        return abs(a) + abs(b)
    # d ln X = -dN / N + x_u du
    return math.sqrt(max(a * a + b * b - 2 * rho * a * b, 0.0))


def default_record(res, a, d, z) -> dict:
    """A fit of the default study against the truth: status, errors, standard errors, verdict.

    Focus is compared in the focus power `u = 1 / d_f` (finite through infinity): `focus_err` is
    `d_f / d_f,true - 1`, or for a lens focused at infinity `u / u_near` (u_near = 1 / nearest
    depth: the share of the largest circle the focus error moves every circle by). Blur is `K`,
    or for a lens at infinity (K = 0 there) `S = K d_f = f^2 / (2 N p (1 - f u))`, the circle per
    diopter (`A f_px` for the ray tracer). `focus_z` and `k_z`: |error| / reported stderr.
    """
    lens = res.lens
    f, n, p = (float(getattr(lens, k)) for k in ("focal_length", "f_number", "pixel_pitch"))
    u = _first(res.focus_power)
    at_inf = math.isinf(d)
    u_true = 0.0 if at_inf else 1.0 / d
    u_near = 1.0 / float(np.min(z))
    if at_inf:
        blur, blur_true, x_u = f * f / (2 * n * p * (1 - f * u)), a * F_PX, f / (1 - f * u)
        focus_err = u / u_near
    else:
        blur, blur_true = float(lens.blur_scale), a * F_PX / d
        x_u = 1 / (u * (1 - f * u)) if u > 0 else np.inf
        focus_err = float(lens.focus_distance) / d - 1
    k_err = blur / blur_true - 1
    se_u = _first(res.focus_power_stderr)
    se_k = blur * _log_stderr(res, lens, x_u)
    status, as_dict = _status(res)
    within = abs(focus_err) < FOCUS_TOL and abs(k_err) < K_TOL
    focus_z = abs(u - u_true) / se_u if se_u > 0 else np.inf
    k_z = abs(blur - blur_true) / se_k if se_k > 0 else np.inf
    success = bool(res.success)
    return dict(
        success=success,
        status=status,
        message=res.message,
        focus_distance=float(lens.focus_distance),
        focus_power=u,
        focus_err=focus_err,
        k=blur,
        k_true=blur_true,
        k_err=k_err,
        focus_power_se=se_u,
        k_se=se_k,
        focus_z=focus_z,
        k_z=k_z,
        within=within,
        silent=success and not within and max(focus_z, k_z) > SIGMAS,
        pixels_used=int(res.pixels_used),
        border=int(res.border),
        result=as_dict,
    )


def no_paths(text: str) -> str:
    """`text` without this machine's folders: paths from the package (or the checkout) down."""
    text = re.sub(r"[^\s\"']*(site|dist)-packages/", "", text)
    for root in {str(library_dir().parent), str(FITS.parent)}:
        text = text.replace(root + "/", "")
    return text


def default_fit(scene, a, d, x64: bool, options: dict | None = None) -> dict:
    """`fit_lens(image, depth, photo, init)` with every default (or `options` forced) on one
    scene and lens; an exception is caught and recorded (a finding, not a crash of the study)."""
    image, z, target = default_inputs(scene, a, d)
    dtype = np.float64 if x64 else np.float32
    image, z, target = (np.asarray(x, dtype) for x in (image, z, target))
    release_compiled_code()  # a long study would reach the kernel's limit of memory maps
    t0 = time.perf_counter()
    try:
        res = fit_lens(image, z, target, default_init(a, d), **(options or {}))
        jax.block_until_ready(res.lenses.focus_distance)
    except Exception as err:
        head = (str(err).splitlines() or [""])[0][:300]
        return dict(
            scene=scene,
            a=a,
            d=d,
            seconds=time.perf_counter() - t0,
            exception=no_paths(f"{type(err).__name__}: {head}"),
            traceback=[no_paths(line) for line in traceback.format_exc().splitlines()][-25:],
        )
    seconds = time.perf_counter() - t0
    record = default_record(res, a, d, z)
    return dict(scene=scene, a=a, d=d, seconds=seconds, treatment=str(res.treatment), **record)


def run_default(
    scenes,
    x64: bool,
    fp: str,
    variant: str = "",
    options: dict | None = None,
    lenses: tuple[int, ...] | None = None,
) -> list[dict]:
    """Every default fit of `scenes` (cached per fingerprint `fp` and precision), or with
    `options` forced (cached apart under the name `variant`); `lenses`: the indices into each
    scene's `default_lenses` to fit (`None`: all)."""
    folder = CACHE / "default" / f"{fp}_{'f64' if x64 else 'f32'}{variant}"
    out = []
    for scene in scenes:
        chosen = default_lenses(scene)
        if lenses is not None:
            chosen = [chosen[i] for i in lenses]
        for a, d in chosen:
            rec, computed = cached_json(
                folder / f"{scene}_A{a}_df{d}.json",
                lambda scene=scene, a=a, d=d: default_fit(scene, a, d, x64, options),
            )
            if computed:
                what = (
                    rec.get("exception")
                    or f"{rec['status']}, focus {rec['focus_err']:+.2%}, K {rec['k_err']:+.2%}"
                )
                print(f"  {scene} A={a} d_f={d}: {what} ({rec['seconds']:.0f} s)", flush=True)
            out.append(rec)
    return out
