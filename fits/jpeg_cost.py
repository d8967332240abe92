"""What comparing a camera JPEG in its blocks costs on a fit on tiles (issue 34; speed, issue 37).

Question: on a photo large enough to be fitted on tiles (1.5 MP), how much longer does the default
fit take when it compares a camera JPEG in its 8 x 8 blocks (`jpeg=None`, the default where the
table is found) than pixel by pixel (`jpeg=False`), warm, and which lens does each give?

Method: a synthetic scene (texture at five scales; depth a ramp from 1.5 m to 4.5 m across the
frame), 1024 x 1536 RGB, rendered by `jaxdof.render` at f/2.8 focused at 2.5 m (50 mm, 36 mm
sensor), written as a Pillow JPEG (quality 90, 4:2:0) and decoded to linear light; the default
call from f/4 at 2 m with `jpeg=None` and `jpeg=False`, each compiled once, then `--rounds` warm
calls of each in turns, timed, with the compiled stages of the last round
(`jaxdof.internal.record_stages`). float32.

Run: `python fits/jpeg_cost.py [--rounds 3]`; prints its figures (nothing is written).
"""

from __future__ import annotations

import argparse
import io
import statistics
import time

import jax


jax.config.update("jax_enable_x64", False)  # float32, as a new user calls it

import numpy as np  # noqa: E402
from PIL import Image  # noqa: E402

import jaxdof  # noqa: E402
from jaxdof._io import linear_to_srgb, srgb_to_linear  # noqa: E402
from jaxdof.internal import record_stages  # noqa: E402


H, W = 1024, 1536


def scene():
    rng = np.random.default_rng(0)
    x = np.zeros((H, W, 3))
    for size in (1, 2, 4, 8, 16):
        n = rng.uniform(size=(H // size + 1, W // size + 1, 3))
        x += np.repeat(np.repeat(n, size, 0), size, 1)[:H, :W] / 5
    image = (0.05 + 0.8 * x).astype(np.float32)
    depth = np.broadcast_to(1.5 + 3.0 * np.linspace(0, 1, W)[None, :], (H, W))
    return image, np.ascontiguousarray(depth, np.float32)


def main(args) -> None:
    image, depth = scene()
    lens = dict(sensor_width=0.036, image_width=W)
    truth = jaxdof.ThinLens.from_sensor(0.05, 2.8, 2.5, **lens)
    init = jaxdof.ThinLens.from_sensor(0.05, 4.0, 2.0, **lens)
    photo = np.asarray(jaxdof.render(image, depth, truth))
    code = np.round(255 * linear_to_srgb(np.clip(photo, 0, 1))).astype(np.uint8)
    buf = io.BytesIO()
    Image.fromarray(code).save(buf, "JPEG", quality=90, subsampling=2)
    buf.seek(0)
    decoded = srgb_to_linear(np.asarray(Image.open(buf)) / 255.0).astype(np.float32)
    calls = {"blocks (jpeg=None)": None, "pixels (jpeg=False)": False}
    times: dict[str, list[float]] = {k: [] for k in calls}
    for rnd in range(args.rounds + 1):
        for name, jpeg in calls.items():
            with record_stages() as log:
                t0 = time.perf_counter()
                res = jaxdof.fit_lens(image, depth, decoded, init, jpeg=jpeg)
                seconds = time.perf_counter() - t0
            if rnd == 0:
                print(f"{name}: cold {seconds:.1f} s", flush=True)
                continue
            times[name].append(seconds)
            if rnd == args.rounds:
                n, d = float(res.lenses.f_number[0]), float(res.lenses.focus_distance[0])
                print(
                    f"{name}: f/{n:.4f} ({100 * (n / 2.8 - 1):+.2f} %), focus {d:.4f} m "
                    f"({100 * (d / 2.5 - 1):+.2f} %), success {res.success}, tiles {len(res.tiles)}"
                )
                print("  stages (s): " + ", ".join(f"{s} {t:.2f}" for s, t in log))
    for name, ts in times.items():
        print(
            f"{name}: warm median {statistics.median(ts):.2f} s of {', '.join(f'{t:.2f}' for t in ts)}"
        )
    a, b = (statistics.median(t) for t in times.values())
    print(f"ratio blocks / pixels: {a / b:.2f}")


if __name__ == "__main__":
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--rounds", type=int, default=3)
    main(ap.parse_args())
