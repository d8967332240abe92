"""The `jaxdof` command line, run as a user runs it: in a subprocess, on small files.

Each subprocess pays for importing JAX and compiling (seconds; a fit compiles for ~20 s of CPU),
so the runs are few: `demo`, one `fit` (read by two tests), two `render`s, two real bad-input
runs (the `jaxdof` script and `python -m jaxdof`), and one subprocess that feeds the whole table
of bad inputs to `jaxdof._cli.main`, the function both entry points call and whose return value
is their exit status. A traceback there fails the test (it would escape `main`). In-process:
the text and JSON output (`report`, on a `FitResult` built directly), what `fit` hands
`fit_lens` (`commands.fit_call`, no solve), and one `render --focus inf`.
"""

import hashlib
import json
import os
import pathlib
import re
import subprocess
import sys

import imageio.v3 as iio
import numpy as np
import pytest

from jaxdof import _io
from jaxdof._cli import commands, main, report
from jaxdof._cli.demo import demo_scene
from jaxdof._cli.parse import build_parser


H, W = 24, 32
SENSOR = "12mm"  # pixel pitch 12 mm / 32 = 0.375 mm: circles of up to ~3.5 px on this scene
TRUTH = {"focal_length": 0.085, "f_number": 1.4, "focus_distance": 3.0}
ENV = {**os.environ, "JAX_PLATFORMS": "cpu"}


def _lens(jaxdof, f_number=1.4, focus=3.0):
    return jaxdof.ThinLens.from_sensor(0.085, f_number, focus, sensor_width=0.012, image_width=W)


@pytest.fixture(scope="module")
def files(tmp_path_factory):
    """Small input files (and bad ones) in one folder, with the SHA-256 of each."""
    import jaxdof

    d = tmp_path_factory.mktemp("cli")
    image, depth = demo_scene(H, W)
    codes = np.round(_io.linear_to_srgb(image) * 255).astype(np.uint8)
    iio.imwrite(d / "sharp.png", codes)
    linear = _io.read_image(str(d / "sharp.png")).array  # what the CLI sees
    np.save(d / "depth.npy", depth)
    iio.imwrite(d / "sharp.tif", linear)
    iio.imwrite(d / "depth_mm.png", np.round(depth * 1000).astype(np.uint16))
    target = np.asarray(jaxdof.render(linear, depth, _lens(jaxdof)))
    for name in ("target.npy", "near.npy", "far.npy"):  # near/far: stand-ins of the same size
        np.save(d / name, target)
    np.save(d / "small.npy", np.ones((H - 1, W), np.float32))
    np.save(d / "small3.npy", np.ones((H, W - 1, 3), np.float32))
    np.save(d / "nan.npy", np.where(np.arange(W) == 3, np.nan, depth).astype(np.float32))
    np.save(d / "zero.npy", np.where(np.arange(W) == 3, 0.0, depth).astype(np.float32))
    np.save(d / "close.npy", np.where(np.arange(W) == 3, 0.05, depth).astype(np.float32))
    np.save(d / "pickled.npy", np.array([{"depth": 1}], dtype=object), allow_pickle=True)
    # --weight: an RGB mask with equal channels that zeroes the left half of the photo, one whose
    # channels differ, and negative weights
    half = np.zeros((H, W, 3), np.uint8)
    half[:, W // 2 :] = 255
    iio.imwrite(d / "half.png", half)
    iio.imwrite(
        d / "colour_mask.png", np.stack([half[..., 0], 255 - half[..., 0], half[..., 0]], -1)
    )
    np.save(d / "negative.npy", -np.ones((H, W), np.float32))
    (d / "garbage.png").write_bytes(b"this is not a png")
    (d / "sharp.bmp").write_bytes((d / "sharp.png").read_bytes())
    hashes = {p.name: hashlib.sha256(p.read_bytes()).hexdigest() for p in d.iterdir()}
    return d, hashes, linear, depth


def _unchanged(d, hashes):
    now = {p.name: hashlib.sha256(p.read_bytes()).hexdigest() for p in d.iterdir()}
    assert {k: now.get(k) for k in hashes} == hashes, "an input file changed"


def _run(args, cwd, *, script=False):
    cmd = (
        [os.path.join(os.path.dirname(sys.executable), "jaxdof")]
        if script
        else [sys.executable, "-m", "jaxdof"]
    )
    return subprocess.run(cmd + args, cwd=cwd, env=ENV, capture_output=True, text=True, timeout=600)


LENS = ["--focal-length", "85mm", "--f-number", "1.4", "--focus", "3m", "--sensor-width", SENSOR]


# ---------------------------------------------------------------------------------------------
# Help (in-process: argparse only)


@pytest.mark.parametrize("command", [[], ["demo"], ["render"], ["fit"]])
def test_help(command, capsys):
    assert main([*command, "--help"]) == 0
    out = capsys.readouterr().out
    assert out.startswith("usage: jaxdof")
    assert ("examples:" in out) == bool(command)
    if command == ["fit"]:
        assert "--weight FILE" in out and "--border {auto,off,N}" in out
    if command in (["fit"], ["render"]):
        assert "or inf" in out and "null" in out  # how an infinite focus is printed


def test_focus_and_border_options_parse():
    """`--focus inf`/`infinity` (any case) is focused at infinity, in render and fit; `--border`
    is auto by default, off is 0, and N a width (refused lengths and borders: `BAD`)."""
    parse = build_parser().parse_args
    for word in ("inf", "Infinity", "+inf"):
        assert parse([*R, *LENS[:4], "--focus", word]).focus == float("inf")
        assert parse([*F, "--focus", word]).focus == float("inf")
    assert parse([*R, *LENS]).focus == 3.0
    assert parse(F).border == "auto" and parse(F).weight is None
    assert parse([*F, "--border", "off"]).border == 0
    assert parse([*F, "--border", "5"]).border == 5


# ---------------------------------------------------------------------------------------------
# Success paths


def test_render_png(files):
    d, hashes, linear, depth = files
    import jaxdof

    res = _run(["render", "sharp.png", "depth.npy", "-o", "out.png", *LENS], d)
    assert res.returncode == 0, res.stderr
    assert "wrote out.png" in res.stdout
    out = iio.imread(d / "out.png")
    assert out.dtype == np.uint8 and out.shape == (H, W, 3)  # 8-bit in, 8-bit sRGB out
    expect = np.asarray(jaxdof.render(linear, depth, _lens(jaxdof)), np.float64)
    # One code of rounding on each side (here float64 lens, there float32).
    assert np.max(np.abs(out.astype(float) - np.round(_io.linear_to_srgb(expect) * 255))) <= 1
    _unchanged(d, hashes)
    (d / "out.png").unlink()


def test_render_footprint_option(files):
    """`--footprint` is `render(..., footprint=True)`: the opt-in pixel-footprint correction."""
    d, hashes, linear, depth = files
    import jaxdof

    res = _run(["render", "sharp.png", "depth.npy", "-o", "out.npy", "--footprint", *LENS], d)
    assert res.returncode == 0, res.stderr
    out = np.load(d / "out.npy")
    expect = np.asarray(jaxdof.render(linear, depth, _lens(jaxdof), footprint=True))
    plain = np.asarray(jaxdof.render(linear, depth, _lens(jaxdof)))
    # float32 in the CLI against this float64 call: rounding only; and not the plain render
    assert np.max(np.abs(out - expect)) < 1e-5
    assert np.max(np.abs(out - plain)) > 1e-3
    _unchanged(d, hashes)
    (d / "out.npy").unlink()


def test_render_auto_method_says_what_it_chose(files):
    """`--method auto`: the scene's treatment (`jaxdof.scene_treatment`), said in the output."""
    d, hashes, linear, depth = files
    import jaxdof

    res = _run(["render", "sharp.png", "depth.npy", "-o", "out.npy", "--method", "auto", *LENS], d)
    assert res.returncode == 0, res.stderr
    t = jaxdof.scene_treatment(depth, _lens(jaxdof))
    assert t.footprint, t  # circles of a few pixels
    assert "treatment: " in res.stdout and "footprint" in res.stdout.split("treatment: ")[1]
    out = np.load(d / "out.npy")
    expect = jaxdof.render(linear, depth, _lens(jaxdof), method=t.method, footprint=t.footprint)
    assert np.max(np.abs(out - np.asarray(expect))) < 1e-5  # float32 there, float64 here
    _unchanged(d, hashes)
    (d / "out.npy").unlink()


def test_render_downsample_option(files):
    """`--downsample 2`: IMAGE and DEPTH at twice the photo's resolution; the output (and the lens's
    pixel pitch, from --sensor-width) is the photo's."""
    d, hashes, linear, depth = files
    import jaxdof

    res = _run(["render", "sharp.png", "depth.npy", "-o", "out.npy", "--downsample", "2", *LENS], d)
    assert res.returncode == 0, res.stderr
    out = np.load(d / "out.npy")
    assert out.shape == (H // 2, W // 2, 3)
    lens = jaxdof.ThinLens.from_sensor(0.085, 1.4, 3.0, sensor_width=0.012, image_width=W // 2)
    expect = np.asarray(jaxdof.render(linear, depth, lens, downsample=2))
    assert np.max(np.abs(out - expect)) < 1e-5  # float32 there, float64 here
    _unchanged(d, hashes)
    (d / "out.npy").unlink()


def test_render_float_tiff_and_millimetre_png(files):
    d, hashes, linear, depth = files
    import jaxdof

    args = ["render", "sharp.tif", "depth_mm.png", "--depth-scale", "1mm", "-o", "out.npy"]
    res = _run([*args, *LENS, "--normalize"], d)
    assert res.returncode == 0, res.stderr
    out = np.load(d / "out.npy")
    assert out.dtype == np.float32 and out.shape == (H, W, 3)  # float in, float linear out
    depth_mm = np.round(depth.astype(np.float64) * 1000) / 1000  # what the 16-bit PNG holds
    expect = jaxdof.render(linear, depth_mm.astype(np.float32), _lens(jaxdof), normalize=True)
    # float32 rendering there, float32 image/depth with a float64 lens here: a few ulps.
    np.testing.assert_allclose(out, np.asarray(expect), rtol=1e-5, atol=1e-6)
    _unchanged(d, hashes)
    (d / "out.npy").unlink()


@pytest.fixture(scope="module")
def fit_run(files):
    """One `jaxdof fit ... --weight half.png --json --plot fit.png` (it compiles for ~20 s of CPU;
    a weight is data, so the unweighted fit compiles the same): its completed process and the
    figure's number of axes (the figure is removed again: later tests check that nothing was left
    in the folder)."""
    d, hashes, _, _ = files
    start = ["--focal-length", "85mm", "--f-number", "4", "--focus", "5m", "--sensor-width", SENSOR]
    argv = ["fit", "sharp.png", "depth.npy", "target.npy", *start, "--weight", "half.png"]
    # The target is the library's own default render: fit exactly that model.
    exact = ["--method", "soft", "--no-footprint", "--edge-weight", "off"]
    res = _run([*argv, *exact, "--json", "--plot", "fit.png", "--steps"], d)
    figure = d / "fit.png"
    ndim = iio.imread(figure).ndim if figure.exists() else None
    figure.unlink(missing_ok=True)
    _unchanged(d, hashes)
    return res, ndim


def test_fit_json_and_plot(fit_run):
    res, figure_ndim = fit_run
    assert res.returncode == 0, res.stderr
    obj = json.loads(res.stdout)  # exactly one JSON object on stdout
    assert obj["success"] is True and obj["steps"] > 0 and obj["loss"] >= 0
    assert set(obj["stderr"]) == {"f_number", "focus_distance"}
    assert obj["treatment"]["forced"] == ["occlusion", "footprint", "edge_weight"]
    assert obj["pixel_pitch"] == pytest.approx(0.012 / W)
    # A noise-free target rendered by the same float32 model: the optimum is the truth, reached
    # to float32 solver precision (the fit's tolerance is 1e-5 in log coordinates).
    for name, value in TRUTH.items():
        assert obj[name] == pytest.approx(value, rel=1e-3), name
    assert len(obj["lenses"]) == 1 and obj["lenses"][0]["focus_distance"] == obj["focus_distance"]
    assert "loss" in res.stderr  # progress goes to stderr
    assert figure_ndim == 3
    # --weight half.png zeroes the left half: the fit uses at most the right half, less the band
    assert 0 < obj["pixels_used"] <= H * (W // 2) - obj["border"] * (W // 2)
    assert obj["border"] > 0  # --border auto
    # FitResult.to_dict()'s keys
    assert obj["status"] == "successful" and obj["names"] == ["f_number", "focus_distance"]
    assert len(obj["covariance"]) == 2 and obj["gain"] == [1.0] and obj["offset"] == [0.0]
    assert obj["focus_power"] == pytest.approx(1 / 3.0, rel=1e-3) and obj["levels"] >= 1
    assert obj["sigma"] >= 0 and obj["condition"] >= 1 and obj["max_radius"] > 0


# A plain progress line (stderr is not a terminal): solve, start i/n, step, loss, lens, elapsed.
_STEP = re.compile(
    r"^\s*solve (\d+) start (\d+)/(\d+)\s+step\s+(\d+)\s+loss (\S+)"
    r"\s+N (\S+)\s+d_f (\S+) m\s+\((\S+) s\)$"
)


def test_fit_progress_prints_each_step_once(fit_run):
    """Each accepted step of each start once on stderr (optimistix's callback fires on every
    trial step, and again for every start already done while the others run), with the lens it
    reached (the free fields) and the time; the best line of the last solve is the fit's answer."""
    res, _ = fit_run
    assert res.returncode == 0, res.stderr
    lines = [line for line in res.stderr.splitlines() if "step" in line]
    assert lines, res.stderr
    assert len(lines) == len(set(lines)), "a step line is repeated"
    steps, last = {}, {}
    for line in lines:
        match = _STEP.match(line)
        assert match, line
        solve, start, starts, step, loss, n, d_f, seconds = match.groups()
        assert 1 <= int(start) <= int(starts)
        steps.setdefault((solve, start), []).append(int(step))
        last[int(solve)] = last.get(int(solve), []) + [(float(loss), float(n), float(d_f))]
        assert float(seconds) >= 0
    assert all(s == sorted(set(s)) for s in steps.values()), steps
    # and the compiled stages, each with its time
    assert re.search(r"^  solving: \S+ s \(\S+ s\)$", res.stderr, re.M), res.stderr
    assert re.search(r"^  standard errors and the adequacy test: ", res.stderr, re.M)
    obj = json.loads(res.stdout)
    _, n, d_f = min(last[max(last)])  # the lowest loss of the last solve
    assert n == pytest.approx(obj["f_number"], rel=1e-3)  # 4 digits printed
    assert d_f == pytest.approx(obj["focus_distance"], rel=1e-3)


def test_fit_downsample_option(tmp_path):
    """`fit --downsample 2`: a 48 x 64 all-in-focus input for a 24 x 32 photo (noise-free, rendered
    by the library with the same float32 model); the lens comes back to solver precision."""
    import jaxdof

    image, depth = demo_scene(2 * H, 2 * W)
    np.save(tmp_path / "sharp.npy", image)
    np.save(tmp_path / "depth.npy", depth)
    lens = jaxdof.ThinLens.from_sensor(0.085, 1.4, 3.0, sensor_width=0.012, image_width=W)
    np.save(tmp_path / "photo.npy", np.asarray(jaxdof.render(image, depth, lens, downsample=2)))
    start = ["--focal-length", "85mm", "--f-number", "2", "--focus", "3.6m", "--sensor-width"]
    argv = ["fit", "sharp.npy", "depth.npy", "photo.npy", *start, SENSOR, "--downsample", "2"]
    exact = ["--method", "soft", "--no-footprint", "--edge-weight", "off"]  # the photo's own model
    res = _run(
        [*argv, *exact, "--border", "off", "--json", "--quiet", "--plot", "fit.png"], tmp_path
    )
    assert res.returncode == 0, res.stderr
    obj = json.loads(res.stdout)
    assert obj["success"] is True
    assert obj["border"] == 0 and obj["pixels_used"] == H * W  # --border off: every photo pixel
    assert obj["pixel_pitch"] == pytest.approx(0.012 / W)  # the photo's pitch
    for name, value in TRUTH.items():
        assert obj[name] == pytest.approx(value, rel=1e-3), name
    assert iio.imread(tmp_path / "fit.png").ndim == 3  # the figure at the photo's pixels


def test_fit_arguments(files, monkeypatch):
    """What `fit` hands `jaxdof.fit_lens` (`commands.fit_call`, in-process, no solve): the
    TARGETs stacked to `(T, H, W, 3)`, the options, the `--weight` file (an RGB mask with equal
    channels: one channel, 8-bit 0/255 as 0/1), `--border`, and a start focused at infinity."""
    d, hashes, _, _ = files
    monkeypatch.chdir(d)
    parse = build_parser().parse_args
    start = ["--focal-length", "85mm", "--sensor-width", SENSOR, "--shared", "f_number"]
    call = commands.fit_call(
        parse(["fit", "sharp.png", "depth.npy", "near.npy", "far.npy", *start])
    )
    image, depth, targets, init = call.positional
    assert image.shape == (H, W, 3) and depth.shape == (H, W)
    assert targets.shape == (2, H, W, 3) and len(call.targets) == 2
    k = call.kwargs
    assert k["shared"] == ("f_number",) and k["free"] == ("focus_distance", "f_number")
    assert k["method"] is None and k["footprint"] is None and k["edge_weight"] is None
    assert k["border"] == "auto" and k["weight"] is None
    assert float(init.focus_distance) == pytest.approx(float(np.median(depth)))
    extra = ["--weight", "half.png", "--border", "off", "--focus", "inf", "--quiet"]
    call = commands.fit_call(parse([*F, *extra]))
    weight = call.kwargs["weight"]
    assert call.positional[2].shape == (H, W, 3)  # one TARGET: as it is
    assert weight.shape == (H, W) and set(np.unique(weight)) == {0.0, 1.0}
    assert weight[:, : W // 2].max() == 0 and weight[:, W // 2 :].min() == 1
    assert call.kwargs["border"] == 0 and call.kwargs["verbose"] is False
    assert float(call.init.focus_distance) == float("inf")
    _unchanged(d, hashes)


def _fit_result(focus, *, success=True):
    """A `jaxdof.FitResult` of `len(focus)` targets, built directly (the fit itself is tested
    above and in tests/test_fit.py): f/1.4 shared, the focus distance per target."""
    import jax.numpy as jnp

    import jaxdof

    n = len(focus)
    lenses = jaxdof.ThinLens(
        jnp.full(n, 0.085), jnp.full(n, 1.4), jnp.array(focus), jnp.full(n, 0.012 / W)
    )
    se = jnp.array([0.02, 0.03][:n])
    names = ("f_number", *(f"focus_distance[{t}]" for t in range(n)))
    return jaxdof.FitResult(
        lenses=lenses,
        stderr={"f_number": jnp.full(n, 0.01), "focus_distance": se},
        covariance=jnp.eye(n + 1) * 1e-4,
        gain=jnp.ones(n),
        offset=jnp.zeros(n),
        loss=jnp.array(0.5),
        sigma=jnp.array(0.01),
        num_steps=jnp.array(7),
        condition=jnp.array(3.0),
        status=jaxdof.RESULTS.successful if success else jaxdof.RESULTS.max_steps,
        success=jnp.array(success),
        focus_power_stderr=jnp.full(n, 0.002),
        pixels_used=jnp.array(1000),
        adequacy=dict(
            chi2=jnp.array(30.0),
            dof=jnp.array(34.0),
            p_value=jnp.array(0.67),
            tiles=jnp.array(9),
            inflation=jnp.array(1.0),
            spread=jnp.array(1.2),
            adequate=jnp.array(True),
        ),
        names=names,
        max_radius=4.0,
        border=3,
        levels=1,
    )


def test_fit_several_targets_output(capsys):
    """The text and JSON layout for several targets (`report.fit_summary` and `print_fit`, on a
    `FitResult` with one lens per target; `fit`'s arguments: `test_fit_arguments`)."""
    summary = report.fit_summary(_fit_result([2.0, 4.5]))
    free = ["focus_distance", "f_number"]
    report.print_fit(summary, ["near.npy", "far.npy"], free, as_json=True)
    obj = json.loads(capsys.readouterr().out)
    assert [x["focus_distance"] for x in obj["lenses"]] == [2.0, 4.5]
    assert [x["stderr"]["focus_distance"] for x in obj["lenses"]] == [0.02, 0.03]
    assert [x["focus_power"] for x in obj["lenses"]] == [0.5, pytest.approx(1 / 4.5)]
    assert obj["focus_distance"] == 2.0 and obj["steps"] == 7 and obj["success"] is True
    assert obj["status"] == "successful" and obj["pixels_used"] == 1000 and obj["border"] == 3
    assert obj["names"] == ["f_number", "focus_distance[0]", "focus_distance[1]"]
    assert obj["sigma"] == 0.01 and obj["levels"] == 1 and obj["gain"] == [1.0, 1.0]
    report.print_fit(summary, ["near.npy", "far.npy"], free, as_json=False, pixels=2 * H * W)
    text = capsys.readouterr().out
    assert "target far.npy:" in text and "4.5 m ± 0.03" in text and "converged" in text
    assert f"pixels used 1000 of {2 * H * W} (border 3 px)" in text
    assert "model check: consistent (p = 0.67, 9 tiles); standard errors: noise" in text
    assert obj["adequacy"]["adequate"] is True and obj["stderr_kind"] == "noise"


def test_fit_output_focus_at_infinity(capsys):
    """A focus distance at infinity is `null` in JSON (SI numbers only) and `inf` in text; a
    failed fit's text names its status; the kind of standard errors shows when known."""
    summary = report.fit_summary(_fit_result([float("inf")], success=False))
    report.print_fit(summary, ["far.npy"], ["f_number"], as_json=True)
    out = capsys.readouterr().out
    assert "Infinity" not in out  # valid JSON
    obj = json.loads(out)
    assert obj["focus_distance"] is None and obj["lenses"][0]["focus_distance"] is None
    assert obj["focus_power"] == 0.0 and obj["success"] is False and obj["status"] == "max_steps"
    report.print_fit(summary, ["far.npy"], ["f_number"], as_json=False)
    text = capsys.readouterr().out
    assert "recovered lens:" in text and "inf m" in text and "(held)" in text
    assert "pixels used 1000 (border 3 px)" in text and "did NOT converge (max_steps)" in text
    # An inconsistent fit: a lens with inflated standard errors (success), and the verdict.
    test = {**summary["adequacy"], "adequate": False, "p_value": 1e-9, "inflation": 2.5}
    bad = {
        **summary,
        "success": True,
        "status": "inconsistent",
        "adequacy": test,
        "stderr_kind": "tile spread",
    }
    report.print_fit(bad, ["far.npy"], [], as_json=False)
    text = capsys.readouterr().out
    assert "model check: INCONSISTENT (p = 1e-09, 9 tiles)" in text
    assert "standard errors: tile spread (noise x 2.5)" in text and "FAILED" not in text
    assert "converged, standard errors inflated to the tiles' spread" in text


def test_render_focus_at_infinity(files, tmp_path):
    """`render --focus inf` (in-process): the library's render of a lens focused at infinity."""
    d, hashes, linear, depth = files
    import jaxdof

    out = tmp_path / "inf.npy"
    lens = [*LENS[:4], "--focus", "inf", "--sensor-width", SENSOR]
    assert main(["render", str(d / "sharp.png"), str(d / "depth.npy"), "-o", str(out), *lens]) == 0
    expect = np.asarray(jaxdof.render(linear, depth, _lens(jaxdof, focus=float("inf"))))
    np.testing.assert_allclose(np.load(out), expect, rtol=1e-5, atol=1e-6)
    _unchanged(d, hashes)


def test_render_in_bands(files, tmp_path, capsys):
    """`render --memory` (in-process): a frame whose render would need more than the budget is
    rendered in bands, the highest that fit, with the whole frame's pixels; stdout says so, and
    stderr (not a terminal) has a plain line per band, none with `--quiet`. The estimate's
    constants are made tiny here, so that a 24 x 32 frame needs bands: a budget of what bands of
    8 rows need gives 3 bands of 8 rows."""
    d, hashes, linear, depth = files
    import jaxdof
    from jaxdof.internal import estimate_memory, tuning

    lens = _lens(jaxdof)
    radius = float(np.max(np.asarray(jaxdof.coc_radius(depth, lens))))
    table = {**tuning.RENDER_MEMORY, "fixed": 0, "band_fixed": 0}
    argv = ["render", str(d / "sharp.png"), str(d / "depth.npy"), *LENS]
    with tuning.override(CLI_MEMORY={"process": 0, "per_pixel": 0.0}, RENDER_MEMORY=table):
        budget = estimate_memory((H, W, 3), radius, band_rows=8)
        assert main([*argv, "-o", str(tmp_path / "bands.npy"), "--memory", f"{budget}B"]) == 0
        out = capsys.readouterr()
        assert "3 bands of 8 rows" in out.out
        assert [line.split()[:2] for line in out.err.splitlines()] == [
            ["band", f"{k}/3"] for k in (1, 2, 3)
        ]
        quiet = ["-o", str(tmp_path / "quiet.npy"), "--memory", f"{budget}B", "--quiet"]
        assert main([*argv, *quiet]) == 0
        assert capsys.readouterr().err == ""
    expect = np.asarray(jaxdof.render(linear, depth, lens))
    np.testing.assert_allclose(np.load(tmp_path / "bands.npy"), expect, rtol=0, atol=1e-6)
    np.testing.assert_array_equal(np.load(tmp_path / "quiet.npy"), np.load(tmp_path / "bands.npy"))
    _unchanged(d, hashes)


def test_out_of_memory_is_one_line(files, tmp_path, monkeypatch, capsys):
    """XLA's `RESOURCE_EXHAUSTED` in `render` or `fit` (here raised by a stand-in): one line
    naming the image's size and what to try, exit status 2; any other error still raises."""
    d, hashes, _, _ = files
    import jax

    import jaxdof

    def exhausted(*args, **kwargs):
        raise jax.errors.JaxRuntimeError(
            "RESOURCE_EXHAUSTED: Out of memory allocating 29665187504 bytes."
        )

    monkeypatch.chdir(d)
    monkeypatch.setattr(jaxdof, "render", exhausted)
    assert main([*R[:4], str(tmp_path / "o.npy"), *LENS]) == 2
    line = _one_line(capsys.readouterr().err)
    assert "out of memory (an allocation of 27.7GB) on a 24x32 image" in line
    assert "smaller --memory" in line
    monkeypatch.setattr(jaxdof, "fit_lens", exhausted)
    assert main([*F, "--quiet"]) == 2
    line = _one_line(capsys.readouterr().err)
    assert line.startswith("jaxdof fit: error: out of memory") and "24x32" in line

    def broken(*args, **kwargs):
        raise RuntimeError("not about memory")

    monkeypatch.setattr(jaxdof, "render", broken)
    with pytest.raises(RuntimeError, match="not about memory"):
        main([*R[:4], str(tmp_path / "o.npy"), *LENS])
    _unchanged(d, hashes)


def test_demo(tmp_path):
    res = _run(["demo", "--out", "demo.png"], tmp_path)
    assert res.returncode == 0, res.stderr
    assert "truth" in res.stdout and "recovered" in res.stdout and "converged" in res.stdout
    assert iio.imread(tmp_path / "demo.png").ndim == 3


# ---------------------------------------------------------------------------------------------
# Bad input: exit status 2, one line on stderr naming the file or option, inputs untouched


def _one_line(stderr: str) -> str:
    assert "Traceback" not in stderr
    lines = stderr.strip().splitlines()
    assert len(lines) == 1, stderr
    return lines[0]


def test_bad_input_script_and_module(files):
    d, hashes, _, _ = files
    res = _run(["render", "sharp.png", "pickled.npy", "-o", "o.png", *LENS], d, script=True)
    assert res.returncode == 2
    assert "pickled.npy" in _one_line(res.stderr) and "pickled" in res.stderr
    res = _run(["render", "missing.png", "depth.npy", "-o", "o.png", *LENS], d)
    assert res.returncode == 2
    assert "missing.png: no such file" in _one_line(res.stderr)
    assert not (d / "o.png").exists()
    _unchanged(d, hashes)


R = ["render", "sharp.png", "depth.npy", "-o", "o.png"]
F = [
    "fit",
    "sharp.png",
    "depth.npy",
    "target.npy",
    "--focal-length",
    "85mm",
    "--sensor-width",
    SENSOR,
]
BAD = [  # (argv, text the one line must contain)
    (["render", "missing.png", "depth.npy", "-o", "o.png", *LENS], "missing.png: no such file"),
    (["render", "garbage.png", "depth.npy", "-o", "o.png", *LENS], "garbage.png: not a valid PNG"),
    (["render", "sharp.bmp", "depth.npy", "-o", "o.png", *LENS], "sharp.bmp: unsupported format"),
    (["render", "sharp.png", "pickled.npy", "-o", "o.png", *LENS], "pickled.npy: holds pickled"),
    (["render", "sharp.png", "small.npy", "-o", "o.png", *LENS], "small.npy: depth is 23x32"),
    (["render", "sharp.png", "nan.npy", "-o", "o.png", *LENS], "nan.npy: depth has"),
    (["render", "sharp.png", "zero.npy", "-o", "o.png", *LENS], "holes (0, negative or NaN"),
    # the library's checks of the values (jaxdof.ThinLens, render, fit_lens), as one line
    (["render", "sharp.png", "close.npy", "-o", "o.png", *LENS], "depth must be beyond the focal"),
    (
        ["render", "sharp.png", "depth_mm.png", "-o", "o.png", *LENS],
        "depth_mm.png: integer depth needs --depth-scale",
    ),
    (["render", "sharp.png", "depth.npy", "--zbuffer", "-o", "o.png", *LENS], "--near and --far"),
    (["render", "sharp.png", "depth.npy", "-o", "sharp.png", *LENS], "sharp.png: is also an input"),
    ([*R, *LENS, "--memory", "lots"], "argument --memory: bad memory size 'lots'"),
    ([*R, *LENS, "--memory", "1MB"], "needs about"),
    ([*R, *LENS, "--method", "occlusion", "--memory", "1MB"], "renders the whole frame at once"),
    (
        ["render", "sharp.png", "depth.npy", "-o", "o.bmp", *LENS],
        "o.bmp: unsupported output format",
    ),
    (
        [*R, *LENS[:-2], "--sensor-width", "12 inches"],
        "argument --sensor-width: bad length '12 inches'",
    ),
    ([*R, *LENS[:4], "--focus", "3km"], "argument --focus: bad length '3km'"),
    ([*R, *LENS[:4], "--focus=-3m"], "argument --focus: bad length '-3m'"),
    ([*R, "--focal-length", "inf", *LENS[2:]], "argument --focal-length: bad length 'inf'"),
    ([*R, *LENS[:-2], "--sensor-width", "infinity"], "argument --sensor-width: bad length"),
    ([*R, *LENS[:4], "--focus", "5cm"], "focus_distance must exceed focal_length"),
    ([*F, "--focus", "5cm"], "focus_distance must exceed focal_length"),
    ([*R, "--focal-length", "85", *LENS[2:]], "argument --focal-length: bare number '85'"),
    ([*R, *LENS[:2], "--f-number", "0", *LENS[4:]], "argument --f-number: '0' must be positive"),
    ([*R, *LENS[:2], "--f-number", "nan", *LENS[4:]], "argument --f-number"),
    ([*R, *LENS[:4]], "the following arguments are required: --focus"),
    ([*R, *LENS, "--method", "magic"], "argument --method: invalid choice"),
    ([*R, *LENS, "--max-radius", "-1"], "argument --max-radius"),
    ([*R, *LENS, "--downsample", "0"], "--downsample 0: downsample must be >= 1"),
    ([*R, *LENS, "--downsample", "5"], "--downsample 5: downsample=5 needs an image whose height"),
    ([*F, "--downsample", "2"], "target.npy: target has shape (24, 32, 3) but image sharp.png"),
    ([*F[:3], "small3.npy", *F[4:]], "small3.npy: target has shape (24, 31, 3)"),
    ([*F[:3], "missing.npy", *F[4:]], "missing.npy: no such file"),
    # the photos are read beside the image: the first broken file, in order, is the one named
    (["fit", "garbage.png", F[2], "missing.npy", *F[4:]], "garbage.png: not a valid PNG"),
    ([*F, "--free", "focal_length", "f_number"], "--free focal_length f_number: one photo"),
    ([*F, "--shared", "focal_length"], "shared must be a subset of free"),
    ([*F, "--free", "aperture"], "argument --free: invalid choice"),
    ([*F, "--max-steps", "0"], "max_steps must be a positive integer, got 0"),
    ([*F, "--method", "hard"], "cannot drive a fit"),
    ([*F, "--plot", "fit.jpg"], "--plot fit.jpg: the figure is written as PNG"),
    ([*F, "--plot", "target.npy"], "--plot target.npy: is also an input"),
    ([*F, "--plot", "half.png", "--weight", "half.png"], "--plot half.png: is also an input"),
    ([*F, "--weight", "small.npy"], "small.npy: weight is 23x32 (HxW) but the photo (TARGET)"),
    ([*F, "--weight", "colour_mask.png"], "colour_mask.png: weight has 3 different channels"),
    ([*F, "--weight", "negative.npy"], "negative.npy: weights must be >= 0"),
    ([*F, "--weight", "missing.png"], "missing.png: no such file (--weight)"),
    ([*F, "--border", "-1"], "argument --border: bad border '-1'"),
    ([*F, "--border", "wide"], "argument --border: bad border 'wide'"),
    # a fit estimated to need more than --memory stops before it starts (jaxdof/_tuning.py's
    # FIT_MEMORY: 0.4 GiB fixed); a 24 x 32 photo has no tile budget that would fit
    ([*F, "--memory", "100MB"], "needs about 411MB, over the 100MB --memory: give a smaller image"),
    (["demo", "--out", "demo.jpg"], "--out demo.jpg"),
    (["render"], "the following arguments are required"),
    (["unknown"], "invalid choice: 'unknown'"),
]

_DRIVER = """
import contextlib, io, json, sys
from jaxdof._cli import main
results = []
for argv in json.loads(sys.stdin.read()):
    err = io.StringIO()
    with contextlib.redirect_stderr(err), contextlib.redirect_stdout(io.StringIO()):
        code = main(argv)
    results.append([code, err.getvalue()])
print(json.dumps(results))
"""


def test_bad_inputs(files):
    d, hashes, _, _ = files
    res = subprocess.run(
        [sys.executable, "-c", _DRIVER],
        input=json.dumps([argv for argv, _ in BAD]),
        cwd=d,
        env=ENV,
        capture_output=True,
        text=True,
        timeout=600,
    )
    assert res.returncode == 0, res.stderr  # no exception escaped main()
    for (argv, expect), (code, stderr) in zip(BAD, json.loads(res.stdout), strict=True):
        assert code == 2, (argv, stderr)
        line = _one_line(stderr)
        assert line.startswith("jaxdof"), line
        assert expect in line, (argv, line)
    _unchanged(d, hashes)
    assert sorted(p.name for p in pathlib.Path(d).iterdir()) == sorted(hashes)  # nothing written


def test_fit_plot_outlines_the_fitted_tiles(tmp_path):
    """`--plot` of a fit on tiles outlines them on the residual panel (`FitResult.tiles`)."""
    pytest.importorskip("matplotlib")
    import matplotlib.pyplot as plt

    from jaxdof._cli import plot

    drawn = []
    real_savefig = plt.Figure.savefig

    def savefig(fig, *args, **kwargs):
        drawn.extend((ax.get_title(), len(ax.patches)) for ax in fig.axes if ax.get_title())
        return real_savefig(fig, *args, **kwargs)

    image = np.full((16, 20, 3), 0.5, np.float32)
    columns = [("target", image, "image"), ("residual (refit - target)", image - 0.5, "residual")]
    boxes = ((2, 3, 4, 4), (8, 10, 4, 4))
    with pytest.MonkeyPatch.context() as mp:
        mp.setattr(plt.Figure, "savefig", savefig)
        plot._grid(str(tmp_path / "fit.png"), columns, 1, [], "--plot", boxes=boxes)
    assert ("residual (refit - target); 2 fitted tiles outlined", 2) in drawn
    assert ("target", 0) in drawn
    assert (tmp_path / "fit.png").exists()
