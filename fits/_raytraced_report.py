"""The measured sections of `raytraced.md`: each function computes one section from the cached
renders and fits and returns its lines (and what later sections need); `figure` draws the PNG.

The summary at the top of the report, written from these results, is in `_raytraced_summary.py`.
"""

from __future__ import annotations

import dataclasses
import importlib.metadata
import os
import platform
import time

import jax


jax.config.update("jax_enable_x64", True)

import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402
from _common import RESULTS, machine_info  # noqa: E402

# The study-only candidate of the pixel-footprint correction (semi-internal).
from _footprint_candidates import footprint_radius  # noqa: E402
from _raytraced_fits import (  # noqa: E402
    FOCUS_TOL,
    K_TOL,
    SIGMAS,
    TREATMENTS,
    fit_cached,
    fit_weight,
    interior,
)
from _raytraced_scenes import (  # noqa: E402
    APERTURE_VIEWS,
    APERTURES,
    CONFIGS,
    DEFAULT_SCENES,
    F_PX,
    FOCUS,
    FOV_X,
    HELD_OUT,
    NEAR_CLIP,
    SCENES,
    SPP_EMITTERS,
    SPP_PINHOLE,
    SPP_THIN,
    SUM_CHECK,
    TUNING,
    H,
    W,
    default_inputs,
    default_lenses,
    emitter_table,
    floor_lens,
    load_scene,
    load_scene_fine,
    noise_pair,
    photo,
    plane_geometry,
    sum_check_renders,
    true_lens,
    z_depth,
)
from scipy.ndimage import distance_transform_edt  # noqa: E402

import jaxdof  # noqa: E402
from jaxdof import footprint_prefilter  # noqa: E402


EDGE_JUMP = 0.03  # relative z jump between 4-neighbours that marks a depth edge (slant: < 1%)
EDGE_BINS = (0, 1, 2, 4, 8, 16, np.inf)  # distance to the nearest depth edge (px)


def edge_distance(z):
    """Euclidean distance (px) from every pixel to the nearest `jaxdof.depth_edges` pixel; inf
    everywhere when there is no depth edge.

    Not the library's `jaxdof.internal.edge_distance`: that one is capped at `limit` (64 px by default;
    equal to this below the cap on random maps and on the CI crops) and returns `limit`, not inf,
    when the scene has no edge, which would put every pixel of slant into the last distance bin
    (the report leaves that bin empty there). It is also brute force, O(edge pixels x limit^2).
    """
    e = jaxdof.depth_edges(z, jump=EDGE_JUMP)
    if not e.any():
        return np.full(z.shape, np.inf)
    return distance_transform_edt(~e)


def psnr(a, b, mask=None):
    err = (np.asarray(a, np.float64) - np.asarray(b, np.float64)) ** 2
    if mask is not None:
        err = err[mask]
    return 10 * np.log10(1.0 / np.mean(err))  # radiance peak is 1 by construction


# ----------------------------------------------------------------------------- head, depth, emitters


def intro_lines(mi) -> list[str]:
    """Title, conditions and the scenes; `mi` the Mitsuba module (its version and variant)."""
    return [
        f"# Ray-traced validation against Mitsuba {mi.__version__} (`{mi.variant()}`)",
        "",
        "Produced by `python fits/raytraced.py` (renders cached in `fits/.cache/raytraced/`). "
        f"Film {W}x{H} px, fov_x {FOV_X}° (f_px = {F_PX:.2f}), box pixel filter, self-emitting "
        f"textured scenes (`path`, `max_depth=1`); pinhole {SPP_PINHOLE} spp, thin lens {SPP_THIN} spp "
        f"(emitters {SPP_EMITTERS}); apertures A = {APERTURES} m, focus distances d_f = {FOCUS} m, so "
        f"K = A f_px / d_f from {min(a * F_PX / d for a, d in CONFIGS):.2f} to "
        f"{max(a * F_PX / d for a, d in CONFIGS):.2f} px. Python {platform.python_version()}, "
        f"jax {jax.__version__}, {platform.machine()} CPU with {os.cpu_count()} cores shared with "
        "other jobs (wall times are indicative only).",
        "",
        "Scenes: **planes** (three fronto-parallel textured planes at 1.5, 2.5, 4 m as vertical "
        "strips, each farther plane continuing behind its neighbour: two occlusion edges), "
        "**slant** (one textured plane, z 1.3-6 m, no depth edge), **occluders** (textured wall at "
        "4.5 m, a card at 2.6 m, a ball at 1.75 m, a pole at 2 m: many occlusion edges), "
        "**emitters** (16 emissive disks of 1 px radius at 1-40 m on black).",
        "",
        f"Held-out split (issues 20, 21): {', '.join(s for s in SCENES if s in TUNING)} are in the "
        "tuning half (`TUNING` in `_raytraced_scenes.py`), so every fit here is on tuning "
        f"scenes; the held-out half ({', '.join(HELD_OUT)}) is reported apart in "
        "[raytraced_default.md](raytraced_default.md).",
        "",
    ]


def depth_lines() -> list[str]:
    """The depth conversion checked on the slanted plane's analytic z (asserted)."""
    _, dist, _, _ = load_scene("slant")
    z = z_depth(dist)
    p0, n = plane_geometry()
    fp = F_PX
    xs = -(np.arange(W) + 0.5 - W / 2) / fp
    ys = -(np.arange(H) + 0.5 - H / 2) / fp
    v = np.stack(np.broadcast_arrays(xs[None, :], ys[:, None], np.ones((H, 1))), -1)
    z_plane = (n @ p0) / (v @ n)
    # The study's claim (asserted, so a re-run that breaks it fails loudly).
    assert np.max(np.abs(z / z_plane - 1)) < 1e-5, "depth conversion"
    return [
        "## Depth",
        "",
        "Mitsuba's `depth` AOV is the distance from the ray origin, and its perspective camera "
        "starts rays on the near plane, so `z = t cos(theta) + near_clip` "
        "(`jaxdof.ray_distance_to_z`). On the slanted plane, rendered with one "
        "unjittered sample per pixel, the converted depth matches the plane's analytic z to "
        f"{np.max(np.abs(z / z_plane - 1)):.1e} (max relative error; float32). Dropping the "
        f"near-clip term would leave {np.max(np.abs((z - NEAR_CLIP) / z_plane - 1)):.1e}.",
        "",
    ]


def emitter_lines() -> list[str]:
    """The lens mapping checked on the blur discs of the small emitters (asserted)."""
    t = emitter_table()
    ratio = t[:, 4] / t[:, 3]
    big, mid = t[:, 3] >= 2.5, (t[:, 3] >= 1) & (t[:, 3] < 2.5)
    assert np.max(np.abs(ratio[big] - 1)) < 0.03, "lens mapping vs blur discs"
    return [
        "## Lens mapping checked on blur discs",
        "",
        "`jaxdof.lens_from_raytracer(A, d_f, fov_x_deg, image_width, focal_length=f)` "
        "returns `ThinLens(f, N = f/(2A), d_f, p = s/f_px)` with `s = f d_f/(d_f - f)`; its "
        "`blur_scale` is exactly `A f_px / d_f` for any `f` (derivation in the docstring). The "
        "disc radius of each emitter is measured as `sqrt(2 (M2_thin - M2_pinhole))` (second "
        "moments about the centroid: the disk's own size and the pixel box cancel).",
        "",
        "| predicted radius | emitters | median measured/predicted | worst |",
        "|---|---|---|---|",
        f"| >= 2.5 px | {big.sum()} | {np.median(ratio[big]):.4f} | {ratio[big][np.argmax(np.abs(ratio[big] - 1))]:.4f} |",
        f"| 1 - 2.5 px | {mid.sum()} | {np.median(ratio[mid]):.4f} | {ratio[mid][np.argmax(np.abs(ratio[mid] - 1))]:.4f} |",
        "",
        "Seed-to-seed scatter of the measured radius is <= 1.7% (two renders of two lenses). "
        "Some emitters show a seed-independent error of up to ~0.3 px² in r² (3% at r = 2 px), of "
        "either sign and similar for every lens: likely the pixel-sampled second moment of the "
        "1 px disk's pinhole image, which depends on its sub-pixel position (aliasing). It "
        "matters only for discs under ~2.5 px.",
        "",
    ]


# ----------------------------------------------------------------------------- PSNR


@dataclasses.dataclass
class Psnr:
    """The PSNR section's results, per scene (lists over the lenses) or per (scene, A, d_f)."""

    overall: dict = dataclasses.field(default_factory=dict)  # soft
    overall_fp: dict = dataclasses.field(default_factory=dict)  # footprint radius
    overall_fpre: dict = dataclasses.field(default_factory=dict)  # footprint prefilter
    overall_occ: dict = dataclasses.field(default_factory=dict)  # occlusion
    overall_bare: dict = dataclasses.field(default_factory=dict)  # occlusion, no fill
    curves: dict = dataclasses.field(default_factory=dict)  # soft PSNR per edge-distance bin
    occ_curves: dict = dataclasses.field(default_factory=dict)  # the same, occlusion
    noises: dict = dataclasses.field(default_factory=dict)  # Monte Carlo floor (dB) per scene
    # (scene, A, d_f, where, MSE soft, MSE occlusion, MSE floor)
    gap_rows: list = dataclasses.field(default_factory=list)
    # (occlusion wall s, occlusion CPU s, soft wall s) per lens
    occ_secs: list = dataclasses.field(default_factory=list)


def psnr_section() -> tuple[list[str], Psnr]:
    """PSNR of every forward model against Mitsuba, overall and by distance to a depth edge."""
    lines = [
        "## Post-process model vs ray tracing (PSNR)",
        "",
        "`render(pinhole, z, lens_from_raytracer(A, d_f))` against the thin-lens render, over "
        "the interior (a border of the largest circle + 2 px is left out: the post-process "
        "cannot see outside the frame). PSNR in dB, peak 1. `noise` is the Monte Carlo floor "
        "of one thin-lens render (two seeds, A = 0.06, d_f = 1.8). `footprint` uses "
        "`coc_filter(image, footprint_radius(coc_radius(z, lens)))`; `fp prefilter` uses "
        "`coc_filter(footprint_prefilter(image, r), r)` with `r = coc_radius(z, lens)`; "
        "`occlusion` is "
        "`render(..., method=jaxdof.Occlusion())` (depth-ordered layers, hidden background "
        "filled, composited with `over`; `jaxdof/_filters/occlusion.py`); `no fill` the same with "
        "`jaxdof.Occlusion(fill=False)` (each layer only its visible pixels). Columns by distance "
        "(px) to the nearest depth edge (a >3% z jump between neighbours), each `soft / "
        "occlusion`.",
        "",
    ]
    hdr = (
        "| scene | A | d_f | K px | all | footprint | fp prefilter | occlusion | no fill | "
        + " | ".join(f"[{EDGE_BINS[k]},{EDGE_BINS[k + 1]})" for k in range(len(EDGE_BINS) - 1))
        + " | render s |"
    )
    lines += [hdr, "|" + "---|" * (hdr.count("|") - 1)]
    res = Psnr()
    for name in SCENES:
        pin, dist, thin, _ = load_scene(name)
        z = z_depth(dist)
        ed = edge_distance(z)
        b = noise_pair(name, 0.06, 1.8)
        noise = psnr(thin[(0.06, 1.8)], b) + 10 * np.log10(2)
        for (a, d), tgt in thin.items():
            lines.append(psnr_row(res, name, pin, z, ed, a, d, tgt))
        res.noises[name] = noise
        res.gap_rows = [
            (*g, 10 ** (-noise / 10)) if g[0] == name and len(g) == 6 else g for g in res.gap_rows
        ]
    lines += [
        "",
        "Monte Carlo noise floor of one thin-lens render (PSNR of its noise alone): "
        + ", ".join(f"{k} {v:.1f} dB" for k, v in res.noises.items())
        + ".",
        "",
    ]
    return lines, res


def models(pin, z, lens, r, mr):
    """The forward models of the PSNR table on one lens: `({name: image}, soft render seconds,
    (occlusion wall s, occlusion CPU s, soft wall s))`; soft and occlusion compiled, then timed."""
    jaxdof.render(pin, z, lens, max_radius=mr).block_until_ready()  # compile
    t0 = time.perf_counter()
    model = np.asarray(jaxdof.render(pin, z, lens, max_radius=mr).block_until_ready())
    secs = time.perf_counter() - t0
    out = dict(soft=model)
    out["fp"] = np.asarray(jaxdof.coc_filter(pin, footprint_radius(r), max_radius=mr))
    out["fpre"] = np.asarray(jaxdof.coc_filter(footprint_prefilter(pin, r), r, max_radius=mr))

    def occ():
        return jaxdof.render(pin, z, lens, max_radius=mr, method=jaxdof.Occlusion())

    occ().block_until_ready()  # compile
    t0, c0 = time.perf_counter(), time.process_time()
    out["occ"] = np.asarray(occ().block_until_ready())
    occ_time = (time.perf_counter() - t0, time.process_time() - c0, secs)
    out["bare"] = np.asarray(
        jaxdof.render(pin, z, lens, max_radius=mr, method=jaxdof.Occlusion(fill=False))
    )
    return out, secs, occ_time


def psnr_row(res: Psnr, name, pin, z, ed, a, d, tgt) -> str:
    """One lens's row of the PSNR table; its numbers are added to `res`."""
    lens = true_lens(a, d)
    r = np.asarray(jaxdof.coc_radius(z, lens))
    m = interior(z.shape, int(np.ceil(r.max())) + 2)
    mr = float(np.ceil(r.max()) + 1)
    out, secs, occ_time = models(pin, z, lens, r, mr)
    res.occ_secs.append(occ_time)
    model, model_occ = out["soft"], out["occ"]
    m3 = m[..., None].repeat(3, -1)
    res.overall.setdefault(name, []).append(psnr(model, tgt, m3))
    res.overall_fp.setdefault(name, []).append(psnr(out["fp"], tgt, m3))
    res.overall_fpre.setdefault(name, []).append(psnr(out["fpre"], tgt, m3))
    res.overall_occ.setdefault(name, []).append(psnr(model_occ, tgt, m3))
    row = [f"{psnr(out[k], tgt, m3):.2f}" for k in ("soft", "fp", "fpre", "occ", "bare")]
    res.overall_bare.setdefault(name, []).append(psnr(out["bare"], tgt, m3))
    curve, curve_occ = [], []
    for k in range(len(EDGE_BINS) - 1):
        mm = m & (ed >= EDGE_BINS[k]) & (ed < EDGE_BINS[k + 1])
        ok = mm.sum() >= 20
        val = psnr(model, tgt, mm[..., None].repeat(3, -1)) if ok else np.nan
        val_occ = psnr(model_occ, tgt, mm[..., None].repeat(3, -1)) if ok else np.nan
        curve.append(val)
        curve_occ.append(val_occ)
        row.append("" if np.isnan(val) else f"{val:.1f} / {val_occ:.1f}")
    res.curves[(name, a, d)] = curve
    res.occ_curves[(name, a, d)] = curve_occ
    if name == "slant":  # no depth gap: one layer, i.e. exactly the soft render
        assert np.array_equal(model_occ, model), "occlusion must equal soft on slant"
    # the share of the model's excess error (over the Monte Carlo floor) that the
    # occlusion treatment removes, over the interior and within 2 px of a depth edge
    near = m & (ed < 2)
    for where, mk in (("all", m), ("edge", near)):
        if mk.sum() < 20:
            continue
        mk3 = mk[..., None].repeat(3, -1)
        ref = tgt[mk3].astype(np.float64)
        mse = lambda x, mk3=mk3, ref=ref: float(np.mean((x[mk3] - ref) ** 2))
        res.gap_rows.append((name, a, d, where, mse(model), mse(model_occ)))
    return f"| {name} | {a} | {d} | {a * F_PX / d:.2f} | " + " | ".join(row) + f" | {secs:.3f} |"


def gap_section(res: Psnr) -> tuple[list[str], dict]:
    """How far each model is above the Monte Carlo floor, and how much of that excess the
    occlusion treatment removes; `(lines, {(scene, where): (soft dB, occlusion dB, closed)})`."""
    db = lambda mse: 10 * np.log10(1 / mse)
    lines = [
        "### The gap to ray tracing and what the occlusion treatment closes",
        "",
        "Per lens: MSE of the model against the Mitsuba render, minus the Monte Carlo floor "
        "(the target's own noise, which no model can remove) = the model's excess error; "
        "**closed** = 1 - excess(occlusion) / excess(soft). Medians over the 6 lenses of each "
        "scene; `edge` = pixels within 2 px of a depth edge.",
        "",
        "| scene | where | soft dB | occlusion dB | floor dB | gap soft dB | gap occlusion dB | "
        "closed (median) | closed (range) |",
        "|---|---|---|---|---|---|---|---|---|",
    ]
    closed_all = {}
    for name in SCENES:
        for where in ("all", "edge"):
            rows = [g for g in res.gap_rows if g[0] == name and g[3] == where]
            if not rows:
                continue
            soft_db = [db(g[4]) for g in rows]
            occ_db = [db(g[5]) for g in rows]
            floor = rows[0][6]
            closed = [1 - max(g[5] - floor, 0) / (g[4] - floor) for g in rows]
            closed_all[(name, where)] = (np.median(soft_db), np.median(occ_db), np.median(closed))
            lines.append(
                f"| {name} | {where} | {np.median(soft_db):.1f} | {np.median(occ_db):.1f} | "
                f"{db(floor):.1f} | {db(floor) - np.median(soft_db):.1f} | "
                f"{db(floor) - np.median(occ_db):.1f} | {np.median(closed):.0%} | "
                f"{min(closed):.0%} - {max(closed):.0%} |"
            )
    occ_secs = np.array(res.occ_secs)
    lines += [
        "",
        f"Time of one occlusion render (128x128x3, float64, compiled): median "
        f"{np.median(occ_secs[:, 0]):.2f} s wall, {np.median(occ_secs[:, 1]):.2f} s process CPU; "
        f"median {np.median(occ_secs[:, 0] / occ_secs[:, 2]):.1f}x the soft render's wall time "
        "measured in the same loop (`fill=True`: one soft scatter per layer, 4 layers).",
        "",
    ]
    for name in ("planes", "occluders"):
        assert all(o >= s_ for s_, o in zip(res.overall[name], res.overall_occ[name])), (
            f"occlusion must not lose PSNR on {name}"
        )
    return lines, closed_all


def fine_input_section():
    """PSNR against Mitsuba with the all-in-focus input at 1x, 2x and 4x the photo's resolution
    (`render(..., downsample=s)`), with and without the footprint prefilter; `(lines, medians)`."""
    out = [
        "### The all-in-focus input at a finer resolution",
        "",
        "A pixel of the pinhole image is an average over its square; a thin lens with circles of "
        "a pixel or two mixes the detail *inside* that square, which no filter of the averages "
        "can know. `render(image, depth, lens, downsample=s)` takes the all-in-focus image and "
        "depth at `s` times the photo's resolution (rendered here by Mitsuba at 256 and 512 px "
        "with the same samples per photo pixel; in practice a pixel-shift capture), scatters "
        "there and averages `s x s` blocks. PSNR (dB) over the interior as above; `+ fp` with "
        "`footprint=True`; occlusion columns `method=jaxdof.Occlusion()`.",
        "",
        "| scene | A | d_f | K px | 1x | 1x + fp | 2x | 2x + fp | 4x | 4x + fp | occlusion 1x + fp "
        "| occlusion 2x + fp |",
        "|---|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    med = {}
    for name in SCENES:
        pin, dist, thin, _ = load_scene(name)
        z = z_depth(dist)
        inputs = {1: (pin, z), **{s: load_scene_fine(name, s) for s in (2, 4)}}
        for (a, d), tgt in thin.items():
            row = fine_input_row(name, inputs, z, a, d, tgt)
            for k, v in row.items():
                med.setdefault((name, k), []).append(v)
            cols = [(1, False), (1, True), (2, False), (2, True), (4, False), (4, True)]
            out.append(
                f"| {name} | {a} | {d} | {a * F_PX / d:.2f} | "
                + " | ".join(f"{row[c]:.2f}" for c in cols)
                + f" | {row[('occ', 1)]:.2f} | {row[('occ', 2)]:.2f} |"
            )
    med = {k: float(np.median(v)) for k, v in med.items()}
    out += [
        "",
        "Medians over the 6 lenses: "
        + "; ".join(
            f"{name} 1x {med[(name, (1, False))]:.1f}, 1x + fp {med[(name, (1, True))]:.1f}, "
            f"2x + fp {med[(name, (2, True))]:.1f}, 4x + fp {med[(name, (4, True))]:.1f} dB"
            + ("" if name == "slant" else f", occlusion 2x + fp {med[(name, ('occ', 2))]:.1f} dB")
            for name in SCENES
        )
        + ". The pinhole renders at 2x and 4x carry their own Monte Carlo noise (the same "
        "samples per photo pixel as the 1x one).",
        "",
    ]
    return out, med


def fine_input_row(name, inputs, z, a, d, tgt) -> dict:
    """PSNR of one lens for every input scale `s` and footprint setting (`(s, fp)`), and of the
    occlusion render with the footprint prefilter at 1x and 2x (`("occ", s)`)."""
    lens = true_lens(a, d)
    r = np.asarray(jaxdof.coc_radius(z, lens))
    m = interior(z.shape, int(np.ceil(r.max())) + 2)[..., None].repeat(3, -1)
    mr = float(np.ceil(r.max()) + 1)
    row = {}
    for s, (im, zz) in inputs.items():
        for fp in (False, True):
            out_s = jaxdof.render(im, zz, lens, max_radius=mr, downsample=s, footprint=fp)
            row[(s, fp)] = psnr(np.asarray(out_s), tgt, m)
    for s in (1, 2):
        if name == "slant":  # one layer: the soft render
            row[("occ", s)] = row[(s, True)]
            continue
        im, zz = inputs[s]
        out_s = jaxdof.render(
            im, zz, lens, max_radius=mr, downsample=s, footprint=True, method=jaxdof.Occlusion()
        )
        row[("occ", s)] = psnr(np.asarray(out_s), tgt, m)
    return row


# ----------------------------------------------------------------------------- fits


def fit_ok(f) -> bool:
    """The study's goal: focus distance within 2 %, blur scale K within 5 %."""
    return abs(f["d_f_err"]) < 0.02 and abs(f["K_err"]) < 0.05


def fit_cell(f, d) -> str:
    """A fit table's cell: `d_f` and `K` errors with their standard errors, and the verdict."""
    f_len = 0.05  # lens_from_raytracer's default focal length
    # se(K)/K <= se(N)/N + se(d_f)/(d_f - f): an upper bound (the N-d_f correlation is not kept)
    se_k = f["K_se"] / f["K"] + f["d_f_se"] / (f["d_f"] - f_len)
    return (
        f"{f['d_f_err']:+.1%}±{f['d_f_se'] / d:.1%}, {f['K_err']:+.1%}±{se_k:.1%}"
        + (" ✓" if fit_ok(f) else " ✗")
        + ("" if f["success"] else " (not converged)")
    )


FIT_INTRO = (
    "Free: focus distance and f-number (focal length 50 mm and pixel pitch fixed at the "
    "mapping's values, so the fit recovers `d_f` and the blur scale `K`); start 15% far in "
    "`d_f` and 30% off in `N`; one start (`starts=1`); float64; weight = interior mask (1.6x "
    "the start's largest circle + 2 px, the frame's border sees content the pinhole image "
    "lacks) times the treatment's weight. Each cell: `d_f` error ± its standard error, `K` "
    "error ± an upper bound of its standard error (fitted/true - 1; the standard errors are "
    "`fit_lens`'s Gauss-Newton errors for white noise, far below the systematic errors); ✓ "
    "when `d_f` is within 2% and `K` within 5%. Treatments: **edge weight** "
    "`edge_weight(z, width=r0 + 1)` with `r0` the start's largest circle; **footprint** the "
    "forward model `coc_filter(image, footprint_radius(coc_radius(z, lens)))` (a forward model "
    "of this study's own, `fit_lens(..., model=...)`); **prefilter** `pixel_prefilter(image)` "
    "before the fit (`jaxdof.internal`, study only); "
    "**occlusion** `fit_lens(..., method=jaxdof.Occlusion())` (the occlusion-aware render as "
    "the forward model, no edge weight); **occlusion + footprint** the same with the "
    "footprint radius; **occlusion + edge + footprint** all three; **fp prefilter** the "
    "forward model `coc_filter(footprint_prefilter(image, r), r)` with `r = coc_radius(z, "
    "lens)` (the image corrected per pixel for its own circle: `fit_lens(..., footprint=True)`), "
    "alone and with the other treatments; **2x** the all-in-focus input (pinhole "
    "image and depth, rendered at 256 x 256) at twice the photo's resolution, "
    "`fit_lens(..., downsample=2)`, with the same photo-pixel weights. (Occlusion fits are "
    "not run on slant: there it is the soft render.) Every fit is at full resolution "
    "(`pyramid=1`)."
)


def fit_section(fits: dict) -> tuple[list[str], dict]:
    """The fit tables (soft and occlusion-aware forward models) and the per-treatment summary;
    `(lines, {(treatment, scene): [(within goal, |d_f error|, |K error|), ...]})`."""
    lines = ["## Lens recovered by `fit_lens` from the ray-traced targets", "", FIT_INTRO, ""]
    summary, times = {}, []
    treatments = list(TREATMENTS)
    groups = (
        ("Soft forward model:", [t for t in treatments if TREATMENTS[t][3] == "soft"]),
        (
            "Occlusion-aware forward model (`method=jaxdof.Occlusion()`):",
            [t for t in treatments if TREATMENTS[t][3] == "occlusion"],
        ),
    )
    for title, group in groups:
        lines += [
            title,
            "",
            "| scene | A m | d_f m | K px | " + " | ".join(group) + " |",
            "|---|---|---|---|" + "---|" * len(group),
        ]
        for name in SCENES:
            for a, d in CONFIGS:
                row = []
                for tr in group:
                    f = fits.get((name, a, d, tr))
                    if f is None:
                        row.append("")
                        continue
                    row.append(fit_cell(f, d))
                    times.append(f["seconds"])
                    summary.setdefault((tr, name), []).append(
                        (fit_ok(f), abs(f["d_f_err"]), abs(f["K_err"]))
                    )
                if any(row):
                    lines.append(
                        f"| {name} | {a} | {d} | {a * F_PX / d:.2f} | " + " | ".join(row) + " |"
                    )
        lines.append("")
    lines += [
        "",
        f"Fit wall time: median {np.median(times):.0f} s, range {min(times):.0f}-{max(times):.0f} s "
        "(128x128x3 float64; the long ones include compiling for a new window size).",
        "",
        "| treatment | scene | fits within goal | median abs d_f error | median abs K error |",
        "|---|---|---|---|---|",
    ]
    for (tr, name), rows in summary.items():
        lines.append(
            f"| {tr} | {name} | {sum(r[0] for r in rows)}/{len(rows)} | "
            f"{np.median([r[1] for r in rows]):.2%} | {np.median([r[2] for r in rows]):.2%} |"
        )
    lines.append("")
    return lines, summary


def smallest_k_section(a=0.03, d=3.0):
    """Loss landscape around the truth at K = 1.76 px, soft model and footprint prefilter, and
    multi-start fits; `(lines, {scene: [loss at the truth, plain and footprint prefilter]})`."""
    lens = true_lens(a, d)
    out = [
        f"## Why the smallest blur scale (K = {a * F_PX / d:.2f} px) is hard to recover",
        "",
        "The loss (the fit's weighted sum of squares, no edge weight) on a grid of focus "
        "distance and blur scale around the truth (fitted/true; f-number chosen to give each "
        "K at each d_f), for the plain soft model and for the footprint prefilter "
        "(`coc_filter(footprint_prefilter(image, r), r)`), and fits from the same start with "
        "`starts=4` (the default of `fit_lens`: extra starts spread in diopters) instead of one.",
        "",
    ]
    at_truth = {}  # scene: [loss at the truth, plain and footprint prefilter]
    for name in ("planes", "slant"):
        pin, dist, thin, _ = load_scene(name)
        z = z_depth(dist).astype(np.float64)
        tgt = thin[(a, d)].astype(np.float64)
        w = fit_weight(z, a, d, False)
        r_true = np.asarray(jaxdof.coc_radius(z, lens))
        dead = float(np.mean(r_true[w > 0] <= 0.5))
        out += [
            f"**{name}**: {dead:.0%} of the fitted pixels have a true circle of at most half a "
            "pixel (where the soft model is the identity).",
            "",
        ]
        for label, model, fp in (
            ("plain", _plain_model, False),
            ("fp prefilter", _prefilter_model, "prefilter"),
        ):
            grid = loss_grid(lens, a, d, pin, z, tgt, w, model)
            i, j = np.unravel_index(np.argmin(grid), grid.shape)
            at_truth.setdefault(name, []).append(float(grid[3, 3]))
            f1 = fit_cached(name, a, d, starts=1, footprint=fp)
            f4 = fit_cached(name, a, d, starts=4, footprint=fp)
            out += [
                f"*{label}*: grid minimum at d_f x{LOSS_DFS[i]}, K x{LOSS_KS[j]} (loss {grid[i, j]:.2f}; at "
                f"the truth {grid[3, 3]:.2f}). Fit, one start: d_f {f1['d_f_err']:+.1%}, K "
                f"{f1['K_err']:+.1%}; four starts: d_f {f4['d_f_err']:+.1%}, K {f4['K_err']:+.1%}.",
                "",
                "| d_f/true (rows), K/true (columns) | "
                + " | ".join(f"{k}" for k in LOSS_KS)
                + " |",
                "|---|" + "---|" * len(LOSS_KS),
            ]
            out += [
                f"| {dd} | " + " | ".join(f"{v:.2f}" for v in row) + " |"
                for dd, row in zip(LOSS_DFS, grid)
            ]
            out.append("")
    return out, at_truth


LOSS_DFS = np.array([0.8, 0.9, 0.95, 1.0, 1.05, 1.1, 1.2, 1.3])  # focus distance / truth
LOSS_KS = np.array([0.5, 0.7, 0.85, 1.0, 1.15, 1.3])  # blur scale / truth


def _plain_model(pin, z, trial):
    return jaxdof.render(pin, z, trial, max_radius=8.0)


def _prefilter_model(pin, z, trial):
    r = jaxdof.coc_radius(z, trial)
    return jaxdof.coc_filter(footprint_prefilter(pin, r), r, max_radius=8.0)


def loss_grid(lens, a, d, pin, z, tgt, w, model) -> np.ndarray:
    """The weighted loss of `model` on the grid `LOSS_DFS` x `LOSS_KS` (rows d_f, columns K)."""
    f_len = float(lens.focal_length)

    @jax.jit
    def loss(df, n):
        trial = jaxdof.ThinLens(lens.focal_length, n, df, lens.pixel_pitch)
        return jnp.sum(w[..., None] * (model(pin.astype(np.float64), z, trial) - tgt) ** 2)

    return np.array(
        [
            [
                float(loss(dd * d, float(lens.f_number) * (d - f_len) / (dd * d - f_len) / kk))
                for kk in LOSS_KS
            ]
            for dd in LOSS_DFS
        ]
    )


# ----------------------------------------------------------------------------- figure


def figure(res: Psnr):
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axs = plt.subplots(3, 6, figsize=(18, 9.5))
    a, d = 0.1, 1.8
    for k, name in enumerate(SCENES):
        pin, dist, thin, _ = load_scene(name)
        z = z_depth(dist)
        model = np.asarray(jaxdof.render(pin, z, true_lens(a, d)))
        err = np.abs(model - thin[(a, d)]).mean(-1)
        model_occ = np.asarray(jaxdof.render(pin, z, true_lens(a, d), method=jaxdof.Occlusion()))
        err_occ = np.abs(model_occ - thin[(a, d)]).mean(-1)
        for ax, img, title in zip(
            axs[k, :5],
            (np.clip(pin, 0, 1), z, np.clip(thin[(a, d)], 0, 1), err, err_occ),
            (
                "pinhole",
                "z (m)",
                f"Mitsuba thin lens A={a} d_f={d}",
                "|render - Mitsuba|",
                "|occlusion - Mitsuba|",
            ),
        ):
            im = ax.imshow(
                img,
                cmap=None if img.ndim == 3 else ("viridis" if title.startswith("z") else "magma"),
                vmax=0.15 if title.startswith("|") else None,
            )
            ax.set_title(f"{name}: {title}", fontsize=9)
            ax.axis("off")
            if img.ndim == 2:
                plt.colorbar(im, ax=ax, fraction=0.046)
        _figure_psnr_panel(axs[k, 5], name, res)
    fig.tight_layout()
    fig.savefig(RESULTS / "raytraced.png", dpi=80)


def _figure_psnr_panel(ax, name, res: Psnr):
    """PSNR against the distance to a depth edge; on slant (no edge) the footprint corrections."""
    centers = [0.5, 1.5, 3, 6, 12, 24]
    if name == "slant":  # no depth edge: show the footprint correction instead
        x = np.arange(len(CONFIGS))
        ax.bar(x - 0.27, res.overall[name], 0.27, label="render")
        ax.bar(x, res.overall_fp[name], 0.27, label="footprint_radius")
        ax.bar(x + 0.27, res.overall_fpre[name], 0.27, label="footprint_prefilter")
        ax.set_xticks(x, [f"A={aa}\nd_f={dd}" for aa, dd in CONFIGS], fontsize=6)
        ax.set_ylim(30, 45)
        ax.set_ylabel("PSNR (dB)")
        ax.set_title("slant (no depth edge): PSNR", fontsize=9)
        ax.legend(fontsize=6)
        return
    for (n, aa, dd), c in res.curves.items():
        if n == name:
            (line,) = ax.plot(centers, c, "o-", label=f"A={aa} d_f={dd} soft", ms=3)
            ax.plot(centers, res.occ_curves[(n, aa, dd)], "s--", color=line.get_color(), ms=3)
    ax.plot([], [], "k--", label="dashed: occlusion")
    ax.set_xscale("log")
    ax.set_xlabel("distance to depth edge (px)")
    ax.set_ylabel("PSNR (dB)")
    ax.set_title(f"{name}: PSNR vs edge distance", fontsize=9)
    ax.legend(fontsize=6)


# ----------------------------------------------------------------------------- the default call
# The sections of `raytraced_default.md` (`raytraced_default.py`): scenes, the aperture-sum check,
# render PSNR and the fit tables, one per half.

SCENE_TEXT = {
    "planes": "three fronto-parallel planes at 1.5, 2.5, 4 m (two occlusion edges)",
    "slant": "one slanted plane, z 1.3-6 m, no depth edge",
    "occluders": "a wall at 4.5 m, a card, a ball and a pole in front (many occlusion edges)",
    "vignette": "slant's photos times cos^4 of the field angle (0.63 in the corners): a falloff "
    "the model lacks",
    "outside": "a plane turned 50 deg (z 1.7-4.4 m, no depth edge) with bright (radiance up to "
    "4), strongly textured strips just beyond the left and right edges and bright bars at 1 m "
    "just above and below the frame: light in the photo's border that the all-in-focus image "
    "lacks, the bars' from nearer than anything in the frame",
    "landscape": "the camera 1 m above textured ground (2.8 m at the bottom row to 400 m), "
    "hills at 25-90 m and a backdrop at 1 km; three lenses focused exactly at infinity (sum of "
    "parallel pinhole views over the disc), one at 20 m (Mitsuba's thin lens); init focus 20 m "
    "for the lenses at infinity",
    "ground": "curved objects on a floor: two balls and a pole on textured ground (2.2 m at the "
    "bottom row) before a wall at 7 m; the floor connects near and far",
    "pentagon": "a plane of its own (slant2, z 1.6-4.8 m, no depth edge) through a regular "
    "pentagonal aperture of the disc's area (sum of pinhole views): an aperture the model lacks",
    "thin": "thin structures: six poles (1.8-5 px wide) at 1.25-2.5 m and three slanted branches "
    "(1.5-2.3 px) on a floor before a wall at 5 m",
    "fgbg": "a card at 1.8 m over 40 % of the frame (a vertical and a diagonal edge) before a "
    "wall turned 40 deg (z 4.2-10.5 m); two lenses focused on the card (a sharp foreground over a blurred background), "
    "two on the wall (the reverse)",
    "texture": "one plane (z 1.9-3.6 m, no depth edge) with a texture near the sampling limit "
    "(detail of 2-3 px period, 32 % of the power above 0.25 cycles/px)",
    "lightfield": "ground's scene as a refocused light field: shift-and-add of an 11 x 11 grid of "
    "pinhole views inside the disc (97 views, no view interpolation)",
}


def k_label(a, d) -> str:
    """The true blur of a lens: `K` (px), or for a lens at infinity `S = A f_px` (px m)."""
    return f"S={a * F_PX:.1f}" if np.isinf(d) else f"{a * F_PX / d:.2f}"


def df_label(d) -> str:
    return "inf" if np.isinf(d) else f"{d:g}"


def default_conditions(x64: bool, render_secs: dict, fp: str, git: str, note) -> list[str]:
    """The run's conditions as a list: machine, precision, library source, renders."""
    try:
        mitsuba = importlib.metadata.version("mitsuba")
    except importlib.metadata.PackageNotFoundError:
        mitsuba = "not installed (every render cached)"
    info = {
        **machine_info(),
        "precision": "float64 (--x64)" if x64 else "float32 (jax_enable_x64 off)",
        "jaxdof source": git,
        "fit cache fingerprint": fp,
        "mitsuba": mitsuba,
        "render seconds per scene (when made)": ", ".join(
            f"{k} {v:.0f}" for k, v in render_secs.items()
        ),
    }
    return ([f"- note: {note}"] if note else []) + [f"- {k}: {v}" for k, v in info.items()]


def default_method_lines() -> list[str]:
    """What the call is, what `within` means, the verdicts."""
    return [
        "The call: `jaxdof.fit_lens(image, depth, photo, init)`, nothing else, on 128x128 RGB "
        "photos (self-emitting textured scenes, Mitsuba 3); init f-number 1.5x the truth's, "
        "focus 20 % short (20 m for a lens focused at infinity). **within**: focus distance "
        f"within {FOCUS_TOL:.0%} and K within {K_TOL:.0%}; for a lens focused at infinity the "
        f"focus power `u = 1/d_f` within {FOCUS_TOL:.0%} of the scene's nearest power "
        "(`u/u_near`: the share of the largest circle that the focus error moves every circle "
        "by) and, for K (0 at infinity), `S = K d_f`, the circle per diopter (`A f_px`, shown "
        "as `S=` in the K column). `abs err / se`: the actual error over the reported standard "
        "error, for the focus power (`focus_power_stderr`) and for K (or S), the latter from "
        "`stderr['f_number']` and `focus_power_stderr` with their correlation from "
        "`covariance`. Verdicts: ✓ within; ✓ (refused) within but success=False; ✗ flagged "
        "outside with success=False; ✗ covered outside with success=True and both errors "
        f"within {SIGMAS:g} standard errors; ⚠ silent outside with success=True and an error "
        f"beyond {SIGMAS:g} standard errors (a silent miss); ! an exception escaped `fit_lens` "
        "(caught here). Wall time per fit includes compiling.",
        "",
    ]


def default_scene_lines() -> list[str]:
    """The scenes, their half, their lenses and how their photos were made."""
    out = [
        "## Scenes",
        "",
        "| scene | half | lenses (A m, d_f m) | photo | what |",
        "|---|---|---|---|---|",
    ]
    for name, (geometry, kind) in DEFAULT_SCENES.items():
        lenses = ", ".join(f"({a}, {df_label(d)})" for a, d in default_lenses(name))
        half = "held out" if name in HELD_OUT else "tuning"
        out.append(f"| {name} | {half} | {lenses} | {kind} ({geometry}) | {SCENE_TEXT[name]} |")
    return out + [""]


def sum_check_lines() -> list[str]:
    """The aperture-sum renderer against Mitsuba's thin lens (a disc, same scene and lens)."""
    disc_sum, thin, thin1 = sum_check_renders()
    geometry, a, d = SUM_CHECK
    return [
        "## The aperture-sum renderer checked",
        "",
        "The pentagon and the lenses focused at infinity are rendered as the mean of "
        f"{APERTURE_VIEWS} pinhole views (one sample per pixel each), the eye moved to points "
        "spread over the aperture and the principal point offset so that the focus plane stays "
        "put (`_raytraced_scenes.render_aperture_sum`). With a disc aperture on "
        f"{geometry}, A = {a} m, d_f = {d} m, it matches Mitsuba's thin lens to "
        f"{psnr(disc_sum, thin):.1f} dB PSNR (full frame), while two seeds of Mitsuba's thin "
        f"lens differ by {psnr(thin, thin1):.1f} dB: no difference beyond the Monte Carlo noise.",
        "",
    ]


def psnr_default_section(scenes) -> list[str]:
    """PSNR of the default `jaxdof.render(image, depth, true lens)` against each photo."""
    out = [
        "## The default render against the ray-traced photos (PSNR)",
        "",
        "`jaxdof.render(image, depth, true lens)` with every default, against each photo: "
        "`interior` leaves out a border of the largest true circle + 2 px (as in raytraced.md), "
        "`frame` is every pixel (the border band holds light from outside the frame). `floor`: "
        "the Monte Carlo noise of one photo (two seeds of one lens per scene, `+ 3 dB`). dB, "
        "peak 1.",
        "",
        "| scene | A m | d_f m | K px | interior | frame | floor |",
        "|---|---|---|---|---|---|---|",
    ]
    for name in scenes:
        fa, fd = floor_lens(name)
        floor = psnr(photo(name, fa, fd)[0], photo(name, fa, fd, seed=1)[0]) + 10 * np.log10(2)
        for a, d in default_lenses(name):
            pin, z, tgt = default_inputs(name, a, d)
            lens = true_lens(a, d)
            r = np.asarray(jaxdof.coc_radius(z, lens))
            m = interior(z.shape, int(np.ceil(r.max())) + 2)[..., None].repeat(3, -1)
            model = np.asarray(jaxdof.render(pin, z, lens))
            out.append(
                f"| {name} | {a} | {df_label(d)} | {k_label(a, d)} | {psnr(model, tgt, m):.1f} | "
                f"{psnr(model, tgt):.1f} | {floor:.1f} |"
            )
    return out + [""]


def first_clause(message: str) -> str:
    """A message's first clause: up to its first `;` or `:`, at most 70 characters."""
    head = message.split(";")[0].split(":")[0].strip()
    return head if len(head) <= 70 else head[:67] + "..."


def verdict(rec) -> str:
    """✓ within the goal; else ⚠ silent (success, > 3 stderr off), ✗ flagged (success=False) or
    ✗ covered (success, within 3 stderr); ! exception. `(refused)` marks a lens within the goal
    that came back with success=False."""
    if "exception" in rec:
        return "! exception"
    if rec["within"]:
        return "✓" if rec["success"] else "✓ (refused)"
    if rec["silent"]:
        return "⚠ silent"
    return "✗ covered" if rec["success"] else "✗ flagged"


def default_fit_table(records, scenes) -> list[str]:
    """One row per fit of `scenes`."""
    out = [
        "| scene | A m | d_f m | K px | success / status | message | focus err | K err | "
        "abs err / se (focus, K) | pixels used (border) | treatment | s | verdict |",
        "|---|---|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    for rec in records:
        if rec["scene"] not in scenes:
            continue
        a, d = rec["a"], float(rec["d"])
        head = f"| {rec['scene']} | {a} | {df_label(d)} | {k_label(a, d)} |"
        if "exception" in rec:
            out.append(
                head + f" exception | {rec['exception'][:90]} | | | | | | "
                f"{rec['seconds']:.0f} | ! exception |"
            )
            continue
        focus = f"u/u_near {rec['focus_err']:+.2%}" if np.isinf(d) else f"{rec['focus_err']:+.2%}"
        out.append(
            head
            + f" {rec['success']} / {rec['status']} | {first_clause(rec['message'])} | {focus} | "
            f"{rec['k_err']:+.2%} | {rec['focus_z']:.2g}, {rec['k_z']:.2g} | "
            f"{rec['pixels_used']} ({rec['border']}) | {rec.get('treatment', '')} | "
            f"{rec['seconds']:.0f} | {verdict(rec)} |"
        )
    return out + [""]
