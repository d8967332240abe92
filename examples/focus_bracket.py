"""Calibrate a lens from a focus bracket: focal length, f-number and every focus distance.

    python examples/focus_bracket.py

One defocused photo fixes the lens only up to its blur scale K = f^2 / (2 N (d_f - f)) and the
focus distance d_f, so f and N cannot be told apart. A bracket (the same lens and aperture,
refocused between shots) can: K changes across the shots as 1 / (d_f - f), at a rate that
depends on f. Here three photos of a synthetic scene, focused at 1.5 m, 2.5 m and 5 m through
an 85 mm f/2.8 lens, are fitted with f and N shared by all shots and one focus distance each,
from a start that is wrong in every parameter.
"""

import numpy as np

import jaxdof


def scene(h: int = 40, w: int = 56):
    """A textured ground plane from 1.2 m to a wall at 10 m, with a box at 2 m (linear light)."""
    rng = np.random.default_rng(0)
    yy, xx = np.mgrid[0:h, 0:w]
    inverse = 1 / 10 + (1 / 1.2 - 1 / 10) * np.clip((yy - 0.3 * h) / (0.7 * h - 1), 0, 1)
    depth = 1 / inverse
    depth[h // 4 : 3 * h // 4, w // 8 : w // 3] = 2.0
    texture = 0.2 + 0.5 * ((yy // 4 + xx // 4) % 2) + 0.3 * rng.uniform(size=(h, w))
    image = texture[..., None] * np.array([1.0, 0.8, 0.6])
    return image.astype(np.float32), depth.astype(np.float32)


def main():
    image, depth = scene()
    focus = np.array([1.5, 2.5, 5.0])
    sensor = dict(sensor_width=0.012, image_width=image.shape[1])  # 12 mm wide crop of a sensor
    truth = jaxdof.ThinLens.from_sensor(0.085, 2.8 + 0 * focus, focus, **sensor)
    rng = np.random.default_rng(1)
    # Each photo as a camera takes it: occlusion at the box's edges, each pixel integrating the
    # light over its area (the footprint), sensor noise. The fit decides by itself to model both.
    camera = dict(method="local_occlusion", footprint=True)
    photos = [
        np.asarray(
            jaxdof.render(
                image, depth, jaxdof.ThinLens.from_sensor(0.085, 2.8, d, **sensor), **camera
            )
        )
        + rng.normal(0, 0.005, image.shape).astype(np.float32)  # sensor noise
        for d in focus
    ]
    start = jaxdof.ThinLens.from_sensor(0.06, 4.0, 3.0, **sensor)  # 60 mm f/4 at 3 m, every shot
    result = jaxdof.fit_lens(
        image,
        depth,
        photos,
        start,
        free=("focal_length", "f_number", "focus_distance"),
        shared=("focal_length", "f_number"),
    )
    print(result.summary())
    print(f"treatment: {result.treatment}")
    fitted, se = result.lenses, result.stderr
    f, n = float(fitted.focal_length[0]), float(fitted.f_number[0])
    print(f"focal length {f * 1e3:.2f} mm ± {float(se['focal_length'][0]) * 1e3:.2f} (truth 85)")
    print(f"f-number     {n:.3f} ± {float(se['f_number'][0]):.3f} (truth 2.8)")
    for t, d in enumerate(focus):
        got, err = float(fitted.focus_distance[t]), float(se["focus_distance"][t])
        print(f"focus[{t}]     {got:.4f} m ± {err:.4f} (truth {d})")
    assert bool(result.success), result.message
    # The truth lies within 5 standard errors of every recovered value (the noise is Gaussian and
    # the model exact, so this fails only if the fit or its error estimate is wrong).
    for name in ("focal_length", "f_number", "focus_distance"):
        z = np.abs(
            np.asarray(getattr(fitted, name)) - np.asarray(getattr(truth, name))
        ) / np.asarray(se[name])
        assert np.all(z < 5), (name, z)


if __name__ == "__main__":
    main()
