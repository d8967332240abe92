"""A photo made by jaxdof's own forward models comes back as its lens with the default `fit_lens`
call (`jaxdof/_fit/select.py`: the photo has a say in the scene's treatment), and the README's
quick example does what it says.

The property tests draw the lens (f-number, focus distance, which fixes the circles) and the
scene (a ramp, or a step between two slanted planes) for each forward model `render` offers; shapes are
fixed so that the examples share compiled programs. The default run covers circles of 0.3 to
about 5 px in float32 and float64; the slow run adds circles up to 30 px, focus at infinity, a
focus bracket and the adequacy test's false-alarm rate on noisy renders.
"""

import contextlib
import io
import json
import logging
import re
from pathlib import Path

import numpy as np
from hypothesis import Phase, given, settings, strategies as st

import jaxdof
from jaxdof._cli import main


def _settings(examples: int):
    # No shrinking: a failing fit is reported at once (shrinking would refit for minutes).
    return settings(
        max_examples=examples,
        deadline=None,
        derandomize=True,
        database=None,
        phases=[Phase.explicit, Phase.generate],
    )


# What `render` offers, as keywords: the plain soft scatter (its default), with the footprint
# correction, the two occlusion renders, and `auto` (the scene's treatment at the true lens).
MODELS = {
    "soft": {},
    "soft+footprint": {"footprint": True},
    "local_occlusion": {"method": "local_occlusion"},
    "occlusion": {"method": "occlusion"},
    "auto": {"method": "auto"},
}
TOL = 1e-4  # relative, on the f-number and on the focus power (over the nearest depth's power)


def _scene(kind: str, h: int, w: int, dtype, seed: int = 0):
    rng = np.random.default_rng(seed)
    image = rng.uniform(0.05, 1.0, size=(h, w, 3)).astype(dtype)
    if kind == "ramp":
        depth = np.linspace(1.0, 5.0, w, dtype=dtype)[None, :].repeat(h, 0)
    else:  # a step between two slanted planes (two flat planes alone leave a near/far ambiguity)
        x = np.linspace(0.0, 1.0, w, dtype=dtype)
        depth = np.where(x < 0.5, 1.2 + x, 3.0 + 2 * x)[None, :].repeat(h, 0).astype(dtype)
    return image, depth


def _lens(n, d_f, width):
    return jaxdof.ThinLens.from_sensor(0.05, n, d_f, sensor_width=0.0048, image_width=width)


def _errors(fit, truth, depth):
    """Relative f-number error and focus-power error over the nearest depth's power."""
    n = float(np.asarray(fit.lenses.f_number).reshape(-1)[0])
    d_f = float(np.asarray(fit.lenses.focus_distance).reshape(-1)[0])
    d_t = float(truth.focus_distance)
    power = lambda d: 0.0 if np.isinf(d) else 1.0 / d
    e_n = n / float(truth.f_number) - 1
    e_u = (power(d_f) - power(d_t)) * float(np.min(depth))
    return e_n, e_u


def _round_trip(model: str, kind: str, n: float, d_f: float, dtype, shape=(40, 56), tol=TOL):
    image, depth = _scene(kind, *shape, dtype)
    truth = _lens(n, d_f, shape[1])
    photo = jaxdof.render(image, depth, truth, **MODELS[model])
    start = _lens(1.5 * n, 0.8 * d_f if np.isfinite(d_f) else 20.0, shape[1])
    fit = jaxdof.fit_lens(image, depth, photo, start)
    e_n, e_u = _errors(fit, truth, depth)
    label = f"{model} {kind} N={n:.3g} d_f={d_f:.3g}: {fit.message} | {fit.treatment}"
    assert bool(fit.success), label
    assert abs(e_n) < tol and abs(e_u) < tol, f"{label}: N {e_n:+.2e}, power {e_u:+.2e}"
    return fit


# Lenses whose circles over the ramp (1-5 m) and the step (1.2-1.7 m, 4-5 m) on a 56 px, 4.8 mm
# sensor run from about 0.3 px to 5 px: f/2-f/11, focused at 1.8-3.5 m. (The tests run with x64 on,
# conftest.py: the dtype of the arrays is the fit's precision.)
@_settings(5)
@given(
    model=st.sampled_from(sorted(MODELS)),
    kind=st.sampled_from(["ramp", "step"]),
    n=st.floats(2.0, 11.0),
    d_f=st.floats(1.8, 3.5),
    dtype=st.sampled_from([np.float32, np.float64]),
)
def test_default_fit_recovers_every_render(model, kind, n, d_f, dtype):
    _round_trip(model, kind, n, d_f, dtype)


@_settings(6)
@given(
    model=st.sampled_from(sorted(MODELS)),
    kind=st.sampled_from(["ramp", "step"]),
    n=st.floats(1.0, 16.0),
    d_f=st.one_of(st.floats(1.5, 6.0), st.just(float("inf"))),
)
def test_default_fit_recovers_every_render_wide(model, kind, n, d_f):
    """Circles from under a pixel (f/16 at 4-6 m) to about 30 px (f/1 at infinity on a 4.8 mm
    sensor of 96 px), focus at infinity included, on a frame that leaves pixels inside the
    border band. The fit renders occlusion as `LocalOcclusion` (per pair of pixels); the global
    layers of `Occlusion` differ from it within a circle of the edges, which with circles of
    tens of pixels moves the lens by up to 1e-3 (9e-4 in N at f/1.5 focused at infinity): its
    renders are held to 1e-3 here, every other model to 1e-4."""
    tol = 1e-3 if model == "occlusion" else TOL
    _round_trip(model, kind, n, d_f, np.float32, shape=(96, 128), tol=tol)


def test_default_fit_recovers_a_rendered_bracket():
    """A focus bracket of three renders through one f-number: focal length and f-number shared,
    each focus its own."""
    image, depth = _scene("ramp", 40, 56, np.float32)
    truths = [_lens(2.8, d, 56) for d in (1.6, 2.5, 4.0)]
    photos = [jaxdof.render(image, depth, t) for t in truths]
    starts = [_lens(4.0, 0.8 * d, 56) for d in (1.6, 2.5, 4.0)]
    fit = jaxdof.fit_lens(
        image, depth, photos, starts, free=("f_number", "focus_distance"), shared=("f_number",)
    )
    assert bool(fit.success), fit.message
    np.testing.assert_allclose(np.asarray(fit.lenses.f_number), 2.8, rtol=TOL)
    np.testing.assert_allclose(
        np.asarray(fit.lenses.focus_distance), [1.6, 2.5, 4.0], rtol=TOL * 1.6
    )


def test_adequacy_passes_noisy_renders_at_its_nominal_rate():
    """The default fit of a render plus Gaussian noise (sigma 1 % of the mean) is consistent at
    about the test's nominal rate (level 0.01): over 16 noise draws, at most 2 inconsistent
    (binomial(16, 0.01) exceeds 2 with probability 5e-4), and the truth within 3 standard errors
    of every consistent fit."""
    image, depth = _scene("ramp", 40, 56, np.float32)
    truth = _lens(2.8, 2.5, 56)
    clean = np.asarray(jaxdof.render(image, depth, truth))
    start = _lens(4.2, 2.0, 56)
    inconsistent = 0
    for seed in range(16):
        noise = np.random.default_rng(100 + seed).normal(0, 0.01 * clean.mean(), clean.shape)
        fit = jaxdof.fit_lens(image, depth, (clean + noise).astype(np.float32), start)
        if not bool(fit.adequacy["adequate"]):
            inconsistent += 1
            continue
        n_err = abs(float(fit.lenses.f_number[0]) - 2.8)
        assert n_err < 3 * float(fit.stderr["f_number"]), fit.summary()
    assert inconsistent <= 2


def test_a_default_fit_compiles_one_solve(caplog):
    """The default fit of a render of a step traces its solve once and its statistics once,
    although it tries two renders (the occlusion render it chose and the soft one, the photo's
    say), solves again at a smaller window (the fitted circles need less than the starts' did)
    and tries the footprint correction off: on a small photo the occlusion and the footprint
    correction are chosen at run time, the refit reuses the larger window's program, and the
    statistics do not depend on the render. (A shape of its own, so that no other test traced
    these programs first.)"""
    image, depth = _scene("step", 44, 60, np.float32)
    photo = jaxdof.render(image, depth, _lens(2.8, 2.5, 60))
    with caplog.at_level(logging.DEBUG, logger="jax._src.dispatch"):
        fit = jaxdof.fit_lens(image, depth, photo, _lens(4.2, 2.0, 60))
    text = str(fit.treatment)
    assert bool(fit.success) and "occlusion off" in text and "footprint off" in text, text
    messages = [r.getMessage() for r in caplog.records]
    traced = [m.split()[2] for m in messages if m.startswith("Finished tracing")]
    assert traced.count("fit_starts") == 1 and traced.count("finish") == 1, traced


def _readme_example() -> str:
    text = (Path(__file__).resolve().parents[1] / "README.md").read_text()
    section = text[text.index("## Quick example") :]
    found = re.search(r"```python\n(.*?)```", section, re.S)
    assert found, "the README's quick example has no python block"
    return found.group(1)


def test_readme_quick_example_recovers_its_lens():
    """The README's quick example, run as written: it prints success, and the truth lies within
    the reported standard errors (and 1e-3) of the fitted lens."""
    code = _readme_example()
    out = io.StringIO()
    ns: dict = {}
    with contextlib.redirect_stdout(out):
        exec(compile(code, "README.md", "exec"), ns)
    printed = out.getvalue()
    fit, truth = ns["fit"], ns["truth"]
    assert "success" in printed and "FAILED" not in printed, printed
    assert bool(fit.success)
    for name in ("f_number", "focus_distance"):
        got = float(np.asarray(getattr(fit.lenses, name)).reshape(-1)[0])
        want = float(getattr(truth, name))
        assert abs(got / want - 1) < 1e-3, (name, got, want)
        assert abs(got - want) <= 3 * float(fit.stderr[name]) + 1e-6 * want, printed


def test_cli_render_then_fit_recovers_the_lens(tmp_path):
    """`jaxdof render` then `jaxdof fit` on the same files, default options: exit 0, the lens."""
    image, depth = _scene("ramp", 40, 56, np.float32)
    np.save(tmp_path / "sharp.npy", image)
    np.save(tmp_path / "depth.npy", depth)
    sensor = ["--sensor-width", "4.8mm"]
    truth = ["--focal-length", "50mm", "--f-number", "2.8", "--focus", "2.5m", *sensor]
    photo = tmp_path / "photo.npy"
    sharp, dep = str(tmp_path / "sharp.npy"), str(tmp_path / "depth.npy")
    assert main(["render", sharp, dep, "-o", str(photo), *truth, "--quiet"]) == 0
    start = ["--focal-length", "50mm", "--f-number", "4", "--focus", "2m", *sensor]
    out = io.StringIO()
    with contextlib.redirect_stdout(out):
        code = main(["fit", sharp, dep, str(photo), *start, "--json", "--quiet"])
    assert code == 0, out.getvalue()
    obj = json.loads(out.getvalue())
    assert obj["success"] is True
    lens = obj["lenses"][0]
    assert abs(lens["f_number"] / 2.8 - 1) < 1e-3 and abs(lens["focus_distance"] / 2.5 - 1) < 1e-3


def test_cli_fit_with_an_8bit_photo_and_a_16bit_depth_png_with_holes(tmp_path):
    """What a camera and a depth sensor give: an 8-bit sRGB PNG photo and a 16-bit depth PNG in
    millimetres with 0 where the sensor has no data. `jaxdof fit`: exit 0 and the lens."""
    import imageio.v3 as iio

    image, depth = _scene("step", 40, 56, np.float32)
    encode = lambda x: np.round(255 * np.clip(x, 0, 1) ** (1 / 2.2)).astype(np.uint8)
    decode = lambda x: (x.astype(np.float32) / 255) ** 2.2  # what the image really is
    iio.imwrite(tmp_path / "sharp.png", encode(image))
    truth = _lens(2.8, 2.5, 56)
    photo = np.asarray(jaxdof.render(decode(encode(image)), depth, truth))
    iio.imwrite(tmp_path / "photo.png", encode(photo))
    mm = np.round(depth * 1000).astype(np.uint16)
    mm[10:13, 8:12] = 0
    mm[25:27, 40:44] = 0
    iio.imwrite(tmp_path / "depth.png", mm)
    out = io.StringIO()
    argv = [str(tmp_path / n) for n in ("sharp.png", "depth.png", "photo.png")]
    lens = ["--focal-length", "50mm", "--f-number", "4", "--focus", "2m", "--sensor-width", "4.8mm"]
    with contextlib.redirect_stdout(out):
        code = main(["fit", *argv, "--depth-scale", "1mm", *lens, "--json", "--quiet"])
    assert code == 0, out.getvalue()
    obj = json.loads(out.getvalue())
    assert obj["success"] is True and obj["treatment"]["depth_holes"] == 20
    fitted = obj["lenses"][0]
    assert (
        abs(fitted["f_number"] / 2.8 - 1) < 0.01 and abs(fitted["focus_distance"] / 2.5 - 1) < 0.01
    )


def test_cli_fit_with_a_camera_jpeg_and_a_16bit_depth_png_with_holes(tmp_path):
    """A camera JPEG (quality 90, colour at half resolution, 4:2:0) of an 8-bit sRGB image's
    render, with a 16-bit depth PNG holding zeros: `jaxdof fit` reads the JPEG's header, compares
    the luma (the full-resolution part of the file) in its blocks, exits 0 and finds the lens
    within 2 %."""
    import imageio.v3 as iio
    from PIL import Image

    from jaxdof._io import linear_to_srgb, srgb_to_linear

    image, depth = _scene("step", 40, 56, np.float32)
    code = np.round(255 * linear_to_srgb(np.clip(image, 0, 1))).astype(np.uint8)
    iio.imwrite(tmp_path / "sharp.png", code)
    truth = _lens(2.8, 2.5, 56)
    sharp = srgb_to_linear(code / 255.0).astype(np.float32)  # what the file holds
    photo = np.asarray(jaxdof.render(sharp, depth, truth))
    jpeg = np.round(255 * linear_to_srgb(np.clip(photo, 0, 1))).astype(np.uint8)
    Image.fromarray(jpeg).save(tmp_path / "photo.jpg", quality=90, subsampling=2)
    mm = np.round(depth * 1000).astype(np.uint16)
    mm[10:13, 8:12] = 0
    iio.imwrite(tmp_path / "depth.png", mm)
    out = io.StringIO()
    argv = [str(tmp_path / n) for n in ("sharp.png", "depth.png", "photo.jpg")]
    lens = ["--focal-length", "50mm", "--f-number", "4", "--focus", "2m", "--sensor-width", "4.8mm"]
    with contextlib.redirect_stdout(out):
        code = main(["fit", *argv, "--depth-scale", "1mm", *lens, "--json", "--quiet"])
    assert code == 0, out.getvalue()
    obj = json.loads(out.getvalue())
    assert obj["success"] is True and obj["nuisances"]["luma"]["fitted"] is True
    assert obj["nuisances"]["luma"]["forced"] is True  # from the file's header
    assert obj["nuisances"]["luma"]["jpeg"]["found"] is True  # in the file's blocks
    fitted = obj["lenses"][0]
    assert abs(fitted["f_number"] / 2.8 - 1) < 0.02, fitted
    assert abs(fitted["focus_distance"] / 2.5 - 1) < 0.02, fitted
