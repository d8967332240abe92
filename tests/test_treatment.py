"""`fit_lens`'s automatic treatment of the scene (`jaxdof/_fit/treatment.py`): which rule turns on
what, that each choice can be forced, and that the result and the CLI report it."""

import math

import jax
import numpy as np
import pytest

import jaxdof
from jaxdof import LocalOcclusion, _corrections
from jaxdof._fit.treatment import (
    EDGE_KEEP_MIN,
    FOOTPRINT_BELOW,
    Treatment,
    choose_treatment,
    start_circles,
)


PITCH = 1e-5


def _lens(f_number: float, focus: float) -> np.ndarray:
    return np.array([[0.05, f_number, focus, PITCH]])


def _step(h: int = 48, w: int = 48, near: float = 1.5, far: float = 4.0) -> np.ndarray:
    """A near plane on the left half, a far one on the right: one vertical depth edge."""
    z = np.full((h, w), far)
    z[:, : w // 2] = near
    return z


def _floor(h: int = 48, w: int = 48) -> np.ndarray:
    """A receding floor: depth grows smoothly down the rows (no 3 % step between neighbours)."""
    return np.repeat(np.linspace(1.5, 2.5, h)[:, None], w, axis=1)


def _choose(depth, rows, **forced):
    fitted = np.ones(depth.shape, bool)
    opts = dict(occlusion=None, footprint=None, edge_weight=None) | forced
    return choose_treatment(depth, rows, fitted, 1, **opts)


def test_start_circles_match_coc_radius():
    z = np.array([[1.0, 2.0, np.inf]])
    for focus in (1.8, math.inf):
        lens = jaxdof.ThinLens(0.05, 2.0, focus, PITCH)
        want = np.asarray(jaxdof.coc_radius(z, lens), np.float64)
        got = start_circles(_lens(2.0, focus), z)
        np.testing.assert_allclose(got, want, rtol=1e-5)


def test_a_scene_without_depth_edges_gets_neither_occlusion_nor_edge_weight():
    t, weight = _choose(_floor(), _lens(2.0, 2.0))
    assert (t.occlusion, t.edge_pixels, t.edge_weight, weight) == (False, 0, 0.0, None)


def test_a_depth_edge_with_blur_turns_on_occlusion_and_the_edge_weight():
    z = _step()
    rows = _lens(16.0, 1.5)  # the near plane sharp, the far one blurred
    r_far = float(start_circles(rows, np.array([4.0]))[0])
    assert 3 < r_far < 4
    t, weight = _choose(z, rows)
    assert t.occlusion and t.edge_pixels == 2 * z.shape[0]
    assert t.edge_weight == pytest.approx(r_far + 1.0, rel=1e-5)
    # the weight ramps from 0 on the edge to 1 one width away
    assert weight[0, 23] == 0 and weight[0, 24] == 0
    assert 0 < weight[0, 25] < weight[0, 26] < 1
    assert weight[0, 24 + math.ceil(t.edge_weight)] == 1 and weight[0, 0] == 1
    assert "occlusion (96 edge pixels)" in str(t)


def test_an_edge_in_the_dead_zone_does_not_matter():
    # f/128 focused between the planes: every circle under half a pixel
    rows = _lens(128.0, 2.0)
    assert start_circles(rows, _step()).max() < 0.5
    t, weight = _choose(_step(), rows)
    assert not t.occlusion and t.edge_pixels == 0 and weight is None


def test_footprint_follows_the_median_circle():
    z = _floor()
    small = _choose(z, _lens(4.0, 2.0))[0]
    assert small.median_circle < FOOTPRINT_BELOW and small.footprint
    large = _choose(z, _lens(1.0, 0.5))[0]
    assert large.median_circle > FOOTPRINT_BELOW and not large.footprint


def test_the_edge_weight_is_dropped_where_the_edges_are_the_scene():
    # stripes of alternating depth every 4 px: the edge weight would leave almost nothing
    z = np.where((np.arange(48) // 4) % 2 == 0, 1.5, 4.0)[None, :].repeat(48, 0)
    t, weight = _choose(z, _lens(8.0, 1.5))
    assert t.occlusion and weight is None and t.edge_weight == 0
    forced, w = _choose(z, _lens(8.0, 1.5), edge_weight=True)
    assert w is not None and w.mean() < EDGE_KEEP_MIN and forced.forced == ("edge_weight",)


def test_every_choice_can_be_forced():
    t, weight = _choose(_step(), _lens(8.0, 1.5), occlusion=False, footprint=False, edge_weight=3.0)
    assert not t.occlusion and not t.footprint and t.edge_weight == 3.0
    assert t.forced == ("occlusion", "footprint", "edge_weight")
    assert "(forced: occlusion, footprint, edge_weight)" in str(t)


def _scene(h: int = 40, w: int = 40):
    """A texture on a plane slanted from 1 to 3 m, with a card at 1.2 m in one quadrant."""
    rng = np.random.default_rng(0)
    image = rng.uniform(0.2, 0.8, (h, w)).astype(np.float32)
    yy, xx = np.mgrid[0:h, 0:w]
    depth = np.where((yy < h // 3) & (xx > w // 2), 1.2, 1.0 + 2.0 * xx / (w - 1))
    return image, depth.astype(np.float32)


def rel_err(fit, true):
    return [
        abs(float(getattr(fit, n)) / float(getattr(true, n)) - 1)
        for n in ("f_number", "focus_distance")
    ]


def test_fit_lens_reports_and_obeys_its_treatment():
    image, depth = _scene()
    truth = jaxdof.ThinLens(0.05, 16.0, 1.6, PITCH)  # circles up to 3 px
    photo = jaxdof.render(image, depth, truth, method=LocalOcclusion(), footprint=True)
    init = jaxdof.ThinLens(0.05, 20.0, 1.4, PITCH)
    auto = jaxdof.fit_lens(image, depth, photo, init, starts=1)
    assert isinstance(auto.treatment, Treatment)
    assert auto.treatment.method == "local_occlusion" and auto.treatment.edge_weight > 0
    assert auto.treatment.footprint and bool(auto.success), auto.message
    err = rel_err(auto.lens, truth)
    assert max(err) < 1e-3, err
    assert auto.treatment.border == auto.border and auto.treatment.forced == ()
    assert auto.to_dict()["treatment"]["text"] == str(auto.treatment)
    forced = jaxdof.fit_lens(
        image, depth, photo, init, starts=1, method="soft", footprint=False, edge_weight=False
    )
    t = forced.treatment
    assert (t.method, t.footprint, t.edge_weight) == ("soft", False, 0.0)
    assert int(forced.pixels_used) > int(auto.pixels_used)  # no pixel weighted out near the edge


def test_fit_lens_refuses_a_bad_edge_weight():
    image, depth = _scene()
    lens = jaxdof.ThinLens(0.05, 2.0, 1.5, PITCH)
    for bad in (0.0, -1.0, math.inf):
        with pytest.raises(ValueError, match="edge_weight"):
            jaxdof.fit_lens(image, depth, image, lens, edge_weight=bad)


def test_edge_distance_is_exact():
    """The capped Euclidean distance to the nearest edge pixel, against brute force (a few
    edges) and scipy's exact transform (a large hole: distances to hundreds of pixels, which
    the float32 transform holds to rounding)."""
    from scipy import ndimage

    rng = np.random.default_rng(0)
    edges = rng.uniform(size=(120, 50)) < 0.003
    whole = _corrections.edge_distance_to(edges, limit=9.0)
    assert whole.dtype == np.float32
    brute = np.full(edges.shape, 9.0)
    for y, x in zip(*np.nonzero(edges)):
        yy, xx = np.mgrid[0:120, 0:50]
        brute = np.minimum(brute, np.hypot(yy - y, xx - x))
    np.testing.assert_allclose(whole, brute, rtol=1e-6)
    holes = np.ones((700, 900), bool)
    holes[100:650, 50:800] = rng.uniform(size=(550, 750)) < 1e-4
    exact = np.minimum(ndimage.distance_transform_edt(~holes), 400.0)
    np.testing.assert_allclose(_corrections.edge_distance_to(holes, limit=400.0), exact, rtol=1e-6)


def test_render_auto_models_what_the_scene_needs(caplog):
    """`render(method="auto")` applies the fit's rules: occlusion and the footprint at a depth
    edge with blur, the footprint alone on a floor, and neither under `jit` (no concrete depth)."""
    image, depth = _scene()
    lens = jaxdof.ThinLens(0.05, 16.0, 1.6, PITCH)  # circles up to 3 px
    t = jaxdof.scene_treatment(depth, lens)
    assert (t.method, t.occlusion, t.footprint) == ("local_occlusion", True, True)
    with caplog.at_level("INFO", logger="jaxdof"):
        auto = jaxdof.render(image, depth, lens, method="auto")
    assert "occlusion (" in caplog.text and "footprint" in caplog.text
    want = jaxdof.render(image, depth, lens, method=LocalOcclusion(), footprint=True)
    np.testing.assert_array_equal(np.asarray(auto), np.asarray(want))
    # forcing the footprint off is obeyed, and said in the treatment
    assert jaxdof.scene_treatment(depth, lens, footprint=False).forced == ("footprint",)
    no_fp = jaxdof.render(image, depth, lens, method="auto", footprint=False)
    want = jaxdof.render(image, depth, lens, method=LocalOcclusion())
    np.testing.assert_array_equal(np.asarray(no_fp), np.asarray(want))
    # a floor: no edge, so the soft numbers (Auto's fastest equivalent) with the footprint
    floor = _floor(40, 40).astype(np.float32)
    t = jaxdof.scene_treatment(floor, lens)
    assert (t.method, t.occlusion, t.footprint) == ("auto", False, True)
    got = jaxdof.render(image, floor, lens, method="auto")
    want = jaxdof.render(image, floor, lens, method="soft", footprint=True)
    np.testing.assert_allclose(np.asarray(got), np.asarray(want), atol=1e-6)  # float32 rounding
    # traced: Auto's fallback, the soft filter without the correction
    traced = jax.jit(lambda d: jaxdof.render(image, d, lens, method="auto", max_radius=4.0))
    want = jaxdof.render(image, depth, lens, method="soft", max_radius=4.0)
    np.testing.assert_allclose(np.asarray(traced(depth)), np.asarray(want), atol=1e-12)


def test_render_auto_in_bands_says_it_leaves_occlusion_out(caplog):
    image, depth = _scene()
    lens = jaxdof.ThinLens(0.05, 16.0, 1.6, PITCH)
    with caplog.at_level("WARNING", logger="jaxdof"):
        got = jaxdof.render(image, depth, lens, method="auto", band_rows=16)
    assert "bands cannot render" in caplog.text
    want = jaxdof.render(image, depth, lens, method="soft", footprint=True)
    np.testing.assert_allclose(np.asarray(got), np.asarray(want), atol=1e-6)  # float32 rounding


def test_depth_holes_are_filled_and_the_pixels_they_reach_left_out():
    """Depth as sensors give it (issue 34): NaN, 0 and negative depths are holes. `fit_lens` fills
    them, leaves the photo pixels within a circle's reach of them out of the fit, reports how
    many, and recovers the lens; `render` refuses them unless `fill_holes=True`; a depth map that
    is all holes is one clear error."""
    rng = np.random.default_rng(0)
    image = rng.uniform(0.05, 1, (32, 40, 3)).astype(np.float32)
    depth = np.linspace(1.0, 5.0, 40, dtype=np.float32)[None].repeat(32, 0)
    truth = jaxdof.ThinLens.from_sensor(0.05, 2.8, 2.5, sensor_width=0.0048, image_width=40)
    photo = jaxdof.render(image, depth, truth)
    holey = depth.copy()
    holey[8:11, 10:13] = np.nan
    holey[20:22, 25:28] = 0.0
    holey[5, 30] = -1.0
    assert jaxdof.depth_holes(holey).sum() == 9 + 6 + 1
    with pytest.raises(ValueError, match="fill_holes=True"):
        jaxdof.render(image, holey, truth)
    filled = jaxdof.fill_depth_holes(holey)
    assert not jaxdof.depth_holes(filled).any()
    assert np.all(filled[~jaxdof.depth_holes(holey)] == holey[~jaxdof.depth_holes(holey)])
    np.testing.assert_array_equal(
        np.asarray(jaxdof.render(image, holey, truth, fill_holes=True)),
        np.asarray(jaxdof.render(image, filled, truth)),
    )
    start = jaxdof.ThinLens.from_sensor(0.05, 4.0, 2.0, sensor_width=0.0048, image_width=40)
    fit = jaxdof.fit_lens(image, holey, photo, start)
    t = fit.treatment
    assert t is not None and t.depth_holes == 16 and t.hole_pixels > 16
    assert "depth holes filled" in str(t)
    assert bool(fit.success), fit.message
    np.testing.assert_allclose(float(fit.lenses.f_number[0]), 2.8, rtol=1e-4)
    np.testing.assert_allclose(float(fit.lenses.focus_distance[0]), 2.5, rtol=1e-4)
    with pytest.raises(ValueError, match="no data"):
        jaxdof.fit_lens(image, np.full_like(depth, np.nan), photo, start)


def test_depth_holes_scattered_over_the_frame_leave_a_quarter():
    """Holes scattered over the whole frame, every pixel within a circle of one: the reach is
    halved until a quarter of the pixels is left, and the fit goes on (no exception)."""
    rng = np.random.default_rng(0)
    image = rng.uniform(0.05, 1, (32, 40, 3)).astype(np.float32)
    depth = np.linspace(1.0, 5.0, 40, dtype=np.float32)[None].repeat(32, 0)
    truth = jaxdof.ThinLens.from_sensor(0.05, 2.8, 2.5, sensor_width=0.0048, image_width=40)
    photo = jaxdof.render(image, depth, truth)
    start = jaxdof.ThinLens.from_sensor(0.05, 4.0, 2.0, sensor_width=0.0048, image_width=40)
    scattered = depth.copy()
    scattered[2::6, 3::7] = np.nan
    fit = jaxdof.fit_lens(image, scattered, photo, start)
    assert fit.treatment is not None and fit.treatment.depth_holes == scattered[2::6, 3::7].size
    assert int(fit.pixels_used) > 0 and bool(fit.success), fit.message
    np.testing.assert_allclose(float(fit.lenses.f_number[0]), 2.8, rtol=0.02)


def test_a_large_hole_keeps_its_full_reach():
    """Depth only on a patch of the frame (a chart: the rest is holes): the photo pixels within
    the circles' reach of the patch's outline are left out at the full reach, since the share
    kept is of the pixels with depth, not of the whole frame."""
    from jaxdof._fit import prepare

    rng = np.random.default_rng(1)
    image = rng.uniform(0.05, 1, (48, 64)).astype(np.float32)
    depth = np.full((48, 64), np.nan, np.float32)
    depth[12:36, 16:48] = np.linspace(1.5, 3.0, 32, dtype=np.float32)[None]
    start = jaxdof.ThinLens.from_sensor(0.05, 2.8, 2.0, sensor_width=0.0048, image_width=64)
    p = prepare.prepare_problem(
        image, depth, image, start, None, jaxdof.DefocusModel(), ("f_number",), (), (), False
    )
    out, left_out, reach = prepare.leave_out_holes(p, 3.0)
    assert reach == 3.0
    inside = np.zeros((48, 64), bool)
    inside[15:33, 19:45] = True  # the patch less 3 px along its outline
    kept = np.asarray(out.sqrt_w)[0] > 0
    assert left_out == int((~kept).sum())  # every pixel was fitted before
    np.testing.assert_array_equal(kept & ~inside, np.zeros_like(kept))
    assert kept[inside].all()


def test_refits_prepare_the_same_arrays_once():
    """Inside `prepared_once` (one `fit_lens` call) a second `prepare_problem` of the same input
    objects with another starting lens reuses the first's arrays (the holes filled, the checks)
    and takes the new lens; the same problem as prepared alone, and no memo outside."""
    from jaxdof._fit import prepare

    rng = np.random.default_rng(2)
    image = rng.uniform(0.05, 1, (24, 32, 3)).astype(np.float32)
    depth = np.tile(np.linspace(1.5, 3.0, 32, dtype=np.float32), (24, 1))
    depth[5:8, 9:12] = np.nan  # a hole: filled once
    lenses = [
        jaxdof.ThinLens.from_sensor(0.05, n, d_f, sensor_width=0.0048, image_width=32)
        for n, d_f in ((2.8, 2.0), (4.0, 2.5))
    ]
    model = jaxdof.DefocusModel()

    def prepared(lens, luma=False):
        args = (image, depth, image, lens, None, model, ("f_number",), (), (), luma)
        return prepare.prepare_problem(*args)

    alone = [prepared(lens) for lens in lenses]
    assert alone[0].depth is not alone[1].depth  # prepared anew each time
    with prepare.prepared_once():
        first, second = (prepared(lens) for lens in lenses)
        grey = prepared(lenses[1], luma=True)
    assert second.depth is first.depth and second.d is first.d and second.targets is first.targets
    assert grey.targets.shape[-1] == 1  # the luma: another set of arrays
    for kept, fresh in zip((first, second), alone):
        np.testing.assert_array_equal(kept.base, fresh.base)
        for name in ("image", "depth", "targets", "sqrt_w", "d"):
            np.testing.assert_array_equal(getattr(kept, name), getattr(fresh, name))
        np.testing.assert_array_equal(kept.holes, fresh.holes)


@pytest.mark.parametrize("n", [8, 24, 64, 200])
def test_depth_edges_are_jumps_not_slopes(n):
    """`depth_edges` (issue 33): no edge on a ramp of any steepness (linear in depth, or a plane:
    linear in inverse depth, as a floor at a grazing angle), nor at a crease where two of them
    meet; an edge at a jump on top of any of them, also one spread over two pixels, and against
    the sky."""
    x = np.arange(n, dtype=np.float64)
    for near, far in ((0.5, 50.0), (1.0, 6.0), (2.0, 2.2), (1.0, 1000.0)):
        lin = np.linspace(near, far, n)
        plane = 1 / np.linspace(1 / near, 1 / far, n)
        for ramp in (lin, plane):
            assert not jaxdof.depth_edges(ramp[None].repeat(5, 0)).any(), (near, far)
            if n < 24 and far / near > 2:
                continue  # depth several times over in 8 px: documented as missed
            jump = np.where(x < n // 2, ramp, 2 * ramp + 0.5)
            edges = jaxdof.depth_edges(jump[None].repeat(5, 0))[0]
            assert edges[n // 2 - 1] and edges[n // 2] and edges.sum() <= 4, (near, far)
    crease = np.where(x < n // 2, 3.0, 3.0 + 0.3 * (x - n // 2))
    assert not jaxdof.depth_edges(crease[None].repeat(5, 0)).any()
    spread = np.where(x < n // 2, 2.0, 4.0)
    spread[n // 2] = 3.0
    assert jaxdof.depth_edges(spread[None].repeat(5, 0))[0, n // 2 - 1 : n // 2 + 2].all()
    sky = np.where(x < n // 2, 3.0, np.inf)
    assert jaxdof.depth_edges(sky[None].repeat(5, 0))[0, n // 2 - 1 : n // 2 + 1].all()
