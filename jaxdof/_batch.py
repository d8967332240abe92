"""Many scenes at once, sharded over devices along the batch axis (`jax.sharding`).

The batch axis is the one that parallelises without communication: every scene is rendered (and
fitted) independently. `render_batch` and `fit_batch` place the batch on a 1-D device `Mesh` with a
`NamedSharding(mesh, PartitionSpec("batch"))` and run one `jit(vmap(render))` or
`jit(vmap(solve_lens))`; XLA's SPMD
partitioner then keeps each device on its own slice. The same code runs on one CPU, on several GPUs,
or on several hosts after `jax.distributed.initialize()` (`jax.devices()` then lists every host's
devices). To try several devices on one CPU, set `XLA_FLAGS=--xla_force_host_platform_device_count=4`
before JAX starts.
"""

from __future__ import annotations

from typing import Any

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jax.sharding import Mesh, NamedSharding, PartitionSpec

from ._filters import AbstractMethod, as_method
from ._filters.common import is_concrete
from ._fit import AbstractForwardModel, FitResult, solve_lens
from ._lens import ThinLens, coc_radius
from ._render import render


BATCH_AXIS = "batch"


def batch_mesh(*, devices: Any = None) -> Mesh:
    """A 1-D `Mesh` over `devices` (default: all of `jax.devices()`), its axis named `"batch"`."""
    devices = jax.devices() if devices is None else list(devices)
    if not devices:
        raise ValueError("batch_mesh needs at least one device")
    return Mesh(np.asarray(devices), (BATCH_AXIS,))


def shard_batch(tree: Any, mesh: Mesh) -> Any:
    """Place every array leaf of `tree` on `mesh`, split along its leading (batch) axis.

    The leading axis must be a multiple of the number of devices (`render_batch` pads to one).
    """
    n = mesh.devices.size

    def put(x):
        x = jnp.asarray(x)
        if x.ndim == 0 or x.shape[0] % n:
            raise ValueError(
                f"shard_batch: a leaf of shape {x.shape} has no leading batch axis divisible by the "
                f"{n} devices of the mesh; pad the batch to a multiple of {n}"
            )
        return jax.device_put(x, NamedSharding(mesh, PartitionSpec(BATCH_AXIS)))

    return jax.tree_util.tree_map(put, tree)


def _lens_per_scene(lens: ThinLens, b: int, what: str, one: str) -> bool:
    """Whether `lens` has one value per scene (fields `(b,)`) rather than one for all (scalars)."""
    leaves = jax.tree_util.tree_leaves(lens)
    per_scene = any(jnp.ndim(x) > 0 for x in leaves)
    if per_scene and any(jnp.shape(x) != (b,) for x in leaves):
        raise ValueError(
            f"{what} must be a scalar ({one} for all scenes) or have shape ({b},) (one per "
            f"scene); got {[jnp.shape(x) for x in leaves]}"
        )
    return per_scene


def render_batch(
    images,
    depths,
    lens: ThinLens,
    *,
    method: str | AbstractMethod = "soft",
    max_radius: float | None = None,
    normalize: bool = False,
    footprint: bool = False,
    downsample: int = 1,
    mesh: Mesh | None = None,
):
    """Render a batch of scenes, sharded over the devices of `mesh` along the batch axis.

    **Arguments:**

    - `images`: `(B, H, W)` or `(B, H, W, C)` all-in-focus linear-light images.
    - `depths`: `(B, H, W)` z-depths (m).
    - `lens`: one `ThinLens` for every scene (scalar fields), or one per scene (fields of shape
      `(B,)`).
    - `method`, `normalize`, `footprint`, `downsample`: as in `jaxdof.render` (a method object or
      a built-in's name; with `downsample` the output is `(B, H / s, W / s, ...)`).
    - `max_radius`: window size in (the photo's) pixels, shared by the batch. `None` takes the largest circle of
      confusion over the batch (needs concrete inputs).
    - `mesh`: a 1-D mesh from `batch_mesh` (default: all devices).

    **Returns:** `(B, ...)` rendered images, like `jax.vmap(render)` would give, sharded along the
    batch axis. The batch is padded (by repeating the last scene) to a multiple of the number of
    devices and the padding is dropped from the result.
    """
    images, depths = jnp.asarray(images), jnp.asarray(depths)
    if images.ndim not in (3, 4) or depths.ndim != 3 or depths.shape != images.shape[:3]:
        raise ValueError(
            "render_batch: images must be (B, H, W) or (B, H, W, C) and depths (B, H, W) with the "
            f"same B, H, W; got images {images.shape} and depths {depths.shape}"
        )
    b = images.shape[0]
    method = as_method(method)  # a bad name fails here, before any device work
    per_scene = _lens_per_scene(lens, b, "render_batch: every lens field", "one lens")
    if max_radius is None:
        if not is_concrete(depths, lens):
            raise ValueError(
                "render_batch: under jit pass max_radius=<float> (pixels), a static number"
            )
        lens_b = (
            lens if per_scene else jax.tree_util.tree_map(lambda x: jnp.broadcast_to(x, (b,)), lens)
        )
        radii = jax.vmap(coc_radius)(depths, lens_b)
        max_radius = float(jnp.max(radii)) if radii.size else 0.0
    mesh = batch_mesh() if mesh is None else mesh
    n = mesh.devices.size
    padded = -(-b // n) * n

    def pad(x):  # repeat the last scene: valid inputs, dropped afterwards
        return jnp.concatenate([x, jnp.repeat(x[-1:], padded - b, axis=0)]) if padded > b else x

    images, depths = pad(images), pad(depths)
    images, depths = shard_batch((images, depths), mesh)
    lens_axes = 0 if per_scene else None
    if per_scene:
        lens = shard_batch(jax.tree_util.tree_map(pad, lens), mesh)

    def one(image, depth, lens_i):
        return render(
            image,
            depth,
            lens_i,
            method=method,
            max_radius=max_radius,
            normalize=normalize,
            footprint=footprint,
            downsample=downsample,
        )

    out_sharding = NamedSharding(mesh, PartitionSpec(BATCH_AXIS))
    fn = jax.jit(jax.vmap(one, in_axes=(0, 0, lens_axes)), out_shardings=out_sharding)
    out = fn(images, depths, lens)
    return out[:b] if padded > b else out


def _pad_batch(tree: Any, b: int, padded: int) -> Any:
    """Repeat the last scene of every leaf up to `padded` (valid inputs, dropped afterwards)."""

    def pad(x):
        x = jnp.asarray(x)
        return jnp.concatenate([x, jnp.repeat(x[-1:], padded - b, axis=0)]) if padded > b else x

    return jax.tree_util.tree_map(pad, tree)


def fit_batch(
    images,
    depths,
    targets,
    init: ThinLens,
    *,
    max_radius: float,
    model: AbstractForwardModel | None = None,
    mesh: Mesh | None = None,
    **solve_kwargs,
) -> FitResult:
    """Fit many independent scenes at once, sharded over the devices of `mesh` along the batch axis.

    One `jit(vmap(jaxdof.solve_lens))`: one compilation for the batch, each device solving its own
    slice of scenes (no communication). On one device this is exactly `jax.vmap(solve_lens)`.

    **Arguments:**

    - `images`: `(B, H, W)` or `(B, H, W, C)` all-in-focus linear-light images.
    - `depths`: `(B, H, W)` z-depths (m).
    - `targets`: the photos, `(B, H, W[, C])` (one per scene) or `(B, T, H, W[, C])` (a bracket
      of `T` per scene).
    - `init`: the start, one `ThinLens` for every scene (scalar fields) or one per scene (fields
      of shape `(B,)`).
    - `max_radius`: the filter window in pixels (static, shared by the batch).
    - `model`: the forward model, shared by the batch (a `jaxdof.AbstractForwardModel`; default
      `jaxdof.DefocusModel` of `method`, `footprint`, `downsample`), as in `solve_lens`.
    - `mesh`: a 1-D mesh from `batch_mesh` (default: all devices).
    - `solve_kwargs`: `free`, `shared`, `solver`, `max_steps`, `weight` (`(B, ...)`), `exposure`,
      or the default model's `method`, `footprint`, `downsample`, as in `solve_lens`.

    **Returns:** a `FitResult` whose array fields have a leading batch axis `B` (read `.status` /
    `.success` per scene, as with `solve_lens`; no multi-start; a scene's `message` from its own
    result, `jax.tree_util.tree_map(lambda x: x[i], result).message`).
    """
    images, depths, targets = jnp.asarray(images), jnp.asarray(depths), jnp.asarray(targets)
    b = images.shape[0]
    if (
        images.ndim not in (3, 4)
        or depths.shape != images.shape[:3]
        or targets.shape[0] != b
        or targets.shape[-images.ndim + 1 :] != images.shape[1:]
    ):
        raise ValueError(
            "fit_batch: images must be (B, H, W[, C]), depths (B, H, W) and targets "
            "(B, [T,] H, W[, C]) with the same B, H, W[, C]; got images "
            f"{images.shape}, depths {depths.shape}, targets {targets.shape}"
        )
    per_scene = _lens_per_scene(init, b, "fit_batch: every field of init", "one start")
    weight = solve_kwargs.pop("weight", None)
    mesh = batch_mesh() if mesh is None else mesh
    n = mesh.devices.size
    padded = -(-b // n) * n
    batched = (images, depths, targets, weight, init if per_scene else None)
    batched = shard_batch(_pad_batch(batched, b, padded), mesh)
    images, depths, targets, weight, inits = batched

    def one(image, depth, target, weight_i, init_i):
        start = init if init_i is None else init_i
        return solve_lens(
            image,
            depth,
            target,
            start,
            max_radius=max_radius,
            weight=weight_i,
            model=model,
            **solve_kwargs,
        )

    axes = (0, 0, 0, None if weight is None else 0, 0 if per_scene else None)
    result = eqx.filter_jit(eqx.filter_vmap(one, in_axes=axes))(
        images, depths, targets, weight, inits
    )
    return jax.tree_util.tree_map(lambda x: x[:b], result) if padded > b else result
