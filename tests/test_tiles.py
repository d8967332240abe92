"""Fits on informative tiles (`jaxdof/_fit/tiles.py`): the mosaic's interiors are exactly the
whole frame's render, the choice, the fit on tiles, and the option's checks."""

import dataclasses
import math

import numpy as np
import pytest

import jaxdof
from jaxdof import LocalOcclusion
from jaxdof._fit import select, tiles as T
from jaxdof._fit.prepare import prepare_problem
from jaxdof._scene import OCCLUSION_METHOD

from .helpers import EXACT


F, PITCH = 0.05, 4e-5
TRUTH = jaxdof.ThinLens(F, 2.0, 2.0, PITCH)
S = 128


def scene(size=S, seed=0):
    rng = np.random.default_rng(seed)
    image = rng.uniform(0.2, 0.8, size=(size, size))
    image = 0.5 * image + 0.125 * sum(np.roll(image, k, a) for k in (1, -1) for a in (0, 1))
    yy, xx = np.mgrid[0:size, 0:size]
    depth = 1.2 + 2.0 * yy / (size - 1) + 0.3 * np.sin(xx / 9.0)
    return image, depth, rng


def test_mosaic_interiors_are_the_whole_frame_render():
    """Every interior pixel of the mosaic renders exactly as in the whole frame: light from a
    neighbour in the mosaic reaches only its halo (the window's reach), which has weight 0."""
    image, depth, _ = scene()
    window = 4.0
    photo = np.asarray(jaxdof.render(image, depth, TRUTH, max_radius=window))
    model = jaxdof.DefocusModel()
    p = prepare_problem(image, depth, photo, TRUTH, None, model, ("f_number",), ())
    halo = model.border_band(window)
    tiles = T.Tiles(((4, 4), (4, 68), (60, 36), (92, 92)), 32, halo, (S, S))
    q = T.tiled_problem(p, tiles)
    mosaic = np.asarray(jaxdof.render(q.image, q.depth, TRUTH, max_radius=window))
    crop = 32 + 2 * halo
    inside = q.sqrt_w[0] > 0
    assert inside.sum() == 4 * 32 * 32
    for i, (r, c) in enumerate(tiles.corners):
        rr, cc = divmod(i, tiles.cols)
        got = mosaic[
            rr * crop + halo : rr * crop + halo + 32, cc * crop + halo : cc * crop + halo + 32
        ]
        np.testing.assert_allclose(got, photo[r : r + 32, c : c + 32], rtol=0, atol=1e-12)
        np.testing.assert_array_equal(
            q.targets[
                0,
                rr * crop + halo : rr * crop + halo + 32,
                cc * crop + halo : cc * crop + halo + 32,
            ],
            photo[r : r + 32, c : c + 32],
        )


def test_choice_follows_information_and_avoids_depth_edges():
    """Pixels of weight 0 (the left half: saturated, say) carry no information about the lens and
    a depth step is an edge the soft model cannot explain: the chosen tiles avoid both."""
    image, depth, _ = scene()
    depth[96:, :] = 6.0  # a depth step at row 96
    weight = np.ones((S, S))
    weight[:, : S // 2] = 0
    photo = np.asarray(jaxdof.render(image, depth, TRUTH, max_radius=4.0))
    model = jaxdof.DefocusModel()
    free = ("f_number", "focus_distance")
    p = prepare_problem(image, depth, photo, TRUTH, weight, model, free, ())
    rows = np.asarray(p.b)[None]
    # Candidates: rows 4, 36, 68 x columns 4, 36, 68 (32 px, halo 4); of these (4, 68) and
    # (36, 68) lie wholly in the weighted half and clear of the step.
    # A model that renders occlusion avoids the edge too (it guesses the hidden surfaces), and then
    # the tiles hold no edge: `fit_lens` fits them with the soft filter.
    occluding = jaxdof.DefocusModel(method=LocalOcclusion())
    for m in (model, occluding):
        info = lambda m=m: T.pixel_information(p, m, rows)  # noqa: E731
        chosen = T.choose_tiles(p, m, 4.0, 2 * 32 * 32, info)
        assert chosen is not None and len(chosen.corners) == 2
        for r, c in chosen.corners:
            assert c >= S // 2  # where the weights are
            assert r + 32 + chosen.halo <= 96  # clear of the depth step
        assert T.edge_free(p, chosen)
    across = T.Tiles(((68, 68), (4, 68)), 32, chosen.halo, (S, S))  # the first crop holds row 96
    assert not T.edge_free(p, across)


def test_occlusion_is_tried_only_where_the_tiles_can_see_an_edge():
    """The photo's say tries the occlusion render on a fit on tiles only where a depth edge lies
    within twice the fitted window of a tile (elsewhere it renders exactly the soft image), crops
    clipped to the frame; on the whole frame wherever the depth map has an edge."""
    image, depth, _ = scene()
    depth[96:, :] = 6.0  # a depth step at row 96
    # (An image pixel per photo pixel; `ratio` 2: the same step at row 48 of a photo half the size.)
    assert T.edges_near(depth, 1, [(62, 4)], 32, 4) and not T.edges_near(depth, 1, [(4, 4)], 32, 4)
    assert T.edges_near(depth, 2, [(31, 2)], 16, 2) and not T.edges_near(depth, 2, [(2, 2)], 16, 2)
    assert not T.edges_near(depth, 1, [(0, 0)], 32, 50)  # rows 0-82 (clipped at 0): clear
    assert T.edges_near(depth, 1, [(0, 0)], 32, 66)  # rows 0-98: the step
    # (A result to hold the treatment, the window and the tiles: a small fit will do. Its inputs
    # read-only: `fit_lens` uses the caller's arrays without copies and must never write to them.)
    small = (image[:40, :40].copy(), depth[:40, :40].copy())
    photo = np.asarray(jaxdof.render(*small, TRUTH, max_radius=4.0)).copy()
    for x in (*small, photo):
        x.flags.writeable = False
    fit = jaxdof.fit_lens(*small, photo, TRUTH, tiles=None, starts=1, pyramid=1, **EXACT)
    t = dataclasses.replace(fit.treatment, occlusion=False, footprint=False)
    call = {"depth": depth, "method": None, "footprint": None}
    assert select.alternatives(dataclasses.replace(fit, treatment=t), call) == [
        ("occlusion on", {"method": OCCLUSION_METHOD})
    ]
    window = float(fit.max_radius)
    for r, seen in ((4, False), (96 - 32 - 2 * math.ceil(window), True)):
        on_tiles = dataclasses.replace(fit, treatment=t, tiles=((r, 64, 32, 32),))
        assert bool(select.alternatives(on_tiles, call)) == seen, r


class _Stages:
    """A `verbose` callable that only records the stages `fit_lens` announces."""

    def __init__(self):
        self.seen = []

    def __call__(self, **kwargs):
        pass

    def stage(self, text):
        self.seen.append(text)


def _fit_on_tiles(pyramid):
    image, depth, rng = scene()
    photo = np.asarray(jaxdof.render(image, depth, TRUTH)) + 0.003 * rng.standard_normal((S, S))
    init = jaxdof.ThinLens(F, 3.0, 1.6, PITCH)
    stages = _Stages()
    res = jaxdof.fit_lens(
        image, depth, photo, init, tiles=4 * 32 * 32, verbose=stages, pyramid=pyramid, **EXACT
    )
    assert stages.seen[0] == f"choosing tiles: {4 * 32 * 32} of {S * S} photo pixels"
    # With a scout (pyramid=2: the photo halved) the starts are solved there and the tiles
    # chosen at its solution; without (this photo is small enough) at the init.
    assert res.levels == (2 if pyramid == 2 else 1)
    assert res.status in (jaxdof.RESULTS.successful, jaxdof.RESULTS.inconsistent), res.message
    # Tiles of at least 32 px and twice the final window's reach (refitted with a larger window
    # when the first one turns out too small), within the budget, inside the frame.
    boxes = np.array(res.tiles)
    assert len(boxes) >= 1 and int(res.pixels_used) == int(np.sum(boxes[:, 2] * boxes[:, 3]))
    assert int(res.pixels_used) <= 4 * 32 * 32 and np.all(boxes[:, 2] >= 2 * res.max_radius)
    assert np.all(boxes[:, :2] >= res.max_radius) and np.all(boxes[:, :2] + boxes[:, 2:] <= S)
    assert f"fitted on {len(boxes)} tiles" in res.message
    assert res.to_dict()["tiles"] == boxes.tolist()
    for name in ("f_number", "focus_distance"):
        err = abs(float(getattr(res.lens, name)) - float(getattr(TRUTH, name)))
        assert err <= 3 * float(res.stderr[name]), (name, err, float(res.stderr[name]))
    return res


def test_fit_on_tiles_with_a_scout_recovers_the_lens():
    res = _fit_on_tiles(pyramid=2)
    # Given an earlier fit's tiles, a fit is on the same pixels (how the photo's say compares
    # its alternatives with the fit they would replace: `select.same_pixels`)
    image, depth, rng = scene()
    photo = np.asarray(jaxdof.render(image, depth, TRUTH)) + 0.003 * rng.standard_normal((S, S))
    assert select.same_pixels(res)["tiles"] == res.tiles
    again = jaxdof.fit_lens(image, depth, photo, res.lens, tiles=res.tiles, starts=1, **EXACT)
    assert again.tiles == res.tiles and int(again.pixels_used) == int(res.pixels_used)


def test_fit_on_tiles_chosen_at_the_init_recovers_the_lens():
    _fit_on_tiles(pyramid=None)


def test_scout_factor():
    """The scout's reduction: the least that brings the longer side to `SCOUT_SIDE`, unless the
    starts' circles (>= 1 px) or the shorter side (>= 24 px) stop it earlier; `pyramid` sets it."""
    assert T.scout_factor((1000, 1500), 24.0, None) == 4  # 250 x 375
    assert T.scout_factor((4000, 6000), 40.0, None) == 16  # 250 x 375
    assert T.scout_factor((4000, 6000), 3.0, None) == 2  # circles of 1.5 px at q = 2
    assert T.scout_factor((4000, 6000), 1.5, None) == 1
    assert T.scout_factor((400, 500), 24.0, None) == 1  # small enough already
    assert T.scout_factor((40, 6000), 40.0, None) == 1  # the shorter side stops it
    assert T.scout_factor((4000, 6000), 40.0, 3) == 4


def test_tiles_option():
    assert T.use_tiles("auto", (100, 100)) is None  # small photos: the whole frame
    assert T.use_tiles("auto", (2000, 1000)) == T.BUDGET
    assert T.use_tiles(None, (5000, 5000)) is None and T.use_tiles(False, (5000, 5000)) is None
    assert T.use_tiles(5000, (10, 10)) == 5000
    # an earlier fit's tiles (`FitResult.tiles`): their interiors' pixels; `()` the whole frame
    assert T.use_tiles(((40, 40, 32, 32), (40, 72, 32, 32)), (200, 200)) == 2 * 32 * 32
    assert T.use_tiles((), (5000, 5000)) is None
    # their halos are the window's reach; where one would leave the frame they are not used
    model = jaxdof.DefocusModel()
    given = T.given_tiles((200, 200), model, 8.0, ((20, 20, 32, 32),))
    assert given == T.Tiles(((20, 20),), 32, int(model.border_band(8.0)), (200, 200))
    assert T.given_tiles((200, 200), model, 16.0, ((10, 20, 32, 32),)) is None
    for bad in (((1, 2, 3),), ((1, 2, 8, 9),), ((1, 2, 8, 8), (3, 4, 16, 16))):
        with pytest.raises(ValueError, match="tiles"):
            T.use_tiles(bad, (100, 100))
    for bad in ("yes", 0, -3, 1.5, True):
        with pytest.raises(ValueError, match="tiles must be"):
            T.use_tiles(bad, (10, 10))
