"""How well does `jaxdof.fit_lens` recover a lens, against the Cramér-Rao bound and scipy? (issue 3)

Questions:

1. From one photo, are `f_number` and `focus_distance` recovered from wrong starts on procedural
   scenes, and is the spread over noisy trials at the Cramér-Rao bound (CRB) computed from the
   Jacobian at the truth? Does the reported standard error match that spread?
2. Does a focus bracket (three photos, `f` and `N` shared) determine `f` and `N` apart, and how well?
3. What do wall time and function evaluations look like against `scipy.optimize.least_squares`
   with a finite-difference Jacobian on the same (jitted) forward model, at 24 x 24 (where
   per-call overheads dominate) and at 96 x 96 and 192 x 192 (where the renders do), with and
   without `fit_lens`'s coarse-to-fine pyramid, from one start and from its default 4 starts
   (scipy from the same 4 starts)?

Run:

    python fits/recover.py            # 24 x 24 scenes, 30 trials per noise level (~10-15 min on 2 cores)
    python fits/recover.py --quick    # 6 trials, fewer timing runs (a few minutes)
    python fits/recover.py --cost-only  # only section 3 (cost vs scipy), keeping sections 1-2

Writes `fits/results/recover.md` and `fits/results/recover.png` (`--quick` adds `_quick`).

Method. float64. Grey 24 x 24 textures (uniform noise smoothed by a 0.7 px Gaussian) on four depth
maps: `planes` (three fronto-parallel bands at 1.2, 2 and 3.5 m), `slant` (a plane from 1 to 3 m),
`steps` (six random depth steps in 1-4 m), `smooth` (smoothed random inverse depth in 1-4 m).
The true lens is f = 50 mm, N = 2, pixel pitch 80 um (large pixels, so that circles of a few pixels
fit a small image), focus distance 1.6 m (1.8 m for `smooth`), giving K ~ 4.5-5 px and circles up to ~3.6 px. Targets are the
soft render plus Gaussian noise of standard deviation sigma in {0, 0.001, 0.01, 0.03} (the image is
in [0.2, 0.8]). Each trial starts from a lens off by a random factor in [1/2, 2] in K (through N)
and a random +-30 % in the focus distance, and fits `free=("f_number", "focus_distance")` with the
default solver and starts, `max_radius=6` px (fixed, so that every fit shares one compilation).
The CRB is `sigma^2 (J^T J)^{-1}` with `J` the Jacobian of the render with respect to (N, d_f) at
the truth (`jax.jacfwd` of `jaxdof.render`, independent of the fitting code), and for K by the
delta method. The RMSE is about the truth (bias included).
"""

from __future__ import annotations

import argparse
import functools
import os
import platform
import sys
import time
from functools import partial

import jax


jax.config.update("jax_enable_x64", True)

import equinox as eqx  # noqa: E402
import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402
import optimistix as optx  # noqa: E402
import scipy  # noqa: E402
import scipy.ndimage  # noqa: E402
import scipy.optimize  # noqa: E402
from _common import (  # noqa: E402
    accelerator,
    load_json,
    median_time,
    result_path,
    save_json,
    write_markdown,
)

import jaxdof  # noqa: E402
from jaxdof import ThinLens, render  # noqa: E402

# Semi-internal: the automatic pyramid rule, the largest circle of a lens, fit_lens's multi-start
# spread (which scipy is given too), and the timer of fit_lens's compiled stages.
from jaxdof.internal import auto_levels, max_circle, record_stages, start_lenses  # noqa: E402


# The targets here are `render`'s default model (plus noise): the study fits exactly that model
# (`fit_lens` would otherwise choose its treatment of a real photo, `jaxdof/_scene.py`).
fit_lens = functools.partial(jaxdof.fit_lens, method="soft", footprint=False, edge_weight=False)


H = W = 24
PITCH = 8e-5
F = 0.05
N_TRUE = 2.0
WINDOW = 6.0
SIGMAS = (0.0, 0.001, 0.01, 0.03)
FREE = ("f_number", "focus_distance")

# The closing paragraph of section 3 (written from the measured numbers; see the report).
WHY_NOT_10X = (
    "Why the ratio is not 10x. A warm call is all solve (no re-tracing, checked in `tests/test_fit.py`), and the "
    "residual and Jacobian at the solution are read back from the solver's last step instead of being recomputed. "
    "Each full-resolution LM step costs a render plus the tangent pass of the Jacobian. The two tangents do share "
    "the filter's weight evaluation: the residual's JVP rule pushes them as one vmapped JVP, and the soft filter's "
    "tangent primitive receives the image and radius unbatched (`__batch_axes=(None, None, None, 0)` in the "
    "jaxpr), so the weights and their slopes are computed once per offset and only the cheap accumulation is "
    "doubled (first table: the vmapped pair costs little more than the tangent of one JVP, and far less than two "
    "separate JVPs; `jax.jacfwd` discards the primal, which XLA then drops, so that column is the tangent pass "
    "alone). With the damped solve on top, an LM step still costs 2-5 renders (the per-step bullets: LM step "
    "time over the render time of the first table), about what a trf iteration costs scipy (a 2-point Jacobian "
    "and a trial point, three renders), and LM takes about as many steps as trf takes Jacobians. Coarse-to-fine moves the search from wrong starts to images 4^l times "
    "cheaper, but the full-resolution level still takes 6-11 LM steps. The coarse minimum is off the "
    "full-resolution one by the downsampling's model error: circles of 0.5-1 fine pixel render as the identity "
    "one level down. In one traced 96 x 96 slant fit (`verbose=True`) the level-1 solution was 3 % off in N and "
    "2.5 % in d_f; from there LM needed 4 full-resolution steps to converge and 3 more before a step fell under "
    "the 1e-8 tolerance. With circles of at "
    "most ~3.6 px the automatic pyramid also stops after 1-2 halvings: the coarsest level keeps the init's "
    "largest circle at 1 px or more. So from one start the pyramid gains little over full resolution (the "
    "bullets above). It pays off when fit_lens runs several starts, its default: the starts that wander or stall "
    "do so on the coarse level, at a looser tolerance, instead of holding the whole vmapped full-resolution solve "
    "until they finish. Since 2026-11-23 the full-resolution level also refines the init itself: in one 96 x 96 "
    "depth-steps trial of this study every start went, on the 48 x 48 level, to N = 17, d_f = 0.42 (the coarse "
    "images keep too little of the 0.7 px texture grain to show the blur), and the full-resolution refinement "
    "of that basin returned N = 14, d_f = 0.48 with success and four times the truth's loss. Carrying the init "
    "fixes that (test `test_pyramid_cannot_lead_the_init_astray`) at a price: the full-resolution solve now runs "
    "two starts, the init's from 2x off in K, so the default call's lead over scipy fell from 6.8x to "
    "2.5-2.7x at 192 x 192 on this machine (two runs), and from one start coarse-to-fine became slower than "
    "full resolution alone (0.5-0.8x), so `pyramid=None` now stays at full resolution when `starts=1`. "
    "Reaching 10x against one scipy start needs full-resolution steps cheaper than a render, "
    "or fewer of them. For cheaper steps: the soft filter computes its tap weights once in the primal render and "
    "again in the tangent, and one fused pass would save most of a render per step. For fewer steps: a coarse level whose "
    "minimum lies within a step or two of the full-resolution one, which box-averaging does not give for circles "
    "of a few pixels. Neither is done here.\n"
)


def texture(rng, size=H):
    img = scipy.ndimage.gaussian_filter(rng.uniform(size=(size, size)), 0.7)
    img = (img - img.min()) / (img.max() - img.min())
    return 0.2 + 0.6 * img


def scenes(rng, size=H):
    """The four scenes at `size x size` (the texture keeps its 0.7 px grain; the depth maps keep
    their shapes, scaled to the image)."""
    h = w = size
    yy, xx = np.mgrid[0:h, 0:w]
    out = {}
    out["planes"] = np.select([xx < w // 3, xx < 2 * w // 3], [1.2, 2.0], 3.5).astype(float)
    out["slant"] = 1.0 + 2.0 * xx / (w - 1)
    edges = np.sort(rng.choice(np.arange(3, w - 3), 5, replace=False))
    levels = rng.uniform(1.0, 4.0, size=6)
    out["steps"] = levels[np.searchsorted(edges, xx[0], side="right")][None, :] + 0 * yy
    inv = scipy.ndimage.gaussian_filter(rng.standard_normal((h, w)), 6.0 * size / H)
    inv = (inv - inv.min()) / (inv.max() - inv.min())
    out["smooth"] = 1 / (1 / 4.0 + inv * (1 / 1.0 - 1 / 4.0))
    return {k: (texture(rng, size), v.astype(np.float64)) for k, v in out.items()}


def true_lens(name):
    return ThinLens(F, N_TRUE, 1.8 if name == "smooth" else 1.6, PITCH)


def blur_scale(n, d_f):
    return F * F / (2 * n * (d_f - F) * PITCH)


@jax.jit
def _forward(image, depth, n, d_f):
    return render(image, depth, ThinLens(F, n, d_f, PITCH), max_radius=WINDOW)


@jax.jit
def _jacobian(image, depth, theta):
    """d render / d (N, d_f) at `theta`, by forward mode (independent of the fitting code)."""

    def model(theta):
        lens = ThinLens(F, theta[0], theta[1], PITCH)
        return render(image, depth, lens, max_radius=WINDOW).ravel()

    return jax.jacfwd(model)(theta)


@jax.jit
def _jvp_one(image, depth, theta):
    """The render and one tangent (d / d d_f) at `theta`: one forward-mode pass."""

    def model(d_f):
        lens = ThinLens(F, theta[0], d_f, PITCH)
        return render(image, depth, lens, max_radius=WINDOW)

    return jax.jvp(model, (theta[1],), (jnp.ones_like(theta[1]),))


@jax.jit
def _jacobian_serial(image, depth, theta):
    """The same Jacobian as `_jacobian`, one tangent pass after the other (no sharing between the
    two passes except the render, unless XLA finds it): the comparison for the vmapped one."""

    def model(theta):
        lens = ThinLens(F, theta[0], theta[1], PITCH)
        return render(image, depth, lens, max_radius=WINDOW).ravel()

    cols = [jax.jvp(model, (theta,), (e,))[1] for e in jnp.eye(2, dtype=theta.dtype)]
    return jnp.stack(cols, axis=1)


# The border band `fit_lens` leaves out by default with `max_radius=WINDOW` (its `border="auto"`:
# the window's reach, where the photo holds light from outside the frame): the bound is that of
# the pixels a fit may use.
BAND = int(np.ceil(WINDOW))


def crb(image, depth, lens, sigma, band=BAND):
    """CRB standard deviations of (N, d_f) and of K, from the Jacobian of the render at the truth
    over the pixels inside the border `band`."""
    theta = jnp.array([float(lens.f_number), float(lens.focus_distance)])
    jac = np.asarray(_jacobian(jnp.asarray(image), jnp.asarray(depth), theta))
    inside = np.zeros(np.shape(image)[:2])
    inside[band : inside.shape[0] - band, band : inside.shape[1] - band] = 1
    jac = jac * inside.reshape(-1, 1)
    cov = sigma**2 * np.linalg.inv(jac.T @ jac)
    n, d_f = float(theta[0]), float(theta[1])
    k = blur_scale(n, d_f)
    grad_k = np.array([-k / n, -k / (d_f - F)])
    return np.sqrt(np.diag(cov)), float(np.sqrt(grad_k @ cov @ grad_k)), cov


def random_init(rng, lens):
    n0, d0 = float(lens.f_number), float(lens.focus_distance)
    d = d0 * rng.uniform(0.7, 1.3)
    k = blur_scale(n0, d0) * np.exp(rng.uniform(np.log(0.5), np.log(2.0)))
    return ThinLens(F, F * F / (2 * k * (d - F) * PITCH), d, PITCH)


def scipy_fit(fwd, target, init, tol):
    """scipy least_squares, 2-point FD Jacobian, same log coordinates, counting forward renders."""
    count = [0]

    def fun(x):
        count[0] += 1
        n, d_f = np.exp(x[0]), F + np.exp(x[1])
        return (np.asarray(fwd(jnp.asarray(n), jnp.asarray(d_f))) - target).ravel()

    x0 = np.array([np.log(float(init.f_number)), np.log(float(init.focus_distance) - F)])
    t, c = time.perf_counter(), time.process_time()
    sol = scipy.optimize.least_squares(
        fun, x0, jac="2-point", method="trf", xtol=tol, ftol=tol, gtol=tol
    )
    wall, cpu = time.perf_counter() - t, time.process_time() - c
    return np.exp(sol.x[0]), F + np.exp(sol.x[1]), wall, cpu, count[0], sol.status > 0


def scipy_multi(fwd, target, depth, init, tol, n_starts=4):
    """scipy from the same starts as `fit_lens`'s default multi-start
    (`jaxdof.internal.start_lenses`: the init, then focus distances spread in diopters keeping
    K), one after the other, keeping the lowest cost: the scipy baseline for the default
    `fit_lens` call. Wall and CPU summed."""
    base = np.array(
        [[float(init.focal_length), float(init.f_number), float(init.focus_distance), PITCH]]
    )
    d = np.asarray(depth, np.float64)
    starts = start_lenses(base, d, free=FREE, starts=n_starts)
    best, wall, cpu, evals = None, 0.0, 0.0, 0
    for s in starts[:, 0]:
        n_s, d_s, w, c, e, _ = scipy_fit(fwd, target, ThinLens(F, s[1], s[2], PITCH), tol)
        wall, cpu, evals = wall + w, cpu + c, evals + e
        cost = float(np.sum((np.asarray(fwd(jnp.asarray(n_s), jnp.asarray(d_s))) - target) ** 2))
        if best is None or cost < best[0]:
            best = (cost, n_s, d_s)
    return best[1], best[2], wall, cpu, evals


def timed_fit(*args, **kwargs):
    """`fit_lens` with wall and process CPU time of the whole call, results on the host."""
    t, c = time.perf_counter(), time.process_time()
    res = fit_lens(*args, **kwargs)
    jax.block_until_ready(res)
    return res, time.perf_counter() - t, time.process_time() - c


def outside_compiled(reps=15):
    """Wall time of a warm `fit_lens` call (24 x 24 `planes`, one start) spent outside its
    compiled stages (input checks, set-up, message): the call's time less the stages' own, which
    `jaxdof.internal.record_stages` times (blocking) inside it (`fit_starts`, then `finish`)."""
    rng = np.random.default_rng(7)
    image, depth = scenes(rng)["planes"]
    lens = true_lens("planes")
    target = np.asarray(render(image, depth, lens, max_radius=WINDOW))
    target = target + 0.01 * rng.standard_normal(target.shape)
    init = random_init(rng, lens)
    kw = dict(free=FREE, max_radius=WINDOW, starts=1, pyramid=1)
    fit_lens(image, depth, target, init, **kw)
    total, outside = [], []
    for _ in range(reps):
        with record_stages() as log:
            t = time.perf_counter()
            jax.block_until_ready(fit_lens(image, depth, target, init, **kw))
            total.append(time.perf_counter() - t)
        outside.append(total[-1] - sum(seconds for _, seconds in log))
    return dict(total=float(np.median(total)), outside=float(np.median(outside)))


def cost_study(quick, sizes=None):
    """Section 3: wall time and evaluations of fit_lens (one start, default starts) and scipy.

    For every size, scene and trial: one warm-up call of each (compilation excluded), then
    `reps` interleaved timed calls of each from the same start on the same target; medians.
    Also the cost of one render and of the Jacobian that one LM step builds, in isolation.
    """
    rng = np.random.default_rng(20261123)
    reps = 3
    # (image size, trials per scene)
    trials = {H: 2 if quick else 4, 96: 1 if quick else 2}
    sizes = [(z, trials.get(z, 1)) for z in (sizes or (H, 96, 192))]
    sigma_t = 0.01
    timing, unit = [], {}
    for size, n_trials in sizes:
        sc = scenes(rng, size)
        for name, (image, depth) in sc.items():
            lens = true_lens(name)
            img_j, dep_j = jnp.asarray(image), jnp.asarray(depth)
            fwd = partial(_forward, img_j, dep_j)  # one compilation per size
            clean = np.asarray(fwd(lens.f_number, lens.focus_distance))
            if name == "slant":
                unit[size] = unit_costs(img_j, dep_j, fwd, lens)
            for _ in range(n_trials):
                target = clean + sigma_t * rng.standard_normal(clean.shape)
                init = random_init(rng, lens)
                row = time_trial(image, depth, target, init, fwd, reps, size, name)
                timing.append(row)
                print(row, flush=True)
    return dict(
        timing=timing,
        unit={str(k): v for k, v in unit.items()},
        outside=outside_compiled(),
        reps=reps,
        load=os.getloadavg()[0],
        date=time.strftime("%Y-%m-%d %H:%M UTC", time.gmtime()),
        **accelerator(),
    )


def unit_costs(img_j, dep_j, fwd, lens) -> dict:
    """Median wall and CPU time of one render, one JVP, the vmapped Jacobian and two serial JVPs."""
    theta = jnp.array([N_TRUE, float(lens.focus_distance)])
    n0, d0 = lens.f_number, lens.focus_distance
    return dict(
        render=median_time(partial(fwd, n0, d0), 20),
        jvp1=median_time(partial(_jvp_one, img_j, dep_j, theta), 20),
        jacobian=median_time(partial(_jacobian, img_j, dep_j, theta), 20),
        serial=median_time(partial(_jacobian_serial, img_j, dep_j, theta), 20),
    )


def time_trial(image, depth, target, init, fwd, reps, size, name) -> dict:
    """One trial of section 3: every configuration warmed up, then `reps` interleaved timed calls
    of each; medians, step counts and the answers' distances in standard errors."""
    kw = dict(free=FREE, max_radius=WINDOW)
    flat = dict(kw, pyramid=1)  # full resolution only
    # Coarse-to-fine from one start, with the levels the automatic rule picks for
    # several starts (from one start the default is full resolution: see the report).
    row = np.array([F, float(init.f_number), float(init.focus_distance), PITCH])
    coarse1 = dict(kw, pyramid=auto_levels(image.shape[:2], max_circle(row, depth)))
    # Warm-up (each configuration compiles once per size).
    fit_lens(image, depth, target, init, starts=1, **flat)
    fit_lens(image, depth, target, init, starts=1, **coarse1)
    fit_lens(image, depth, target, init, **kw)
    fit_lens(image, depth, target, init, **flat)
    scipy_fit(fwd, target, init, 1e-8)
    keys = "ours1 cpu1 pyr1 pyr_cpu1 ours4 pyr4 pyr_cpu4 scipy scipy_cpu scipy4 scipy_cpu4"
    rec = {k: [] for k in keys.split()}
    for _ in range(reps):
        r1, w1, c1 = timed_fit(image, depth, target, init, starts=1, **flat)
        rec["ours1"].append(w1)
        rec["cpu1"].append(c1)
        p1, wp, cp = timed_fit(image, depth, target, init, starts=1, **coarse1)
        rec["pyr1"].append(wp)
        rec["pyr_cpu1"].append(cp)
        p4, w4, c4 = timed_fit(image, depth, target, init, **kw)
        rec["pyr4"].append(w4)
        rec["pyr_cpu4"].append(c4)
        rec["ours4"].append(timed_fit(image, depth, target, init, **flat)[1])
        n_s, d_s, ws, cs, evals, sok = scipy_fit(fwd, target, init, 1e-8)
        n4, d4, ws4, cs4, evals4 = scipy_multi(fwd, target, depth, init, 1e-8)
        rec["scipy4"].append(ws4)
        rec["scipy_cpu4"].append(cs4)
        rec["scipy"].append(ws)
        rec["scipy_cpu"].append(cs)
    row = {k: float(np.median(v)) if v else float("nan") for k, v in rec.items()}
    row.update(
        size=size,
        scene=name,
        steps=int(r1.num_steps),
        pyr_steps=int(p1.num_steps),
        evals4=evals4,
        # The default call (4 starts, pyramid) against scipy's best of the same starts.
        d4N=abs(n4 - float(p4.lens.f_number)) / float(p4.stderr["f_number"]),
        d4D=abs(d4 - float(p4.lens.focus_distance)) / float(p4.stderr["focus_distance"]),
        levels=int(p1.levels),
        pyr_ok=bool(p1.success),
        # The pyramid's answer against the full-resolution fit's, in standard errors.
        pN=abs(float(p1.lens.f_number) - float(r1.lens.f_number)) / float(r1.stderr["f_number"]),
        pD=abs(float(p1.lens.focus_distance) - float(r1.lens.focus_distance))
        / float(r1.stderr["focus_distance"]),
        evals=evals,
        scipy_ok=bool(sok),
        ours_ok=bool(r1.success),
        # Agreement in units of the reported standard error.
        dN=abs(n_s - float(r1.lens.f_number)) / float(r1.stderr["f_number"]),
        dD=abs(d_s - float(r1.lens.focus_distance)) / float(r1.stderr["focus_distance"]),
    )
    return row


def parse_args(argv=None) -> argparse.Namespace:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--quick", action="store_true", help="6 trials per noise level, fewer timings")
    ap.add_argument(
        "--report-only", action="store_true", help="rewrite the report from the saved raw results"
    )
    ap.add_argument(
        "--trials", type=int, default=None, help="override the number of trials (smoke runs)"
    )
    ap.add_argument(
        "--cost-only",
        action="store_true",
        help="re-run only section 3 (cost against scipy) and rewrite the report, keeping the saved "
        "results of sections 1 and 2",
    )
    ap.add_argument(
        "--recovery-only",
        action="store_true",
        help="re-run only sections 1 and 2 (recovery, bracket) and rewrite the report, keeping the "
        "saved results of section 3",
    )
    ap.add_argument(
        "--bracket-only",
        action="store_true",
        help="re-run only section 2 (the focus bracket) and rewrite the report, keeping the "
        "saved results of sections 1 and 3",
    )
    ap.add_argument(
        "--recompute-bounds",
        action="store_true",
        help="with --report-only: compute the Cramér-Rao bounds of the saved rows anew (e.g. after "
        "the fit's border band changed which pixels it uses)",
    )
    ap.add_argument(
        "--tag",
        default="",
        help="with --cost-only: suffix of the outputs (e.g. _gpu on a GPU machine); sections 1 and 2 "
        "are copied from the untagged run",
    )
    ap.add_argument(
        "--cost-sizes", type=int, nargs="+", default=None, help="image sides of section 3"
    )
    return ap.parse_args(argv)


def main(argv=None):
    args = parse_args(argv)
    raw_path = result_path("recover", "_raw.json", quick=args.quick)
    if args.report_only:
        raw = load_json(raw_path)
        if args.recompute_bounds:
            raw["rows"] = recompute_bounds(raw["rows"])
            save_json(raw_path, raw)
        return report(raw, args.quick)
    if args.bracket_only:
        raw = load_json(raw_path)
        rng = np.random.default_rng(20261122)
        raw["bracket"] = bracket_study(scenes(rng), rng, min(raw["trials"], 10)).tolist()
        save_json(raw_path, raw)
        return report(raw, args.quick)
    if args.cost_only:
        raw = load_json(raw_path)
        raw["cost"] = cost_study(args.quick, args.cost_sizes)
        raw.pop("timing", None)  # the format of section 3 before the cost study was split out
        save_json(result_path("recover", "_raw.json", quick=args.quick, tag=args.tag), raw)
        return report(raw, args.quick, args.tag)
    trials = args.trials or (6 if args.quick else 30)
    n_bracket = min(trials, 3 if args.quick else 10)
    rng = np.random.default_rng(20261122)
    sc = scenes(rng)
    t_start = time.perf_counter()
    rows, compile_s = recovery_study(sc, rng, trials)  # 1. recovery vs CRB
    bracket = bracket_study(sc, rng, n_bracket)  # 2. focus bracket
    # 3. timing vs scipy (or the saved one)
    cost = load_json(raw_path)["cost"] if args.recovery_only else cost_study(args.quick)
    total = time.perf_counter() - t_start
    raw = dict(
        rows=[
            {k: (v.tolist() if isinstance(v, np.ndarray) else v) for k, v in r.items()}
            for r in rows
        ],
        bracket=bracket.tolist(),
        cost=cost,
        compile_s=compile_s,
        trials=trials,
        total=total,
    )
    save_json(raw_path, raw)
    report(raw, args.quick)


def recompute_bounds(rows):
    """The rows with their Cramér-Rao bounds computed anew (`crb`, over the pixels inside the
    border band) on the same scenes (same seed)."""
    sc = scenes(np.random.default_rng(20261122))
    for r in rows:
        if r["sigma"] > 0:
            image, depth = sc[r["scene"]]
            c, ck, _ = crb(image, depth, true_lens(r["scene"]), r["sigma"])
            r["crb"] = [float(c[0]), float(c[1]), ck]
    return rows


def recovery_study(sc, rng, trials):
    """Section 1: `trials` noisy fits per scene and noise level; `(rows, compile seconds)`, the
    first fit's wall time standing for the compilation (left out of the median wall times)."""
    rows = []
    compile_s = None
    for name, (image, depth) in sc.items():
        lens = true_lens(name)
        clean = np.asarray(render(image, depth, lens, max_radius=WINDOW))
        for sigma in SIGMAS:
            fits = [one_fit(image, depth, clean, sigma, lens, rng) for _ in range(trials)]
            walls = [f["wall"] for f in fits]
            if compile_s is None:
                compile_s, walls = walls[0], walls[1:]
            rows.append(cell_row(name, sigma, image, depth, lens, fits, walls))
            r = rows[-1]
            print(
                f"{name:7s} sigma={sigma:<6g} ok={r['success']:.2f} rmse(N,d_f,K)={r['rmse']} "
                f"crb={r['crb']} stderr={r['stderr']} steps={r['steps']}",
                flush=True,
            )
    return rows, compile_s


def one_fit(image, depth, clean, sigma, lens, rng) -> dict:
    """One trial: noise on the clean render, a random wrong start, `fit_lens`; the estimates of
    (N, d_f, K), their standard errors, success, steps and wall time."""
    target = clean + sigma * rng.standard_normal(clean.shape)
    init = random_init(rng, lens)
    t = time.perf_counter()
    res = fit_lens(image, depth, target, init, free=FREE, max_radius=WINDOW)
    dt = time.perf_counter() - t
    n, d_f = float(res.lens.f_number), float(res.lens.focus_distance)
    grad_k = np.array([-1 / n, -1 / (d_f - F)])
    k_se = float(np.sqrt(grad_k @ np.asarray(res.covariance) @ grad_k) * blur_scale(n, d_f))
    # The reference: the least-squares solution nearest the truth (one start at the truth, steps
    # to spare). Where the default call's loss is no higher, its answer is the estimator's (the
    # maximum-likelihood one for Gaussian noise), whatever its distance from the truth.
    ref = fit_lens(
        image, depth, target, lens, free=FREE, max_radius=WINDOW, starts=1, max_steps=1000
    )
    n_r, d_r = float(ref.lens.f_number), float(ref.lens.focus_distance)
    return dict(
        est=[n, d_f, blur_scale(n, d_f)],
        est_ref=[n_r, d_r, blur_scale(n_r, d_r)],
        # the default's loss above the reference's (> floor: the search missed a better point)
        loss_gap=float(res.loss - ref.loss),
        loss_floor=float(1e-9 * ref.loss + 1e-12 * 0.5 * np.sum(np.square(target))),
        se=[float(res.stderr["f_number"]), float(res.stderr["focus_distance"]), k_se],
        ok=bool(res.success),
        # the adequacy test fired on a target the model explains: a false alarm
        fired=bool(res.status == jaxdof.RESULTS.inconsistent),
        steps=int(res.num_steps),
        wall=dt,
    )


def cell_row(name, sigma, image, depth, lens, fits, walls) -> dict:
    """One row of section 1 from the trials of one scene and noise level."""
    est, se = np.array([f["est"] for f in fits]), np.array([f["se"] for f in fits])
    truth = np.array([N_TRUE, float(lens.focus_distance), float(lens.blur_scale)])
    if sigma > 0:
        c, ck, _ = crb(image, depth, lens, sigma)
        bound = np.array([c[0], c[1], ck])
    else:
        bound = np.zeros(3)
    ref = np.array([f["est_ref"] for f in fits])
    higher = np.array([f["loss_gap"] > f["loss_floor"] for f in fits])
    # ended elsewhere: more than 3 Cramér-Rao deviations from the reference in N or d_f (or,
    # noise-free, by more than the solver's tolerance); a fit's own standard error can be large
    # exactly where it ended far off (a flatter region), so it is no yardstick here
    far = 3 * bound[:2] + 1e-6 * np.abs(ref[:, :2])
    elsewhere = np.any(np.abs(est - ref)[:, :2] > far, axis=1)
    return dict(
        scene=name,
        sigma=sigma,
        rmse_ref=np.sqrt(np.mean((ref - truth) ** 2, axis=0)),
        # trials that ended away from the reference at a loss no higher (the data's own best
        # lens is there) and at a higher loss (the search missed the better point)
        elsewhere_lower=float(np.mean(elsewhere & ~higher)),
        elsewhere_higher=float(np.mean(elsewhere & higher)),
        success=float(np.mean([f["ok"] for f in fits])),
        fired=float(np.mean([f.get("fired", False) for f in fits])),
        rmse=np.sqrt(np.mean((est - truth) ** 2, axis=0)),
        max_rel=np.max(np.abs(est / truth - 1), axis=0),
        stderr=se.mean(axis=0),
        spread=est.std(axis=0, ddof=1),
        crb=bound,
        steps=float(np.median([f["steps"] for f in fits])),
        wall=float(np.median(walls)) if walls else float("nan"),
    )


def bracket_study(sc, rng, n_bracket) -> np.ndarray:
    """Section 2: `n_bracket` fits of a three-photo focus bracket of `slant`, f and N shared;
    rows `(f, N, stderr f, stderr N, success)`."""
    image, depth = sc["slant"]
    focus = [1.2, 1.8, 2.6]
    cleans = [
        np.asarray(render(image, depth, ThinLens(F, N_TRUE, d, PITCH), max_radius=WINDOW))
        for d in focus
    ]
    bracket = []
    sigma_b = 0.01
    for _ in range(n_bracket):
        targets = [c + sigma_b * rng.standard_normal(c.shape) for c in cleans]
        inits = [
            ThinLens(
                F * rng.uniform(0.8, 1.25),
                N_TRUE * rng.uniform(0.7, 1.4),
                d * rng.uniform(0.9, 1.1),
                PITCH,
            )
            for d in focus
        ]
        res = fit_lens(
            image,
            depth,
            targets,
            inits,
            free=("focal_length", "f_number", "focus_distance"),
            shared=("focal_length", "f_number"),
            max_radius=10.0,
            # The targets are the model's own renders, with no light from outside the frame, so
            # every pixel is kept: the default band (the 10 px window's reach) would leave 4 x 4
            # of the 24 x 24 pixels per photo, and f and N undetermined (measured: 8 of 10
            # bracket fits failed, with standard errors of ~0.5 m on f).
            border=0,
        )
        bracket.append(
            (
                float(res.lens.focal_length),
                float(res.lens.f_number),
                float(res.stderr["focal_length"][0]),
                float(res.stderr["f_number"][0]),
                bool(res.success),
            )
        )
    bracket = np.array(bracket)
    print("bracket", bracket, flush=True)
    return bracket


def report(raw, quick, tag=""):
    # Runs before 2026-12-03 have no reference fits: their columns read nan.
    missing = dict(rmse_ref=[np.nan] * 3, elsewhere_lower=np.nan, elsewhere_higher=np.nan)
    rows = [
        {k: (np.array(v) if isinstance(v, list) else v) for k, v in {**missing, **r}.items()}
        for r in raw["rows"]
    ]
    write(
        rows,
        np.array(raw["bracket"]),
        raw["cost"],
        raw["compile_s"],
        raw["trials"],
        raw["total"],
        quick,
        tag,
    )


def fmt(x, digits=3):
    return f"{x:.{digits}g}"


def _cells(timing, sizes):
    """`(size, scene, m)` per row of a cost table, `m(key)` the median of `key` over its trials."""
    for size in sizes:
        for name in dict.fromkeys(t["scene"] for t in timing if t["size"] == size):
            ts = [t for t in timing if t["scene"] == name and t["size"] == size]
            yield size, name, (lambda k, ts=ts: float(np.median([t[k] for t in ts])))


def write(rows, bracket, cost, compile_s, trials, total, quick, tag=""):
    """The report (sections 1-3 and the conclusions, which assert the study's claims) and plot."""
    md = conditions_lines(cost, compile_s, trials, total, quick)
    md += recovery_lines(rows)
    ratios, srat = efficiency(rows)
    md.append("")
    md.append(
        f"Over the {len(ratios)} noisy cells: RMSE/CRB from {ratios.min():.2f} to {ratios.max():.2f} (median {np.median(ratios):.2f}); "
        f"reported stderr / observed spread from {srat.min():.2f} to {srat.max():.2f}. Noise-free: largest relative error "
        f"{max(r['max_rel'].max() for r in rows if r['sigma'] == 0):.2g}; success rate over all fits "
        f"{np.mean([r['success'] for r in rows]):.3f}; the adequacy test fired (status "
        f"`inconsistent`, a false alarm: the model is right) on "
        f"{np.mean([r.get('fired', np.nan) for r in rows if r['sigma'] > 0]):.1%} of the noisy "
        f"fits and {np.mean([r.get('fired', np.nan) for r in rows if r['sigma'] == 0]):.1%} of "
        "the noise-free ones (goal: at most 5 %).\n"
    )
    md += bracket_lines(bracket)
    timing = cost["timing"]
    sizes = list(dict.fromkeys(t["size"] for t in timing))
    md += cost_intro_lines(cost, sizes)
    md += unit_cost_lines(cost["unit"])
    lines, speeds = one_start_lines(timing, sizes)
    md += lines
    md += default_call_lines(timing, sizes, speeds)
    md += outside_lines(timing, cost)
    md.append(WHY_NOT_10X)
    md.append("## Conclusions\n")
    claims = conclusions(rows, bracket, timing, ratios, srat, speeds)
    md += [f"- {c}" for c in claims]
    path = write_markdown(result_path("recover", quick=quick, tag=tag), md)
    plot(rows, result_path("recover", ".png", quick=quick, tag=tag))
    print(f"wrote {path}")


def efficiency(rows):
    """RMSE / CRB (N, d_f, K) and reported stderr / observed spread (N, d_f) of the noisy cells."""
    noisy = [r for r in rows if r["sigma"] > 0]
    ratios = np.array([r["rmse"] / r["crb"] for r in noisy])
    srat = np.array([r["stderr"][:2] / r["spread"][:2] for r in noisy])
    return ratios, srat


def conditions_lines(cost, compile_s, trials, total, quick) -> list[str]:
    md = []
    md.append("# Lens recovery: accuracy against the Cramér-Rao bound, and cost against scipy\n")
    md.append(
        "Produced by `python fits/recover.py"
        + (" --quick" if quick else "")
        + "`. "
        + __doc__.split("Method.")[1].split('"""')[0].strip().replace("\n", " ")
        + "\n"
    )
    md.append("## Conditions\n")
    md.append(
        f"- jaxdof {jaxdof.__version__}, jax {jax.__version__}, equinox {eqx.__version__}, "
        f"optimistix {optx.__version__ if hasattr(optx, '__version__') else '?'}, numpy {np.__version__}, scipy {scipy.__version__}, Python {sys.version.split()[0]}"
    )
    md.append(
        f"- {platform.platform()}, {platform.processor() or platform.machine()}, {os.cpu_count()} CPU cores "
        f"(shared with other jobs: load average {cost['load']:.1f} at the end of the cost study, so timings are noisy; the ratios are measured in one run, interleaved)"
    )
    md.append(
        f"- {trials} trials per scene and noise level; total run time {total / 60:.1f} min; first fit (compilation) {compile_s:.1f} s\n"
    )
    return md


def recovery_lines(rows) -> list[str]:
    md = ["## 1. One photo: `f_number` and `focus_distance` from wrong starts\n"]
    md.append(
        "RMSE over the trials about the truth; `CRB` the Cramér-Rao standard deviation at the truth; `stderr` the mean reported standard error; `spread` the sample standard deviation of the estimates. K in pixels, d_f in metres. `reference`: the same photos fitted from the truth itself (one start, up to 1000 steps), the least-squares solution nearest the truth; `elsewhere`: the share of trials where the default call ended more than 3 CRB (in N or d_f) from that reference, at a loss no higher than the reference's (the photo's own best fit is there: the estimator's error) or higher (the search missed the better point).\n"
    )
    md.append(
        "| scene | sigma | success | adequacy fired | max rel err N / d_f / K | RMSE N | CRB N | stderr N | RMSE d_f | CRB d_f | stderr d_f | RMSE K | CRB K | RMSE/CRB (N, d_f, K) | reference RMSE/CRB (N, d_f, K) | elsewhere, lower / higher loss | stderr/spread (N, d_f) | median steps | median wall (s) |"
    )
    md.append("|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|")
    for r in rows:
        ratio = r["rmse"] / np.where(r["crb"] > 0, r["crb"], np.nan)
        sr = r["stderr"][:2] / np.where(r["spread"][:2] > 0, r["spread"][:2], np.nan)
        md.append(
            f"| {r['scene']} | {r['sigma']:g} | {r['success']:.2f} | {r.get('fired', np.nan):.2f} | "
            + " / ".join(fmt(x, 2) for x in r["max_rel"])
            + f" | {fmt(r['rmse'][0])} | {fmt(r['crb'][0])} | {fmt(r['stderr'][0])} | {fmt(r['rmse'][1])} | {fmt(r['crb'][1])} | {fmt(r['stderr'][1])} | {fmt(r['rmse'][2])} | {fmt(r['crb'][2])} | "
            + ", ".join(fmt(x, 3) for x in ratio)
            + " | "
            + ", ".join(fmt(x, 3) for x in r["rmse_ref"] / np.where(r["crb"] > 0, r["crb"], np.nan))
            + f" | {r['elsewhere_lower']:.2f} / {r['elsewhere_higher']:.2f} | "
            + ", ".join(fmt(x, 3) for x in sr)
            + f" | {r['steps']:g} | {fmt(r['wall'], 2)} |"
        )
    return md


def bracket_lines(bracket) -> list[str]:
    md = ["## 2. Focus bracket: `f` and `N` apart\n"]
    md.append(
        f"`slant` scene, three photos focused at 1.2, 1.8, 2.6 m, sigma = 0.01, {len(bracket)} trials from starts off by up to 25 % in f, 40 % in N, 10 % in d_f; "
        "`free=(focal_length, f_number, focus_distance)`, `shared=(focal_length, f_number)`.\n"
    )
    md.append("| | truth | mean | RMSE | mean reported stderr | spread |")
    md.append("|---|---|---|---|---|---|")
    for i, (label, truth) in enumerate((("focal length (m)", F), ("f-number", N_TRUE))):
        col = bracket[:, i]
        md.append(
            f"| {label} | {truth:g} | {col.mean():.5g} | {np.sqrt(np.mean((col - truth) ** 2)):.3g} | {bracket[:, 2 + i].mean():.3g} | {col.std(ddof=1) if len(col) > 1 else float('nan'):.3g} |"
        )
    md.append(
        f"\nSuccess in {int(bracket[:, 4].sum())} of {len(bracket)} bracket fits. From one photo the same pair is refused as degenerate.\n"
    )
    return md


def cost_intro_lines(cost, sizes) -> list[str]:
    size_txt = ", ".join(f"{z} x {z}" for z in sizes)
    return [
        "## 3. Cost against scipy with finite differences\n",
        f"Measured {cost['date']} "
        + (
            f"on {cost['machine']}, its own machine (sections 1 and 2 above are the CPU run's, copied). "
            if "machine" in cost
            else f"(load average {cost['load']:.1f} on the 2 shared cores at the end of this section). "
        )
        + f"float64, sigma = 0.01, `max_radius=6`; the four scenes at {size_txt} (the texture grain and the lens stay "
        "the same, so the circles stay at up to ~3.6 px: a bigger image is a wider field of view, not a finer one). "
        "Both solvers start from the same wrong lens, fit the same target in the same log coordinates, float64, on the "
        "same jitted `jaxdof.render`. `fit_lens` from one start (`starts=1`; default LM, `rtol=atol=1e-8`), at full "
        "resolution only (`pyramid=1`) and coarse-to-fine (the levels that `pyramid=None` chooses for several starts, from the image "
        "size and the start's largest circle), and with its default 4 starts: wall time of the whole call (input checks, "
        "pyramid, solves, statistics, message), after a warm-up call, so compilation is excluded. "
        "scipy: `least_squares(method='trf', jac='2-point', xtol=ftol=gtol=1e-8)`, numpy in and out, its renders counted. "
        f"Each number is the median of {cost['reps']} interleaved calls per trial, then the median over the trials; "
        "CPU is process CPU time (all threads). One LM step of `fit_lens` evaluates one render and its Jacobian with respect "
        "to the two free parameters by forward mode (the two tangents as one vmapped JVP sharing the render), built once per "
        "point; the first table gives the cost of each piece in isolation: the render, one JVP (render and one tangent), "
        "the Jacobian as `fit_lens`'s JVP rule builds it (`jax.jacfwd`: both tangents in one vmapped pass; the primal is "
        "unused there and XLA drops it, so this is the tangent pass alone), and the same Jacobian from two separate JVPs "
        "(each with its own weight evaluation).\n",
    ]


def unit_cost_lines(unit) -> list[str]:
    md = [
        "| size | render wall (ms) | CPU (ms) | 1 JVP (render + 1 tangent) wall (ms) | CPU (ms) | 2 tangents vmapped (`jacfwd`, primal dropped) wall (ms) | CPU (ms) | 2 separate JVPs wall (ms) | CPU (ms) | vmapped pair / render (CPU) |",
        "|---|---|---|---|---|---|---|---|---|---|",
    ]
    for size, u in unit.items():
        (rw, rc), (jw, jc) = u["render"], u["jacobian"]
        vw, vc = u.get("jvp1", (float("nan"),) * 2)
        sw, sc2 = u.get("serial", (float("nan"),) * 2)
        md.append(
            f"| {size} x {size} | {rw * 1e3:.2f} | {rc * 1e3:.2f} | {vw * 1e3:.2f} | {vc * 1e3:.2f} | {jw * 1e3:.2f} | {jc * 1e3:.2f} | {sw * 1e3:.2f} | {sc2 * 1e3:.2f} | {jc / rc:.1f} |"
        )
    md.append("")
    return md


def one_start_lines(timing, sizes):
    """The one-start table and bullets; `(lines, speeds)`, `speeds[size]` the medians of ratios."""
    md = [
        "| size | scene | fit_lens 1 start, full res (s) | CPU (s) | LM steps | pyramid 1 start (s) | CPU (s) | levels | full-res LM steps | scipy (s) | scipy CPU (s) | scipy renders | scipy / full res wall | scipy / pyramid wall | CPU | |pyramid - full res| / stderr (N, d_f) | |scipy - full res| / stderr (N, d_f) |",
        "|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    speeds = {}
    for size, name, m in _cells(timing, sizes):
        md.append(
            f"| {size} | {name} | {m('ours1'):.4f} | {m('cpu1'):.4f} | {m('steps'):g} | {m('pyr1'):.4f} | {m('pyr_cpu1'):.4f} | {m('levels'):g} | {m('pyr_steps'):g} | {m('scipy'):.4f} | {m('scipy_cpu'):.4f} | {m('evals'):g} | {m('scipy') / m('ours1'):.2f} | {m('scipy') / m('pyr1'):.2f} | {m('scipy_cpu') / m('pyr_cpu1'):.2f} | {m('pN'):.2g}, {m('pD'):.2g} | {m('dN'):.2g}, {m('dD'):.2g} |"
        )
    for size in sizes:
        sel = [t for t in timing if t["size"] == size]
        speeds[size] = dict(
            flat=float(np.median([t["scipy"] / t["ours1"] for t in sel])),
            flat_cpu=float(np.median([t["scipy_cpu"] / t["cpu1"] for t in sel])),
            pyr=float(np.median([t["scipy"] / t["pyr1"] for t in sel])),
            pyr_cpu=float(np.median([t["scipy_cpu"] / t["pyr_cpu1"] for t in sel])),
            gain=float(np.median([t["ours1"] / t["pyr1"] for t in sel])),
            levels=sorted({int(t["levels"]) for t in sel}),
            n=len(sel),
        )
    md.append("")
    for size, v in speeds.items():
        md.append(
            f"- {size} x {size}: median speed ratio scipy / fit_lens (one start) {v['flat']:.2f}x wall, {v['flat_cpu']:.2f}x CPU "
            f"at full resolution only; {v['pyr']:.2f}x wall, {v['pyr_cpu']:.2f}x CPU coarse-to-fine (levels used: "
            f"{', '.join(map(str, v['levels']))}; pyramid / full resolution wall-time gain {v['gain']:.2f}x"
            + (", timing noise: the pyramid is off here" if v["levels"] == [1] else "")
            + f"), over {v['n']} fits."
        )
    for size in speeds:
        sel = [t for t in timing if t["size"] == size]
        step = float(np.median([t["ours1"] / t["steps"] for t in sel]))
        per_render = float(np.median([t["scipy"] / t["evals"] for t in sel]))
        ratio = float(np.median([3 * t["steps"] / t["evals"] for t in sel]))
        md.append(
            f"- {size} x {size}: fit_lens {step * 1e3:.2f} ms per LM step (a render and its Jacobian), scipy "
            f"{per_render * 1e3:.2f} ms per render (its own Python and numpy included); LM steps per scipy "
            f"Jacobian (renders / 3) median {ratio:.2f}."
        )
    md.append("")
    return md, speeds


def default_call_lines(timing, sizes, speeds) -> list[str]:
    """The default 4-start call against scipy from the same starts (adds `multi*` to `speeds`)."""
    md = [
        "The default call: `fit_lens` with its 4 starts (the init, then focus distances spread in diopters), at full "
        "resolution only and coarse-to-fine, against scipy run from the same 4 starts one after the other, keeping the "
        "lowest cost (its wall and CPU times summed).",
        "",
        "| size | scene | fit_lens 4 starts, full res (s) | pyramid 4 starts (s) | CPU (s) | scipy 4 starts (s) | CPU (s) | scipy renders | scipy / pyramid wall | CPU | full res / pyramid wall | |scipy - ours| / stderr (N, d_f) |",
        "|---|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    for size, name, m in _cells(timing, sizes):
        md.append(
            f"| {size} | {name} | {m('ours4'):.4f} | {m('pyr4'):.4f} | {m('pyr_cpu4'):.4f} | {m('scipy4'):.4f} | {m('scipy_cpu4'):.4f} | {m('evals4'):g} | {m('scipy4') / m('pyr4'):.2f} | {m('scipy_cpu4') / m('pyr_cpu4'):.2f} | {m('ours4') / m('pyr4'):.2f} | {m('d4N'):.2g}, {m('d4D'):.2g} |"
        )
    for size in sizes:
        sel = [t for t in timing if t["size"] == size]
        speeds[size].update(
            multi=float(np.median([t["scipy4"] / t["pyr4"] for t in sel])),
            multi_cpu=float(np.median([t["scipy_cpu4"] / t["pyr_cpu4"] for t in sel])),
            multi_gain=float(np.median([t["ours4"] / t["pyr4"] for t in sel])),
        )
    md.append("")
    for size, v in speeds.items():
        md.append(
            f"- {size} x {size}, default 4 starts: median scipy (same 4 starts) / fit_lens {v['multi']:.2f}x wall, "
            f"{v['multi_cpu']:.2f}x CPU; the pyramid makes the 4-start call {v['multi_gain']:.2f}x faster than at full resolution only"
            + (
                " (timing noise: at this size the pyramid is off, one level)."
                if v["levels"] == [1]
                else "."
            )
        )
    return md


def outside_lines(timing, cost) -> list[str]:
    worst_p = max(max(t["pN"], t["pD"]) for t in timing)
    md = [
        f"- Coarse-to-fine lands on the full-resolution fit: at most {worst_p:.2g} standard errors apart over all fits "
        "(both stop at the solver tolerance, 1e-8 in the log coordinates)."
    ]
    if "outside" in cost:
        o = cost["outside"]
        md.append(
            f"- Outside its two compiled calls (input checks in numpy, set-up, the message), a warm 24 x 24 call "
            f"spends {o['outside'] * 1e3:.1f} ms of {o['total'] * 1e3:.1f} ms (median of 15)."
        )
    md.append("")
    return md


def conclusions(rows, bracket, timing, ratios, srat, speeds):
    claims = []
    noise_free = [r for r in rows if r["sigma"] == 0]
    worst = max(r["max_rel"].max() for r in noise_free)
    assert all(r["success"] == 1.0 for r in noise_free), "a noise-free fit failed"
    assert worst < 1e-4, worst
    claims.append(
        f"Noise-free, every fit from the wrong starts succeeded and recovered N, d_f and K to {worst:.1g} relative or better (float64)."
    )
    low = np.array([r["rmse"] / r["crb"] for r in rows if 0 < r["sigma"] <= 0.01])
    high = np.array([r["rmse"] / r["crb"] for r in rows if r["sigma"] == 0.03])
    claims.append(
        f"RMSE / CRB for sigma <= 0.01: median {np.median(low):.2f}, range {low.min():.2f}-{low.max():.2f} "
        f"(issue goal: within 1.3x); at sigma = 0.03: median {np.median(high):.2f}, up to {high.max():.2f}. "
        "With 30 trials an RMSE is itself uncertain by about +-13 % (1 sigma), so single cells scatter "
        "around 1 by that much; the median is the estimate of efficiency."
    )
    worst_cell = max((r for r in rows if r["sigma"] == 0.03), key=lambda r: r["max_rel"].max())
    noisy = [r for r in rows if r["sigma"] > 0]
    missed = max(r["elsewhere_higher"] for r in noisy)
    ref_ratio = np.array([r["rmse_ref"] / r["crb"] for r in noisy])
    claims.append(
        f"The worst cell at sigma = 0.03 ({worst_cell['scene']}, largest relative error "
        f"{worst_cell['max_rel'].max():.0%}, RMSE/CRB "
        + ", ".join(f"{x:.2f}" for x in worst_cell["rmse"] / worst_cell["crb"])
        + f"): {worst_cell['elsewhere_lower']:.0%} of its trials ended far from the fit started "
        "at the truth at a loss no higher than that fit's (a lens far off explains that noisy "
        "photo at least as well: the 12 x 12 pixels inside the 6 px border band of a 24 x 24 "
        "frame, with circles of 0-2 px, do not tell the two apart), and "
        f"{worst_cell['elsewhere_higher']:.0%} at a higher loss (the search's miss). The fits "
        "from the truth have RMSE/CRB "
        + ", ".join(f"{x:.2f}" for x in worst_cell["rmse_ref"] / worst_cell["crb"])
        + f" there, and {ref_ratio.min():.2f}-{ref_ratio.max():.2f} over every noisy cell. "
        + (
            "The excess in that cell is the global least-squares estimate's own, which a better "
            "search would not remove."
            if worst_cell["elsewhere_higher"] == 0
            else "Part of the excess in that cell is the search's."
        )
        + " Over every noisy cell the default call's search missed a better point far off in at "
        f"most {missed:.0%} of the trials."
    )
    # The estimator is efficient where the noise is small: the median ratio is 1 within the
    # sampling error of a median over the cells, and no cell is off by more than ~3 sampling sigmas.
    assert 0.8 < np.median(low) < 1.2 and low.max() < 1.5, low
    claims.append(
        f"Reported standard error / observed spread: median {np.median(srat):.2f}, range "
        f"{srat.min():.2f}-{srat.max():.2f} (the same +-13 % sampling error per cell)."
    )
    # Where the noise is small (every fit in the right basin) the errors are honest; at sigma =
    # 0.03 on 144 fitted pixels a start can settle in another basin (see the table's max rel err),
    # which no Gauss-Newton error describes: those cells are reported, not asserted.
    small = np.array(
        [s for s, r in zip(srat, [r for r in rows if r["sigma"] > 0]) if r["sigma"] <= 0.01]
    )
    assert 0.85 < np.median(small) < 1.15 and small.max() < 1.6 and small.min() > 1 / 1.6, small
    f_mean, f_se = bracket[:, 0].mean(), bracket[:, 2].mean()
    n_mean, n_se = bracket[:, 1].mean(), bracket[:, 3].mean()
    k = len(bracket)
    claims.append(
        f"A focus bracket (1.2 / 1.8 / 2.6 m) determines f and N apart, but weakly: at sigma = 0.01 the "
        f"reported standard errors are {f_se * 1e3:.2g} mm on f = 50 mm ({f_se / F:.0%}) and {n_se:.2g} on N = 2 "
        f"({n_se / N_TRUE:.0%}); the mean over {k} trials is f = {f_mean * 1e3:.1f} mm, N = {n_mean:.2f}. Only "
        "the change of K across the bracket, K_t ~ 1/(d_f,t - f), carries f, and it is of order "
        "f / d_f (a few %); a bracket focused closer (d_f of a few f) or EXIF for one field does far better."
    )
    # Unbiased within the sampling error of the mean of k trials.
    assert abs(f_mean - F) < 3 * f_se / np.sqrt(k) + 1e-9 and abs(
        n_mean - N_TRUE
    ) < 3 * n_se / np.sqrt(k), (f_mean, n_mean)
    assert bracket[:, 4].all(), "a bracket fit failed"
    best = max(max(v["flat"], v["pyr"]) for v in speeds.values())
    per_size = "; ".join(
        f"{z} x {z}: {v['flat']:.2f} full resolution, {v['pyr']:.2f} coarse-to-fine"
        for z, v in speeds.items()
    )
    claims.append(
        f"Against scipy's finite-difference least squares on the same jitted render, the wall-time ratio scipy / fit_lens "
        f"(one start; medians; above 1 means fit_lens is faster) is {per_size} "
        f"({'meets' if best >= 10 else 'does not meet'} the issue's 10x goal on this machine), and fit_lens lands within "
        f"{max(max(t['dN'], t['dD']) for t in timing):.2g} standard errors of scipy's answer."
    )
    multi = "; ".join(
        f"{z} x {z}: {v['multi']:.2f}x wall, {v['multi_cpu']:.2f}x CPU" for z, v in speeds.items()
    )
    claims.append(
        f"The default call (4 starts, coarse-to-fine) against scipy from the same 4 starts: {multi} (medians). "
        "The pyramid's gain is in the multi-start search, which it runs on the coarsest level: "
        + "; ".join(f"{z} x {z}: {v['multi_gain']:.2f}x" for z, v in speeds.items())
        + " faster than the same 4-start call at full resolution only."
    )
    return claims


def plot(rows, path):
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, 3, figsize=(13, 4))
    labels = ("N", "d_f (m)", "K (px)")
    for j, ax in enumerate(axes):
        for name in dict.fromkeys(r["scene"] for r in rows):
            rs = [r for r in rows if r["scene"] == name and r["sigma"] > 0]
            s = [r["sigma"] for r in rs]
            (line,) = ax.loglog(s, [r["rmse"][j] for r in rs], "o-", label=f"{name} RMSE")
            ax.loglog(
                s, [r["crb"][j] for r in rs], "--", color=line.get_color(), label=f"{name} CRB"
            )
            if j < 2:
                ax.loglog(s, [r["stderr"][j] for r in rs], "x", color=line.get_color())
        ax.set_xlabel("noise sigma")
        ax.set_title(f"{labels[j]}: RMSE (o), CRB (--), stderr (x)")
    axes[0].legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(path, dpi=110)


if __name__ == "__main__":
    main()
