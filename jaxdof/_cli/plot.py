"""The `--plot` and `demo` figures: grids of images, residuals and circle-of-confusion maps.

matplotlib is an optional dependency (the `plot` extra), imported only when a figure is made.
"""

from __future__ import annotations

import os

import jax
import jax.numpy as jnp
import numpy as np

import jaxdof

from .._io import InputError, atomic_write, check_output, linear_to_srgb
from .._render import box_downsample


def check_plot(path: str | None, inputs: list[str], option: str) -> None:
    """Refuse a figure path before any work: no matplotlib, an input's path, not `*.png`."""
    if path is None:
        return
    try:
        import matplotlib  # noqa: F401
    except ImportError:
        raise InputError(f"{option} needs matplotlib: pip install 'jaxdof[plot]'") from None
    check_output(path, inputs, option)
    if os.path.splitext(path)[1].lower() != ".png":
        raise InputError(f"{option} {path}: the figure is written as PNG; name it *.png")


def _grid(
    path: str,
    columns: list[tuple[str, np.ndarray, str]],
    rows: int,
    inputs,
    option,
    boxes=(),
) -> None:
    """A grid figure: `columns` is a flat list of `(title, array, kind)` with kind in
    {"image", "residual", "coc"}, laid out `rows` by `len(columns) // rows`; `boxes`
    (`(row, column, height, width)`, a fit's tiles) are outlined on the residual panels."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.patches import Rectangle

    ncols = len(columns) // rows
    fig, axes = plt.subplots(rows, ncols, figsize=(2.6 * ncols, 2.3 * rows), squeeze=False)
    for ax, (title, array, kind) in zip(axes.ravel(), columns):
        if kind == "image":
            shown = linear_to_srgb(array)  # linear light, displayed as sRGB
            ax.imshow(shown, cmap="gray" if array.ndim == 2 else None, vmin=0, vmax=1)
        elif kind == "residual":
            res = array if array.ndim == 2 else array.mean(axis=-1)
            lim = float(np.max(np.abs(res))) or 1.0
            im = ax.imshow(res, cmap="RdBu", vmin=-lim, vmax=lim)
            fig.colorbar(im, ax=ax, fraction=0.046)
            for r, c, h, w in boxes:  # the pixels the fit used
                ax.add_patch(Rectangle((c - 0.5, r - 0.5), w, h, fill=False, lw=0.6, ec="k"))
            if boxes:
                title = f"{title}; {len(boxes)} fitted tiles outlined"
        else:
            im = ax.imshow(array, cmap="viridis")
            fig.colorbar(im, ax=ax, fraction=0.046)
        ax.set_title(title, fontsize=8)
        ax.axis("off")
    fig.tight_layout()
    atomic_write(path, lambda tmp: fig.savefig(tmp, dpi=90, format="png"), list(inputs), option)
    plt.close(fig)


def _lens_at(lens, index: int):
    return jax.tree_util.tree_map(lambda v: v if np.ndim(v) == 0 else v.reshape(-1)[index], lens)


def plot_fit(path: str, image, depth, targets, result, names, inputs, *, render_options) -> None:
    """One row per target: sharp, target, refit, residual, CoC map, at the photo's pixels.

    `image` and `depth` are the fit's inputs (`render_options["downsample"]` times the photo's
    resolution); `render_options` are the fit's forward-model options for `jaxdof.render`.
    """
    s = render_options.get("downsample", 1)
    small_image, small_depth = image, depth
    if s > 1:  # linear light by box means; depth by means of inverse depth (as the fit's pyramid)
        small_image = np.asarray(box_downsample(jnp.asarray(image), s))
        small_depth = 1 / np.asarray(box_downsample(1 / jnp.asarray(depth), s))
    columns = []
    for i, target in enumerate(targets):
        lens = _lens_at(result.lenses, i)
        refit = np.asarray(jaxdof.render(image, depth, lens, **render_options))
        radius = np.asarray(jaxdof.coc_radius(small_depth, lens))
        columns += [
            ("sharp" if i == 0 else "", small_image, "image"),
            (f"target {os.path.basename(names[i])}", target, "image"),
            ("refit", refit, "image"),
            ("residual (refit - target)", refit - target, "residual"),
            ("CoC radius (px)", radius, "coc"),
        ]
    _grid(path, columns, len(targets), inputs, "--plot", boxes=result.tiles or ())


def plot_demo(path: str, image, target, refit, radius) -> None:
    """The demo's figure: sharp, target, refit, residual, true CoC map."""
    columns = [
        ("sharp (all in focus)", image, "image"),
        ("target: 85mm f/1.4 @ 3 m", target, "image"),
        ("refit", refit, "image"),
        ("residual (refit - target)", refit - target, "residual"),
        ("true CoC radius (px)", radius, "coc"),
    ]
    _grid(path, columns, 1, [], "--out")
