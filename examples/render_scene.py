"""Render a built-in procedural scene through a thin lens and write `render_scene.png`.

python examples/render_scene.py [--out render_scene.png]
"""

import argparse

import matplotlib


matplotlib.use("Agg")
import jax.numpy as jnp
import matplotlib.pyplot as plt
import numpy as np

import jaxdof


def scene(h: int = 160, w: int = 240):
    """A checker texture on three planes (2 m, 4 m and a background at 12 m)."""
    yy, xx = np.mgrid[0:h, 0:w]
    image = 0.15 + 0.7 * (((yy // 8) + (xx // 8)) % 2)
    image = np.stack([image, 0.5 * image + 0.2 * (xx / w), image * (yy / h)], axis=-1)
    depth = np.full((h, w), 12.0)
    depth[:, : w // 3] = 2.0
    depth[h // 4 : 3 * h // 4, w // 3 : 2 * w // 3] = 4.0
    return image.astype(np.float32), depth.astype(np.float32)


def main(out: str = "render_scene.png") -> None:
    image, depth = scene()
    lens = jaxdof.ThinLens.from_sensor(
        0.085, 1.4, 4.0, sensor_width=0.036, image_width=image.shape[1]
    )
    radius = jaxdof.coc_radius(jnp.asarray(depth), lens)
    # Three depth planes, three radii: `Auto()` computes the soft filter's weights once per radius
    # and looks them up (`jaxdof.choose_method(radius)` says which way it chose), same numbers as
    # the default `Soft()`. The window is sized from the largest circle in the scene.
    blurred = jaxdof.render(image, depth, lens, method=jaxdof.Auto())
    print(
        f"blur scale K = {float(lens.blur_scale):.2f} px, largest circle {float(radius.max()):.2f} px"
    )
    fig, axes = plt.subplots(1, 3, figsize=(12, 3))
    for ax, img, title in zip(
        axes,
        (image, np.asarray(blurred), np.asarray(radius)),
        ("all in focus", "85 mm f/1.4 focused at 4 m", "CoC radius (px)"),
    ):
        ax.imshow(np.clip(img, 0, 1) if img.ndim == 3 else img)
        ax.set_title(title)
        ax.axis("off")
    fig.tight_layout()
    fig.savefig(out, dpi=80)
    print(f"wrote {out}")


if __name__ == "__main__":
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--out", default="render_scene.png")
    main(parser.parse_args().out)
