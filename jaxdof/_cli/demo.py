"""The `jaxdof demo` scene: procedural, so the demo needs no files."""

from __future__ import annotations

import numpy as np


def demo_scene(h: int = 72, w: int = 96) -> tuple[np.ndarray, np.ndarray]:
    """A procedural all-in-focus scene: `(image (h, w, 3) linear, depth (h, w) metres)`.

    A textured ground plane recedes from 1.2 m at the bottom edge to a wall at 12 m, with two
    boxes standing on it at 1.8 m and 5 m, so the depths straddle a 3 m focus on both sides.
    The texture (a checker plus seeded noise) has detail at every scale for the blur to remove.
    """
    rng = np.random.default_rng(0)
    yy, xx = np.mgrid[0:h, 0:w].astype(np.float64)
    # Ground: inverse depth linear in the row (a plane seen in perspective), capped by the wall.
    inv = 1 / 12 + (1 / 1.2 - 1 / 12) * np.clip((yy - 0.3 * h) / (0.7 * h - 1), 0, 1)
    depth = 1 / inv
    checker = ((yy // 6 + xx // 6) % 2).astype(np.float64)
    base = 0.15 + 0.5 * checker + 0.3 * rng.uniform(size=(h, w))
    image = base[..., None] * np.stack([1.0 + 0 * xx, 0.6 + 0.4 * xx / w, 0.5 + 0.5 * yy / h], -1)
    boxes = [  # (rows, cols, depth m, colour): a near red box and a far blue one
        (
            slice(int(0.25 * h), int(0.85 * h)),
            slice(int(0.10 * w), int(0.35 * w)),
            1.8,
            (0.9, 0.3, 0.2),
        ),
        (
            slice(int(0.15 * h), int(0.55 * h)),
            slice(int(0.55 * w), int(0.85 * w)),
            5.0,
            (0.2, 0.4, 0.9),
        ),
    ]
    stripes = 0.35 + 0.65 * ((xx + yy) // 3 % 2)  # finer texture on the boxes
    for rows, cols, d, colour in boxes:
        depth[rows, cols] = d
        image[rows, cols] = stripes[rows, cols, None] * np.asarray(colour)
    image = np.clip(image, 0, 1)
    return image.astype(np.float32), depth.astype(np.float32)
