"""`jaxdof chart` and `jaxdof calibrate`, in-process through `jaxdof._cli.main` on small files:
the files written, the refusals (one line, exit status 2), and a photo without the chart
refused before anything is compiled."""

import json
import time

import imageio.v3 as iio
import numpy as np
import pytest

import jaxdof
from jaxdof._cli import main


@pytest.fixture(scope="module")
def sidecar(tmp_path_factory):
    d = tmp_path_factory.mktemp("chart")
    assert main(["chart", str(d / "c"), "--dpi", "40", "--seed", "3"]) == 0
    return d / "c.json"


def test_chart_writes_files(sidecar, capsys):
    d = sidecar.parent
    assert {p.name for p in d.iterdir()} >= {"c.png", "c.pdf", "c.json"}
    side = json.loads(sidecar.read_text())
    assert side["seed"] == 3 and side["dpi"] == 40 and side["png"] == "c.png"
    assert len(side["frame"]) == 4 and side["frame_width_m"] > 0  # the dark frame's outline
    chart, raster = jaxdof.read_chart(sidecar)
    again, raster2 = jaxdof.make_chart(dpi=40, seed=3)
    assert np.array_equal(raster, raster2) and chart.markers.keys() == again.markers.keys()


def test_chart_refusals(sidecar, tmp_path, capsys):
    stem = str(sidecar.with_suffix(""))
    assert main(["chart", stem, "--dpi", "40", "--seed", "3"]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and "exists; pass overwrite=True" in err
    assert main(["chart", str(tmp_path / "m"), "--monitor"]) == 2
    assert "--monitor needs --screen-px" in capsys.readouterr().err
    assert main(["chart", str(tmp_path / "s"), "--size", "100x80mm", "--dpi", "10"]) == 2
    assert "markers of" in capsys.readouterr().err
    args = ["chart", str(tmp_path / "m"), "--monitor", "--screen-px", "640x360"]
    assert main([*args, "--screen-width", "0.3m"]) == 0
    assert (tmp_path / "m.png").exists() and not (tmp_path / "m.pdf").exists()
    assert main(["chart", str(tmp_path / "l"), "--paper", "letter", "--dpi", "30"]) == 0
    assert jaxdof.read_chart(tmp_path / "l.json")[0].width_m == pytest.approx(0.2794, abs=1e-3)


def test_calibrate_without_the_chart(sidecar, tmp_path, capsys):
    """A photo without the chart: one line, exit status 2, within seconds (no compile)."""
    photo = tmp_path / "noise.png"
    iio.imwrite(photo, np.random.default_rng(0).integers(0, 255, (240, 320), dtype=np.uint8))
    t0 = time.perf_counter()
    assert main(["calibrate", str(photo), "--chart", str(sidecar), "--quiet"]) == 2
    assert time.perf_counter() - t0 < 10
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and "noise.png: no chart found" in err


def test_calibrate_bad_sidecar(sidecar, tmp_path, capsys):
    bad = tmp_path / "bad.json"
    bad.write_text("{}")
    photo = tmp_path / "p.png"
    iio.imwrite(photo, np.zeros((32, 32), np.uint8))
    assert main(["calibrate", str(photo), "--chart", str(bad)]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and "not a jaxdof chart sidecar" in err


def test_calibrate_another_charts_photo(sidecar, tmp_path, capsys):
    """A photo of another chart (another seed: other marker ids): refused in one line."""
    chart, raster = jaxdof.make_chart(dpi=40, seed=4)
    photo = tmp_path / "other.png"
    codes = np.round(jaxdof._io.linear_to_srgb(raster) * 255).astype(np.uint8)
    iio.imwrite(photo, np.pad(codes, 20, constant_values=128))
    assert main(["calibrate", str(photo), "--chart", str(sidecar), "--quiet"]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and "of this chart's" in err and "sidecar" in err


def test_help():
    for command in ("chart", "calibrate"):
        with pytest.raises(SystemExit):
            jaxdof._cli.parse.build_parser().parse_args([command, "--help"])


@pytest.mark.slow  # 439 s on a shared 2-core machine with two studies beside it
def test_calibrate_a_camera_jpeg(sidecar, tmp_path, capsys):
    """A camera JPEG (4:2:0, quality 95) of the chart tilted 35 degrees through f/2 focused at
    0.5 m, 320 x 240: `jaxdof calibrate --json` exits 0 with the lens (focus distance within
    2 %, blur scale within 5 %), compares the luma (the file's subsampling), aligns the chart
    again with the fitted blur, and writes the figure."""
    from PIL import Image

    from jaxdof._chart._geometry import camera_matrix

    chart, raster = jaxdof.read_chart(sidecar)
    shape, f_px, focal = (240, 320), 380.0, 0.025
    a, b = np.radians(15), np.radians(35)
    rx = np.array([[1, 0, 0], [0, np.cos(a), -np.sin(a)], [0, np.sin(a), np.cos(a)]])
    ry = np.array([[np.cos(b), 0, np.sin(b)], [0, 1, 0], [-np.sin(b), 0, np.cos(b)]])
    r = ry @ rx
    centre = np.array([chart.width_m / 2, chart.height_m / 2, 0])
    pose = jaxdof.ChartPose(r, np.array([0, 0, 0.45]) - r @ centre)
    sharp, depth = jaxdof.chart_scene(chart, raster, pose, camera_matrix(f_px, shape), shape)
    s = focal * 0.5 / (0.5 - focal)
    truth = jaxdof.ThinLens(focal, 2.0, 0.5, s / f_px)
    photo = np.asarray(jaxdof.render(sharp, jaxdof.fill_depth_holes(depth), truth))
    rgb = np.stack([photo * 0.9, photo * 0.8, photo * 0.7], axis=-1)  # a warm light
    codes = np.round(np.clip(jaxdof._io.linear_to_srgb(rgb), 0, 1) * 255).astype(np.uint8)
    path = tmp_path / "photo.jpg"
    Image.fromarray(codes).save(path, quality=95, subsampling=2)
    args = ["calibrate", str(path), "--chart", str(sidecar), "--json", "--quiet"]
    args += ["--focal-length", "25mm", "--sensor-width", f"{s / f_px * 320 * 1000:.6f}mm"]
    assert main([*args, "--plot", str(tmp_path / "fit.png")]) == 0
    out = json.loads(capsys.readouterr().out)
    lens = out["lenses"][0]
    assert lens["focus_distance"] == pytest.approx(0.5, rel=0.02)
    k = jaxdof.ThinLens(
        *(lens[n] for n in ("focal_length", "f_number", "focus_distance", "pixel_pitch"))
    )
    assert float(k.blur_scale) == pytest.approx(float(truth.blur_scale), rel=0.05)
    assert out["nuisances"]["luma"]["fitted"]
    assert len(out["chart"]["aligned_px"]) == 1
    assert (tmp_path / "fit.png").stat().st_size > 0
