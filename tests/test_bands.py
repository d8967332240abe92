"""`jaxdof.render(..., band_rows=...)`: a frame rendered in bands of rows, each with the halo that
makes it exact, gives the whole frame's pixels; and `jaxdof.internal.estimate_memory`.

The frames are small (29 rows: bands of 4, 5 and 7 rows do not divide them) and float64, where
the bands are bitwise equal to the whole frame for every method but those whose scatter adds in
an order that depends on the frame (`Aperture`'s splats, a polygon's overlap: within 1e-15).
Each band shape compiles once (`_render._filter_jit`), so a case costs about two compilations.
"""

import json
import os
import subprocess
import sys

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jaxdof
from jaxdof._render import _circles, _filter, band_halo, band_starts
from jaxdof.internal import estimate_memory, tuning

from .helpers import CATALOGUE, method_id


H, W = 29, 23


def _scene(h: int = H, w: int = W, dtype=np.float64):
    """A random RGB image and a smooth depth map of 1-5 m."""
    rng = np.random.default_rng(0)
    image = rng.uniform(size=(h, w, 3)).astype(dtype)
    yy, xx = np.mgrid[0:h, 0:w]
    depth = (1.0 + 4.0 * (0.5 + 0.5 * np.sin(xx / 5.0 + yy / 7.0))).astype(dtype)
    return image, depth


def _lens(sensor_width: float, width: int = W) -> jaxdof.ThinLens:
    """50 mm f/1.4 focused at 2 m; the sensor width sets the circles: 4 mm over 23 px, up to
    2.6 px; 2 mm, up to 5.3 px (a halo of 7 rows, a quarter of the frame)."""
    return jaxdof.ThinLens.from_sensor(0.05, 1.4, 2.0, sensor_width=sensor_width, image_width=width)


SMALL, LARGE = 0.004, 0.002  # sensor widths: circles up to 2.6 and 5.3 px


# ---------------------------------------------------------------------------------------------
# The layout of the bands


@pytest.mark.parametrize("rows, band", [(29, 4), (29, 7), (29, 29), (29, 40), (1, 1), (30, 5)])
def test_bands_cover_every_row_once_or_twice(rows, band):
    """Every row is in a band; bands are `band` high (the last moved up to end at the bottom, so
    at most two band shapes), the whole frame when `band` covers it."""
    starts = band_starts(rows, band)
    covered = np.zeros(rows, int)
    for a in starts:
        covered[a : min(a + band, rows)] += 1
    assert covered.min() >= 1 and covered.max() <= 2
    assert starts == sorted(starts) and starts[0] == 0
    assert starts[-1] == max(rows - band, 0)
    if band >= rows:
        assert starts == [0]


def test_halo():
    """`ceil(s R) + 1` input rows (+1 with the footprint correction), a multiple of `s`."""
    assert band_halo(2.5) == 4  # ceil(2.5) + 1
    assert band_halo(3.0) == 4  # an integer radius reaches 3 rows; one more for a splat
    assert band_halo(0.0) == 1
    assert band_halo(2.5, footprint=True) == 6  # its stencils read 2 more rows
    assert band_halo(2.5, downsample=2) == 6  # ceil(5) + 1 = 6, a multiple of 2
    assert band_halo(2.5, downsample=2, footprint=True) == 8  # ceil(5) + 1 + 2


# ---------------------------------------------------------------------------------------------
# The same pixels


def _both(method, lens, band_rows, **options):
    image, depth = _scene()
    whole = np.asarray(jaxdof.render(image, depth, lens, method=method, **options))
    banded = np.asarray(
        jaxdof.render(image, depth, lens, method=method, band_rows=band_rows, **options)
    )
    return whole, banded


@pytest.mark.parametrize("band_rows", [4, 7])
def test_soft_bands_are_the_whole_frame(band_rows):
    """The default method, circles reaching a quarter of the frame, `normalize` (the frame's
    edges are the bands' edges only at the top and bottom): bitwise the whole frame."""
    whole, banded = _both("soft", _lens(LARGE), band_rows, normalize=True)
    assert banded.shape == whole.shape == (H, W, 3)
    np.testing.assert_array_equal(banded, whole)


_WHOLE_FRAME = ("jitter", "occlusion", "local_occlusion")  # refused in bands (test_refusals)
_BANDED = [m for name, m in CATALOGUE.items() if name not in _WHOLE_FRAME]


# `Auto` at the larger window only: it runs the methods tested at both (150 s of compiling each).
_CASES = [
    pytest.param(method, width, id=f"{label}-{method_id(method)}")
    for width, label in ((SMALL, "r2.6"), (LARGE, "r5.3"))
    for method in (*_BANDED, jaxdof.Soft(blades=6))
    if not (isinstance(method, jaxdof.Auto) and width == SMALL)
]


@pytest.mark.slow
@pytest.mark.parametrize("method, sensor_width", _CASES)
def test_every_method_in_bands(method, sensor_width):
    """Every method that can run in bands, two window sizes, bands of 5 rows (29 = 5 * 5 + 4):
    the whole frame's pixels. `Auto` and `Layered` prepare on the whole frame's circles (their
    levels cut to each band). Bitwise, but for the scatters whose additions run in an order set
    by the frame's size (`Aperture`'s splats, the polygon's overlap): float64 rounding, 1e-15
    on pixels of about 1 (a few ulps)."""
    if isinstance(method, jaxdof.Auto):
        whole, banded = _auto_both(_lens(sensor_width), 5)
    else:
        whole, banded = _both(method, _lens(sensor_width), 5)
    np.testing.assert_allclose(banded, whole, rtol=0, atol=4e-15)


def _auto_both(lens, band_rows):
    """`render(method="auto")` renders this scene (the smooth depth in terraces: a depth edge
    every few pixels) with `LocalOcclusion` on the whole frame, which bands cannot
    (`test_treatment`), so in bands it renders the filter-level `Auto` with the footprint
    correction: the whole frame's pixels of that are `_filter`'s, the whole-frame render after
    the scene's choice."""
    image, depth = _scene()
    depth = np.round(depth * 2) / 2  # terraces half a metre apart (a smooth depth has no edge)
    t = jaxdof.scene_treatment(depth, lens)
    assert t.occlusion and t.footprint
    radius = _circles(jnp.asarray(image), jnp.asarray(depth), lens, 1)
    options = dict(window=None, normalize=False, footprint=True, s=1)
    whole = np.asarray(
        _filter(jnp.asarray(image), jnp.asarray(depth), radius, method=jaxdof.Auto(), **options)
    )
    banded = np.asarray(jaxdof.render(image, depth, lens, method="auto", band_rows=band_rows))
    return whole, banded


@pytest.mark.slow  # ~10 s of compiling on 2 cores
def test_bands_with_downsample_footprint_and_a_window():
    """`downsample=2` (bands of photo rows, halos a multiple of 2), the footprint correction (its
    stencils read two rows more) and `normalize`; and a given `max_radius` below the largest
    circle (the window, not the circles, sets the halo). Within an ulp of the whole frame (one
    rounding apart where the compiled band fuses the footprint's or the block means' arithmetic
    differently from the whole frame's eager call: 1.1e-16 seen)."""
    image, depth = _scene(2 * 15, 2 * 11)
    lens = _lens(LARGE, 11)
    options = dict(downsample=2, footprint=True, normalize=True)
    whole = np.asarray(jaxdof.render(image, depth, lens, **options))
    banded = np.asarray(jaxdof.render(image, depth, lens, band_rows=4, **options))
    assert whole.shape == banded.shape == (15, 11, 3)
    np.testing.assert_allclose(banded, whole, rtol=0, atol=4.5e-16)  # 2 ulps at 1
    image, depth = _scene()
    lens = _lens(LARGE)
    whole = np.asarray(jaxdof.render(image, depth, lens, max_radius=2.0))
    banded = np.asarray(jaxdof.render(image, depth, lens, max_radius=2.0, band_rows=6))
    np.testing.assert_array_equal(banded, whole)


@pytest.mark.slow  # ~10 s of compiling on 2 cores
def test_float32_bands():
    """float32 arrays (the CLI's): the same pixels within an ulp (1.2e-7 at 1, seen with the
    footprint correction and `downsample`; exact without)."""
    image, depth = _scene(dtype=np.float32)
    lens = _lens(LARGE)
    whole = np.asarray(jaxdof.render(image, depth, lens))
    banded = np.asarray(jaxdof.render(image, depth, lens, band_rows=6))
    assert banded.dtype == np.float32
    np.testing.assert_allclose(banded, whole, rtol=0, atol=2.4e-7)


def test_bands_of_the_frame_or_more_are_the_whole_frame_also_under_jit():
    """`band_rows` at least the frame's height is the whole-frame render, which runs under jit."""
    image, depth = _scene()
    lens = _lens(SMALL)
    whole = jax.jit(lambda im, z: jaxdof.render(im, z, lens, max_radius=3.0))
    fn = jax.jit(lambda im, z: jaxdof.render(im, z, lens, max_radius=3.0, band_rows=H))
    np.testing.assert_array_equal(np.asarray(fn(image, depth)), np.asarray(whole(image, depth)))


def test_refusals():
    """`ValueError`s that say why and what to do: a method that decides from the whole frame
    (depth layers, per-pixel random patterns), traced inputs, a band height that is not an int
    `>= 1`."""
    image, depth = _scene()
    lens = _lens(SMALL)
    for method in (CATALOGUE[name] for name in _WHOLE_FRAME):
        with pytest.raises(ValueError, match="whole frame"):
            jaxdof.render(image, depth, lens, method=method, band_rows=5)
    with pytest.raises(ValueError, match="concrete inputs"):
        jax.jit(lambda z: jaxdof.render(image, z, lens, max_radius=3.0, band_rows=5))(depth)
    for bad in (0, -3, True):  # (a float or a string: the annotation, checked in the tests)
        with pytest.raises(ValueError, match="band_rows"):
            jaxdof.render(image, depth, lens, band_rows=bad)
    close = depth.copy()
    close[20, 3] = 0.01  # in a band other than the first: checked on the whole frame first
    with pytest.raises(ValueError, match="depth must be beyond"):
        jaxdof.render(image, close, lens, band_rows=5)


def test_band_progress_is_logged(caplog):
    """Each band done is a DEBUG record on the `"jaxdof"` logger with `record.band = (done, of)`
    (the CLI's progress display reads it)."""
    image, depth = _scene()
    with caplog.at_level("DEBUG", logger="jaxdof"):
        jaxdof.render(image, depth, _lens(SMALL), band_rows=10)
    bands = [r.band for r in caplog.records if hasattr(r, "band")]
    assert bands == [(1, 3), (2, 3), (3, 3)]


# ---------------------------------------------------------------------------------------------
# The memory estimate


def test_estimate_memory_follows_its_table():
    """The estimate: the table's fixed bytes plus bytes per pixel filtered at once; a band's is
    its rows with the halo plus what the banded render holds of the frame."""
    table = tuning.RENDER_MEMORY
    shape = (4000, 6000, 3)
    whole = estimate_memory(shape, 15.0)
    assert whole == int(table["fixed"] + table["per_pixel"]["soft"] * 4000 * 6000)
    band = estimate_memory(shape, 15.0, band_rows=500)
    rows = 500 + 2 * band_halo(15.0)
    per_band = table["band_scale"]["soft"] * table["per_pixel"]["soft"] * rows * 6000
    assert band == int(table["band_fixed"] + per_band + table["band_frame"] * 4000 * 6000)
    assert band < whole
    assert estimate_memory(shape, 15.0, band_rows=4000) == whole  # one band: the whole frame
    # larger frames, more channels, float64, footprint and normalize need more
    assert estimate_memory((100, 100, 3), 15.0) < whole
    assert (
        estimate_memory((4000, 6000), 15.0) < whole < estimate_memory(shape, 15.0, normalize=True)
    )
    assert whole < estimate_memory(shape, 15.0, footprint=True)
    assert estimate_memory(shape, 15.0, dtype=np.float64) - table["fixed"] == pytest.approx(
        2 * (whole - table["fixed"]), abs=2
    )
    # methods: the measured rows, the spans from SPANS_MIN_RADIUS on, the largest for your own
    assert estimate_memory(shape, 15.0, "hard") < whole < estimate_memory(shape, 15.0, "layered")
    assert estimate_memory(shape, tuning.SPANS_MIN_RADIUS, "soft") > whole
    assert estimate_memory(shape, 15.0, _Mine()) == int(
        table["fixed"] + max(table["per_pixel"].values()) * 4000 * 6000
    )
    # a method that prepares on the whole frame keeps its radius map (4 bytes per pixel) in bands
    layered = table["band_scale"]["layered"] * table["per_pixel"]["layered"] * rows * 6000
    held = (table["band_frame"] + 4) * 4000 * 6000
    assert estimate_memory(shape, 15.0, "layered", band_rows=500) == int(
        table["band_fixed"] + layered + held
    )
    with pytest.raises(ValueError, match="downsample"):
        estimate_memory((101, 100, 3), 15.0, downsample=2)


class _Mine(jaxdof.AbstractMethod):
    """A method of one's own (the identity): the estimate takes the table's largest row."""

    differentiable_in_radius = True

    def spread(self, image, radius, *, max_radius, depth):
        return image


_MEASURE = """
import json, sys
import numpy as np
import jaxdof

def status(field):  # kB, from /proc/self/status (Linux)
    with open("/proc/self/status") as fh:
        return next(int(line.split()[1]) for line in fh if line.startswith(field + ":"))

h, w, rows = 2000, 1500, sys.argv[1]
if rows == "none":  # as the CLI: the allocator keeps freed memory for a frame that fits only
    jaxdof.retain_freed_memory()
rng = np.random.default_rng(0)
image = rng.random((h, w, 3), dtype=np.float32)
xx = np.linspace(0, 1, w, dtype=np.float32)[None, :]
yy = np.linspace(0, 1, h, dtype=np.float32)[:, None]
depth = (1.0 + 9.0 * (0.5 + 0.5 * np.sin(6 * xx + 4 * yy))).astype(np.float32)
lens = jaxdof.ThinLens.from_sensor(0.05, 2.8, 2.0, sensor_width=0.036, image_width=w)
before = status("VmRSS")
with open("/proc/self/clear_refs", "w") as fh:  # the peak (VmHWM) from here on
    fh.write("5")
band_rows = None if rows == "none" else int(rows)
jaxdof.render(image, depth, lens, band_rows=band_rows).block_until_ready()
peak = status("VmHWM")
r = float(np.max(np.asarray(jaxdof.coc_radius(depth, lens))))
print(json.dumps({"bytes": (peak - before) * 1024, "radius": r}))
"""


@pytest.mark.slow
@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="reads /proc/self/status")
def test_bands_need_less_memory_as_estimated():
    """Peak resident memory (Linux's `VmHWM`, reset before the call) of one render of a 3 MP RGB
    float32 frame, a fresh process each, with the CLI's allocator setting for each: bands of 100
    rows need under 3/4 of the whole frame's (measured 185 MB against 417 MB), and each stays
    within [0.5, 1.25] of its estimate (0.71 and 0.70 of it measured, 2026-12-07; the table holds
    the largest figures measured, and the peak moves with the allocator by ~10 %)."""
    # XLA's default optimisation level, which users run (not the tests' level 0, conftest.py).
    env = {**os.environ, "JAX_PLATFORMS": "cpu", "XLA_FLAGS": ""}
    measured = {}
    for rows in ("none", "100"):
        out = subprocess.run(
            [sys.executable, "-c", _MEASURE, rows],
            env=env,
            capture_output=True,
            text=True,
            timeout=600,
            check=True,
        )
        measured[rows] = json.loads(out.stdout)
    radius = measured["none"]["radius"]
    assert measured["100"]["bytes"] < 0.75 * measured["none"]["bytes"], measured
    for rows, band_rows in (("none", None), ("100", 100)):
        estimate = estimate_memory((2000, 1500, 3), radius, band_rows=band_rows)
        assert 0.5 * estimate <= measured[rows]["bytes"] <= 1.25 * estimate, (rows, measured)
