"""Does the adequacy check say when the model does not fit? (issue 20, deliverable 5)

Questions:

1. On targets the model explains (the noisy trials of `fits/recover.py`: its four 24 x 24 scenes,
   its lens, starts and noise levels), how often does the between-tile check fire? The goal:
   at most 5 % of the noisy trials, and never on noise-free ones.
2. On targets rendered with a deliberately wrong model and fitted with the default soft model
   (a pentagonal aperture, vignetting, occlusion rendered but not modelled, a border left in),
   does the check fire, and does the uncertainty it reports (the fit's standard errors times the
   check's `inflation`) cover the actual error? A *silent miss* is a fit that reports success,
   passes the check, is outside the tolerance (2 % in N, 5 % in d_f) and more than 3 reported
   standard errors from the truth.

Run:

    python fits/adequacy.py            # 12 trials per cell of section 1, 3 of section 2 (~5 min)
    python fits/adequacy.py --quick    # 6 and 2 (~3 min)
    python fits/adequacy.py --trials 30  # recover.py's 30 trials per cell (~10 min)
    python fits/adequacy.py --report-only

Writes `fits/results/adequacy.md` and `fits/results/adequacy_raw.json` (`--quick` adds `_quick`).

Method. float64, the scenes, lens, starts and noise of `fits/recover.py` (imported from it;
same seed, so the same scenes): grey 24 x 24 textures on four depth maps, f = 50 mm,
N = 2, pitch 80 um, focus 1.6 m (1.8 m for `smooth`), `free=("f_number", "focus_distance")`,
`max_radius=6`, the default starts and border (`border="auto"`: the 6 px band that light from
outside the frame reaches is left out, so 12 x 12 pixels are fitted). Each fit is `fit_lens`,
whose own adequacy test (run in every fit on the residual and Jacobian at the solution; the
statistic and the inflation do not depend on the coordinates) is read from `FitResult.adequacy`:
the fit's border as the mask and band, the default tiles (3 x 3 over the 12 x 12 pixels), each
tile with its own gain and offset, the noise floor at the targets' rounding level, `alpha = 0.01`;
its standard errors are the fit's, inflated where the test fired. Mis-modelled targets, each plus Gaussian noise sigma in {0.001, 0.01}:
`pentagon` (`jaxdof.Soft(blades=5)`, the pentagon inscribed in each circle), `vignette` (the
soft render times `1 - 0.3 rho^2`, rho = 1 in the corners), `occlusion` (`method="occlusion"`),
`border` (the scene drawn at 36 x 36, rendered, and its central 24 x 24 fitted with `border=0`,
so the edge pixels lack the light from outside). The pentagon's area is
`(5/2) sin(72 deg) / pi = 0.757` of its circle's, so to first order it blurs like the disc of
`sqrt(0.757) = 0.870` times the radius, i.e. of `N / 0.870`: the table also gives the error
against that equal-area lens, which is what a photo can determine.
"""

from __future__ import annotations

import argparse
import functools
import time

import jax


jax.config.update("jax_enable_x64", True)

import numpy as np  # noqa: E402
from _common import (  # noqa: E402
    command,
    load_json,
    machine_info,
    result_path,
    save_json,
    write_markdown,
)

import jaxdof  # noqa: E402
from jaxdof import render  # noqa: E402


# isort: split
# recover.py's scenes, lens and starts: the false-alarm trials are that study's trials.
from recover import (  # noqa: E402
    FREE,
    N_TRUE,
    SIGMAS,
    WINDOW,
    F,
    H,
    W,
    blur_scale,
    crb,
    random_init,
    scenes,
    true_lens,
)


# isort: split
from jaxdof.internal import ADEQUACY_ALPHA as ALPHA  # noqa: E402


# The targets here are `render`'s default model (plus noise): the study fits exactly that model
# (`fit_lens` would otherwise choose its treatment of a real photo, `jaxdof/_scene.py`).
fit_lens = functools.partial(jaxdof.fit_lens, method="soft", footprint=False, edge_weight=False)


KINDS = ("pentagon", "vignette", "occlusion", "border")
MIS_SIGMAS = (0.001, 0.01)
TOL = (0.02, 0.05)  # relative errors in N and d_f that count as recovered
BIG = 36  # the larger frame of `border`
WINDOW_BAND = int(np.ceil(WINDOW))  # the default border band of a fit with max_radius = 6
PENTAGON_AREA = 2.5 * np.sin(np.deg2rad(72.0)) / np.pi


# --------------------------------------------------------------- the check on a fit


def one(image, depth, target, lens, rng, *, truth_n=N_TRUE, **kw) -> dict:
    """Fit from a random start, run the check, and compare with the truth (N, d_f, K)."""
    init = random_init(rng, lens)
    try:
        res = fit_lens(image, depth, target, init, free=FREE, max_radius=WINDOW, **kw)
    except ValueError as err:  # refused: the data do not determine the lens at the solution
        nan = [float("nan")] * 3
        return dict(
            est=nan,
            se=nan,
            rel=nan,
            z=np.inf,
            z_inflated=np.inf,
            ok=False,
            raised=str(err).split(":")[0],
            adequate=True,
            p_value=1.0,
            inflation=1.0,
            chi2=0.0,
            dof=0.0,
            tiles=0.0,
            spread=1.0,
        )
    # The fit's own adequacy test; its standard errors are already inflated where it fired.
    a = {k: float(v) for k, v in res.adequacy.items()}
    n, d_f = float(res.lens.f_number), float(res.lens.focus_distance)
    grad_k = np.array([-1 / n, -1 / (d_f - F)])
    k_se = float(np.sqrt(grad_k @ np.asarray(res.covariance) @ grad_k) * blur_scale(n, d_f))
    d_true = float(lens.focus_distance)
    est = np.array([n, d_f, blur_scale(n, d_f)])
    truth = np.array([truth_n, d_true, blur_scale(truth_n, d_true)])
    se = np.array([float(res.stderr["f_number"]), float(res.stderr["focus_distance"]), k_se])
    z_inflated = float(np.max(np.abs(est - truth) / se))
    return dict(
        est=est.tolist(),
        se=se.tolist(),
        rel=(est / truth - 1).tolist(),
        z=z_inflated * a["inflation"],  # against the noise-only standard errors
        z_inflated=z_inflated,
        # the fit itself fine, whatever the adequacy test said (its own verdict: `adequate`)
        ok=bool(res.success) or bool(res.status == jaxdof.RESULTS.inconsistent),
        status=jaxdof.RESULTS[res.status].split(":")[0][:40],
        **a,
    )


# --------------------------------------------------------------- the two sections


def false_alarms(trials, border) -> list[dict]:
    """Section 1: correct-model trials of recover.py's scenes and noise levels."""
    rng = np.random.default_rng(20261122)  # recover.py's seed: the same scenes
    rows = []
    for name, (image, depth) in scenes(rng).items():
        lens = true_lens(name)
        clean = np.asarray(render(image, depth, lens, max_radius=WINDOW))
        for sigma in SIGMAS:
            fits = [
                one(
                    image,
                    depth,
                    clean + sigma * rng.standard_normal(clean.shape),
                    lens,
                    rng,
                    border=border,
                )
                for _ in range(trials)
            ]
            est = np.array([f["est"][:2] for f in fits])
            truth = np.array([N_TRUE, float(lens.focus_distance)])
            band = WINDOW_BAND if border == "auto" else border
            bound = crb(image, depth, lens, sigma, band)[0] if sigma > 0 else np.zeros(2)
            rmse = np.sqrt(np.mean((est - truth) ** 2, axis=0))
            rows.append(
                dict(
                    scene=name,
                    sigma=sigma,
                    trials=trials,
                    fired=[not f["adequate"] for f in fits],
                    ok=[f["ok"] for f in fits],
                    z=[f["z"] for f in fits],
                    rel=[f["rel"] for f in fits],
                    p=[f["p_value"] for f in fits],
                    dof=fits[0]["dof"],
                    tiles=fits[0]["tiles"],
                    rmse_over_crb=(rmse / bound).tolist() if sigma > 0 else None,
                )
            )
            r = rows[-1]
            print(
                f"{name:7s} sigma={sigma:<6g} fired {sum(r['fired'])}/{trials} "
                f"ok {sum(r['ok'])}/{trials} dof {r['dof']:.0f} rmse/crb {r['rmse_over_crb']}",
                flush=True,
            )
    return rows


def vignette():
    yy, xx = np.mgrid[0:H, 0:W]
    rho2 = ((yy - (H - 1) / 2) ** 2 + (xx - (W - 1) / 2) ** 2) / (((H - 1) / 2) ** 2 * 2)
    return 1 - 0.3 * rho2


def mismodelled(trials) -> list[dict]:
    """Section 2: targets from a wrong model, fitted with the default soft model."""
    rng = np.random.default_rng(20261207)
    small = scenes(rng)
    big = scenes(rng, BIG)
    m = (BIG - H) // 2
    rows = []
    for kind in KINDS:
        for name in small:
            lens = true_lens(name)
            image, depth = small[name]
            kw = {}
            if kind == "pentagon":
                method = jaxdof.Soft(blades=5)
                clean = render(image, depth, lens, method=method, max_radius=WINDOW)
            elif kind == "vignette":
                clean = render(image, depth, lens, max_radius=WINDOW) * vignette()
            elif kind == "occlusion":
                clean = render(image, depth, lens, method="occlusion", max_radius=WINDOW)
            else:  # border: the centre of a larger frame, fitted with every pixel
                big_image, big_depth = big[name]
                clean = render(big_image, big_depth, lens, max_radius=WINDOW)[m : m + H, m : m + W]
                image, depth = big_image[m : m + H, m : m + W], big_depth[m : m + H, m : m + W]
                kw = dict(border=0)
            clean = np.asarray(clean)
            for sigma in MIS_SIGMAS:
                for _ in range(trials):
                    target = clean + sigma * rng.standard_normal(clean.shape)
                    f = one(image, depth, target, lens, rng, **kw)
                    row = dict(kind=kind, scene=name, sigma=sigma, **f)
                    if kind == "pentagon":  # against the equal-area disc's f-number
                        eq = N_TRUE / np.sqrt(PENTAGON_AREA)
                        g = one_against(f, eq, float(lens.focus_distance))
                        row.update(
                            rel_eq=g["rel"], z_eq=g["z"] * f["inflation"], z_eq_inflated=g["z"]
                        )
                    rows.append(row)
                    print(
                        f"{kind:9s} {name:7s} sigma={sigma:<6g} ok={int(f['ok'])} "
                        f"fired={int(not f['adequate'])} p={f['p_value']:.2g} "
                        f"rel(N,d_f)=({f['rel'][0]:+.1%},{f['rel'][1]:+.1%}) z={f['z']:.1f} "
                        f"inflation={f['inflation']:.2f} z/inflation={f['z_inflated']:.1f}",
                        flush=True,
                    )
    return rows


def one_against(f, truth_n, d_true) -> dict:
    """A trial's relative errors and largest |error| / stderr against another truth."""
    est, se = np.array(f["est"]), np.array(f["se"])
    truth = np.array([truth_n, d_true, blur_scale(truth_n, d_true)])
    return dict(rel=(est / truth - 1).tolist(), z=float(np.max(np.abs(est - truth) / se)))


# --------------------------------------------------------------- report


def outside_tolerance(rel) -> bool:
    return abs(rel[0]) > TOL[0] or abs(rel[1]) > TOL[1]


def verdict(row, rel_key="rel", z_key="z_inflated") -> str:
    """`refused` (the fit's own success=False), `fired`, `recovered` (within the tolerance),
    `covered` (outside it, within 3 reported standard errors) or `silent miss`."""
    if not row["ok"]:
        return "refused"
    if not row["adequate"]:
        return "fired"
    if not outside_tolerance(row[rel_key]):
        return "recovered"
    return "covered" if row[z_key] <= 3 else "silent miss"


def report(raw, quick, tag=""):
    lines = [
        "# Model adequacy: the between-tile check (issue 20, deliverable 5)",
        "",
        f"Command: `{raw['command']}`, {raw['total']:.0f} s. Date: {raw['date']}.",
        "",
        "Machine: " + "; ".join(f"{k}: {v}" for k, v in raw["machine"].items()),
        "",
        "Method: see the docstring of `fits/adequacy.py`; the check is "
        "`jaxdof.internal.adequacy` (Chow's test in score form over a 3 x 3 grid of tiles "
        "of the fitted pixels, each tile with its own lens, gain and offset; F test, "
        f"alpha = {raw['alpha']}). Section 2 fits with the default border (`border=0` for "
        "`border`).",
        "",
        "## 1. False alarms on targets the model explains",
        "",
        f"Fits with `border={raw.get('border', 'auto')!r}`"
        + (
            " (the 6 px band left out: 12 x 12 pixels fitted, 3 x 3 tiles of 4 px)."
            if raw.get("border", "auto") == "auto"
            else " (24 x 24 pixels fitted, 3 x 3 tiles of 8 px)."
        ),
        "",
        "Fired: trials where the check fired. Among converged: of the trials whose fit reports "
        "success and lies within 5 reported standard errors of the truth, or within 1e-6 "
        "relative when noise-free (a fit in another "
        "basin is rightly flagged, and is not a false alarm). RMSE / CRB of (N, d_f) over all "
        "trials (the check does not change the estimates).",
        "",
        "| scene | sigma | trials | fired | fired among converged | success | dof | RMSE/CRB N | RMSE/CRB d_f |",
        "|---|---|---|---|---|---|---|---|---|",
    ]
    tot = dict(noisy=0, fired=0, conv=0, conv_fired=0, clean=0, clean_fired=0)
    for r in raw["false_alarms"]:
        fired, ok, z = np.array(r["fired"]), np.array(r["ok"]), np.array(r["z"])
        rel = np.array([np.max(np.abs(x[:2])) for x in r["rel"]])
        conv = ok & ((z <= 5) | (rel < 1e-6))  # noise-free: standard errors are ~0
        rc = r["rmse_over_crb"]
        rc = ("-", "-") if rc is None else tuple(f"{x:.2f}" for x in rc)
        lines.append(
            f"| {r['scene']} | {r['sigma']:g} | {r['trials']} | {fired.sum()} | "
            f"{(fired & conv).sum()}/{conv.sum()} | {ok.sum()} | {r['dof']:.0f} | {rc[0]} | {rc[1]} |"
        )
        if r["sigma"] > 0:
            tot["noisy"] += len(fired)
            tot["fired"] += int(fired.sum())
            tot["conv"] += int(conv.sum())
            tot["conv_fired"] += int((fired & conv).sum())
        else:
            tot["clean"] += len(fired)
            tot["clean_fired"] += int(fired.sum())
    lines += [
        "",
        f"Noisy trials: fired {tot['fired']}/{tot['noisy']} "
        f"({tot['fired'] / max(tot['noisy'], 1):.1%}); among converged fits "
        f"{tot['conv_fired']}/{tot['conv']} ({tot['conv_fired'] / max(tot['conv'], 1):.1%}); "
        f"goal <= 5 %. Noise-free trials: fired {tot['clean_fired']}/{tot['clean']}.",
        "",
        "## 2. Mis-modelled targets",
        "",
        "Verdicts: `refused` (the fit itself returned success=False), `fired` (the check fired: "
        "a distinct status with the inflated standard errors), `recovered` (passed, within "
        f"{TOL[0]:.0%} in N and {TOL[1]:.0%} in d_f), `covered` (passed, outside that, within 3 "
        "reported standard errors), `silent miss` (passed, outside both). z: the largest "
        "|error| / standard error over N, d_f and K; z/infl: the same with the check's inflated "
        "standard errors (equal to z where it did not fire).",
        "",
        "| model | scene | sigma | fired | median rel. error N | median z | median z/infl | covered when fired (z/infl <= 3) | verdicts |",
        "|---|---|---|---|---|---|---|---|---|",
    ]
    rows = raw["mismodelled"]
    summary = {}
    for kind in KINDS:
        for name in ("planes", "slant", "steps", "smooth"):
            for sigma in MIS_SIGMAS:
                cell = [
                    r
                    for r in rows
                    if r["kind"] == kind and r["scene"] == name and r["sigma"] == sigma
                ]
                if not cell:
                    continue
                fired = [not r["adequate"] for r in cell]
                cov = [r["z_inflated"] <= 3 for r, f in zip(cell, fired) if f]
                verdicts = [verdict(r) for r in cell]
                for v in verdicts:
                    summary.setdefault(kind, {}).setdefault(v, 0)
                    summary[kind][v] += 1
                counts = ", ".join(f"{v} {verdicts.count(v)}" for v in sorted(set(verdicts)))
                lines.append(
                    f"| {kind} | {name} | {sigma:g} | {sum(fired)}/{len(cell)} | "
                    f"{np.median([r['rel'][0] for r in cell]):+.1%} | "
                    f"{np.median([r['z'] for r in cell]):.1f} | "
                    f"{np.median([r['z_inflated'] for r in cell]):.1f} | "
                    f"{sum(cov)}/{len(cov)} | {counts} |"
                )
    lines += ["", "Totals per model:", ""]
    for kind, counts in summary.items():
        lines.append(f"- {kind}: " + ", ".join(f"{v} {c}" for v, c in sorted(counts.items())))
    pent = [r for r in rows if r["kind"] == "pentagon"]
    if pent:
        eq = [verdict(r, "rel_eq", "z_eq_inflated") for r in pent]
        lines += [
            "",
            "Pentagon against the equal-area disc's f-number (N / 0.870): median relative error "
            f"{np.median([r['rel_eq'][0] for r in pent]):+.1%}, verdicts "
            + ", ".join(f"{v} {eq.count(v)}" for v in sorted(set(eq)))
            + ".",
        ]
    write_markdown(result_path("adequacy", quick=quick, tag=tag), lines)


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--quick", action="store_true", help="6 and 2 trials per cell")
    ap.add_argument("--report-only", action="store_true", help="rewrite the report from raw")
    ap.add_argument("--trials", type=int, default=None, help="section 1 trials per cell")
    ap.add_argument(
        "--border",
        default="auto",
        help="section 1 fits' border (fit_lens's; an int, or auto), e.g. 0 for every pixel; "
        "the outputs get the suffix _border<N>",
    )
    args = ap.parse_args(argv)
    tag = "" if args.border == "auto" else f"_border{args.border}"
    raw_path = result_path("adequacy", "_raw.json", quick=args.quick, tag=tag)
    if args.report_only:
        return report(load_json(raw_path), args.quick, tag)
    t = time.perf_counter()
    raw = dict(
        command=command("adequacy.py", argv),
        machine=machine_info(),
        date=time.strftime("%Y-%m-%d %H:%M UTC", time.gmtime()),
        alpha=ALPHA,
        false_alarms=false_alarms(
            args.trials or (6 if args.quick else 12),
            args.border if args.border == "auto" else int(args.border),
        ),
        border=args.border,
        mismodelled=mismodelled(2 if args.quick else 3),
    )
    raw["total"] = time.perf_counter() - t
    save_json(raw_path, raw)
    report(raw, args.quick, tag)


if __name__ == "__main__":
    main()
