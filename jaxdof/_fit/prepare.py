"""Input checks and conversion: options in Python, arrays in one float dtype (numpy on the host
for `fit_lens`, jax under `solve_lens`), and the forward model from `model=` or its keywords."""

from __future__ import annotations

import contextlib
import contextvars
import dataclasses
import math
from collections.abc import Iterator

import jax
import jax.numpy as jnp
import numpy as np

from .._corrections import depth_edges
from .._filters.common import is_concrete
from .._holes import depth_holes, filled, near_holes
from .._lens import ThinLens
from .forward import AbstractForwardModel, DefocusModel
from .layout import ALL_FIELDS, LENS_FIELDS, _Arr, _Layout, _Spec
from .photo import luma


def forward_model(model, *, method=None, footprint=None, downsample=None) -> AbstractForwardModel:
    """The forward model of a fit: `model`, or a `DefocusModel` of the keywords that were given
    (`None` means not given). Giving both is a `ValueError`: the model holds its own options."""
    given = dict(method=method, footprint=footprint, downsample=downsample)
    given = {k: v for k, v in given.items() if v is not None}
    if model is None:
        return DefocusModel(**given, checks=False)  # cacheable (`DefocusModel.checks`)
    if given:
        kw = ", ".join(f"{k}={v!r}" for k, v in given.items())
        raise ValueError(
            f"model={model} was given together with {kw}: those are options of the default "
            "forward model. Pass them to the model instead, e.g. "
            f"model=jaxdof.DefocusModel({kw}), or leave them out."
        )
    if not isinstance(model, AbstractForwardModel):
        raise ValueError(
            f"model must be a jaxdof.AbstractForwardModel (e.g. jaxdof.DefocusModel()), "
            f"got {type(model).__name__}"
        )
    return model


def check_differentiable(model: AbstractForwardModel) -> None:
    """Refuse a forward model whose photo has no useful derivative with respect to the lens."""
    if not model.differentiable_in_lens:
        raise ValueError(
            f"{model} cannot drive a fit: its output has no useful derivative with respect to the "
            "lens (for a DefocusModel: its method's output has none with respect to the circle "
            "radii, differentiable_in_radius is False). Use a method that has one, e.g. the "
            "default 'soft' (or 'aperture', 'auto', 'local_occlusion')."
        )


def _check_names(free, shared) -> tuple[tuple[str, ...], tuple[str, ...]]:
    if isinstance(free, str):
        free = (free,)
    if isinstance(shared, str):
        shared = (shared,)
    free, shared = tuple(free), tuple(shared)
    for name in free:
        if name == "pixel_pitch":
            raise ValueError(
                "pixel_pitch cannot be fitted: it scales every circle of confusion exactly as "
                "1/K does, so it is indistinguishable from the other fields. Set it from the "
                "sensor width (ThinLens.from_sensor) and fit the others."
            )
        if name not in LENS_FIELDS:
            raise ValueError(f"free must name fields among {LENS_FIELDS}, got {name!r}")
    if not free:
        raise ValueError(f"free must name at least one field among {LENS_FIELDS}")
    if len(set(free)) != len(free):
        raise ValueError(f"free names a field twice: {free}")
    for name in shared:
        if name not in free:
            raise ValueError(
                f"shared must be a subset of free (a fixed field keeps its init value in every "
                f"target anyway), got shared={shared}, free={free}"
            )
    free = tuple(n for n in LENS_FIELDS if n in free)
    shared = tuple(n for n in LENS_FIELDS if n in shared)
    return free, shared


def _check_options(max_steps, starts, verbose, max_radius, free) -> tuple[int, int]:
    """`fit_lens`'s scalar options: `(max_steps, starts)` as ints (`starts=None`: the default)."""
    if int(max_steps) < 1:
        raise ValueError(f"max_steps must be a positive integer, got {max_steps}")
    if starts is None:
        starts = 4 if "focus_distance" in free else 3
    if int(starts) < 1:
        raise ValueError(f"starts must be >= 1, got {starts}")
    if verbose is not False and verbose is not True and not callable(verbose):
        raise ValueError(f"verbose must be a bool or a callable, got {verbose!r}")
    if max_radius is not None and (not math.isfinite(float(max_radius)) or max_radius < 0):
        raise ValueError(f"max_radius must be a finite number >= 0 (pixels), got {max_radius}")
    return int(max_steps), int(starts)


def photo_and_ratio(
    model: AbstractForwardModel, image_shape: tuple[int, ...]
) -> tuple[tuple[int, ...], int]:
    """The photo's shape (`model.photo_shape`) and the integer ratio `s` of the image's `(H, W)`
    to the photo's, checked: the coarse-to-fine pyramid keeps that ratio."""
    image_shape = tuple(image_shape)
    photo = tuple(model.photo_shape(image_shape))
    fits = len(photo) == len(image_shape) >= 2 and photo[2:] == image_shape[2:]
    s = image_shape[0] // photo[0] if fits and photo[0] > 0 else 1
    if not fits or (photo[0] * s, photo[1] * s) != image_shape[:2]:
        raise ValueError(
            f"{type(model).__name__}.photo_shape({image_shape}) returned {photo}: the photo's "
            "(H, W) must be the image's divided by one integer, its other axes the image's"
        )
    return photo, s


@dataclasses.dataclass(frozen=True)
class Problem:
    """`fit_lens`'s inputs on the host, checked: the arrays in one float dtype, float64 copies
    of the depth and init for Python-side decisions, and the parameter layout."""

    image: np.ndarray
    depth: np.ndarray
    targets: np.ndarray  # (T, *photo)
    sqrt_w: np.ndarray  # (T, *photo)
    base: np.ndarray  # (T, 4) init lens rows (f, N, d_f, pitch) in the data's dtype
    single: bool  # one target given as an image, not a sequence
    ratio: int  # the image's (H, W) over the photo's
    spec: _Spec
    layout: _Layout
    d: np.ndarray  # depth, float64
    b: np.ndarray  # base, float64
    fcap: np.ndarray  # the layout's bound on f, float64
    holes: np.ndarray | None = None  # (H, W) image pixels without a depth (filled in `depth`)

    @property
    def dtype(self):
        return self.image.dtype

    @property
    def photo(self) -> tuple[int, int]:
        return tuple(self.targets.shape[1:3])

    @property
    def args(self) -> tuple:
        """The solver's `args` at full resolution."""
        return (self.image, self.depth, self.targets, self.sqrt_w, self.layout)


def prepare_problem(
    image, depth, targets, init, weight, model: AbstractForwardModel, free, shared,
    nuisances: tuple[str, ...] = (), luma: bool = False,
) -> Problem:  # fmt: skip
    """`_prepare` in numpy plus the checks that need values, and the layout: one `Problem`.

    Inside `prepared_once`, the arrays prepared from the same input objects are reused: the
    refits of one `fit_lens` call differ from its first fit in the lens, not in the data."""
    arrays = _prepared_arrays(image, depth, targets, weight, model, luma, init)
    image, depth, targets, sqrt_w, single, holes, d, ratio = arrays
    base = np.asarray(_base(np, init, targets.shape[0]).astype(image.dtype))
    b = np.asarray(base, np.float64)
    if np.any(np.isnan(d)) or not np.all(d > b[:, 0].max()):
        raise ValueError(
            f"depth must exceed the focal length everywhere (metres; found min depth {np.nanmin(d)} m "
            f"or NaN, focal length {b[:, 0].max()} m)"
        )
    spec = _Spec(free, shared, targets.shape[0], nuisances, luma)
    layout = spec.layout(base, depth)
    fcap = np.asarray(layout.fcap, np.float64)
    if np.any(b[:, 0] >= fcap):
        raise ValueError(
            "init.focal_length must be below the nearest depth (and the focus distance): "
            f"got {b[:, 0]} m against a bound of {fcap} m"
        )
    return Problem(
        image, depth, targets, sqrt_w, base, bool(single), ratio, spec, layout, d, b, fcap, holes
    )


# `prepared_once`'s arrays, by the identity of the inputs they were prepared from.
_PREPARED: contextvars.ContextVar[dict | None] = contextvars.ContextVar(
    "jaxdof_prepared", default=None
)


@contextlib.contextmanager
def prepared_once() -> Iterator[None]:
    """Within the block, `prepare_problem` prepares each set of input arrays once: a 24 MP
    problem (its holes filled, its checks, its float64 depth) costs seconds, and `fit_lens`'s
    refits (the photo's say, the nuisances) prepare the same inputs again."""
    token = _PREPARED.set({})
    try:
        yield
    finally:
        _PREPARED.reset(token)


def scene_edges(depth: np.ndarray) -> np.ndarray:
    """`jaxdof.depth_edges(depth)` (read-only), once per depth map within `prepared_once`: the
    scene's rule and the tiles' choice ask it of every refit's same prepared depth (a 24 MP map:
    most of a second each)."""
    memo = _PREPARED.get()
    if memo is None:
        return depth_edges(depth)
    key = ("edges", id(depth))
    if key not in memo:
        edges = depth_edges(depth)
        edges.flags.writeable = False
        memo[key] = (depth, edges)  # (held, so that its id stays its own)
    return memo[key][1]


def _prepared_arrays(image, depth, targets, weight, model, luma: bool, init) -> tuple:
    """The arrays of `prepare_problem` that do not depend on the lens: `(image, depth, targets,
    sqrt_w, single, holes, d, ratio)`, from `prepared_once`'s memo where the same objects were
    prepared (held there, so their ids stay theirs)."""
    memo = _PREPARED.get() if np.ndim(image) in (2, 3) else None  # else `_prepare` says why
    inputs = (image, depth, targets, weight)
    key = ()
    if memo is not None:
        key = (*map(id, inputs), bool(luma), tuple(model.photo_shape(tuple(np.shape(image)))))
        if key in memo:
            return memo[key][1]
    # Depth holes (NaN, 0, negative: no data) are filled so that the render runs; the photo
    # pixels their light reaches leave the residual once the window is known (`leave_out_holes`).
    holes = depth_holes(depth) if np.ndim(depth) == 2 else None
    if holes is not None and holes.any():
        depth = filled(np.asarray(depth), holes)
    else:
        holes = None
    # Checks and set-up in numpy on the host: two compiled calls per fit (`fit_starts`, `finish`)
    # and one transfer of a few small results back, not one device call per array operation.
    *arrays, single = _prepare(image, depth, targets, init, weight, model, xp=np)
    # (numpy arrays already: `np.asarray` makes no copies, it tells the type checker so.)
    image, depth, targets, sqrt_w, _ = (np.asarray(x) for x in arrays)
    for name, x in (("image", image), ("targets", targets)):
        if not np.all(np.isfinite(x)):
            raise ValueError(
                f"{name} contains NaN or inf; mask such pixels with weight=0 and set them to 0"
            )
    if luma:
        targets, sqrt_w = (np.asarray(x) for x in luma_targets(targets, sqrt_w))
    _, ratio = photo_and_ratio(model, image.shape)
    d = np.asarray(depth, np.float64)
    out = (image, depth, targets, sqrt_w, single, holes, d, ratio)
    if memo is not None:
        memo[key] = (inputs, out)
    return out


def luma_targets(targets, sqrt_w):
    """Colour targets `(T, H, W, 3)` and their weights as their sRGB luma `(T, H, W, 1)`
    (`photo.luma`) and the smallest weight of each pixel's channels (a masked channel masks the
    pixel). Anything else is refused: the luma is of RGB photos."""
    if targets.ndim != 4 or targets.shape[-1] != 3:
        raise ValueError(
            f"luma=True compares RGB photos in their luma; the targets have shape "
            f"{targets.shape[1:]}, not (H, W, 3)"
        )
    y = luma(jnp.asarray(targets))
    if isinstance(targets, np.ndarray):  # on the host (`prepare_problem`)
        return np.asarray(y), np.min(np.asarray(sqrt_w), axis=-1, keepdims=True)
    return y, jnp.min(sqrt_w, axis=-1, keepdims=True)


# The share of the fitted photo pixels with depth that must stay out of a hole's reach; short of
# it the reach is halved until it holds (`leave_out_holes`).
_HOLES_KEEP = 0.25


def leave_out_holes(p: Problem, reach: float) -> tuple[Problem, int, float]:
    """`p` with zero weight at the photo pixels within `reach` photo pixels (a circle and the
    render's stencils) of a depth hole, how many photo pixels that left out, and the reach used.

    Where that would leave under `_HOLES_KEEP` of the fitted pixels with depth (holes scattered
    over a whole small frame), the reach is halved until it does not (the filled depth is a smooth
    continuation of its neighbours, so the nearest pixels matter most). Raises `ValueError`
    only when the holes themselves cover every fitted photo pixel."""
    if p.holes is None:
        return p, 0, reach
    w = p.sqrt_w
    fitted = np.any(w > 0, axis=(0, 3)) if w.ndim == 4 else np.any(w > 0, axis=0)
    # The share is of the pixels with depth: a chart fills a fifth of its photo, the rest holes.
    with_depth = int(np.sum(fitted & ~near_holes(p.holes, 0.0, p.ratio)))
    while True:
        near = near_holes(p.holes, reach * p.ratio, p.ratio)
        left = int(np.sum(fitted & ~near))
        if left >= _HOLES_KEEP * with_depth or (reach <= 0 and left > 0):
            break
        if reach <= 0:
            raise ValueError(
                f"depth has {int(p.holes.sum())} holes (NaN, 0 or negative: no data) that "
                "cover every fitted photo pixel: give a depth map with fewer holes"
            )
        reach = float(math.floor(reach / 2))
    keep = (~near).astype(p.dtype)
    sqrt_w = w * (keep[None, ..., None] if w.ndim == 4 else keep[None])
    return dataclasses.replace(p, sqrt_w=sqrt_w), int(np.sum(near & fitted)), reach


def _prepare(
    image, depth, targets, init, weight, model: AbstractForwardModel, xp=jnp
) -> tuple[_Arr, _Arr, _Arr, _Arr, _Arr, bool]:
    """Validate and convert inputs: arrays in one float dtype, targets `(T, ...)`, base `(T, 4)`.

    The targets (and weights) have the photo's shape, `model.photo_shape(image.shape)` (with a
    `DefocusModel`'s `downsample = s`, the image's with each spatial axis divided by `s`).

    `xp=np` (concrete inputs only) does it all in numpy, without a device call per operation; the
    dtypes are jax's either way (`float64` becomes `float32` without `jax_enable_x64`).
    """
    image = _asarray(xp, image)
    depth = _asarray(xp, depth)
    if image.ndim not in (2, 3):
        raise ValueError(f"image must have shape (H, W) or (H, W, C), got {image.shape}")
    if depth.shape != image.shape[:2]:
        raise ValueError(
            f"depth must have the image's (H, W) = {image.shape[:2]}, got {depth.shape}"
        )
    photo, s = photo_and_ratio(model, image.shape)
    of = "the image's shape" if s == 1 else f"the image's shape divided by downsample={s}"
    targets, single = _stack_targets(xp, targets, photo, of)
    for name, x in (("image", image), ("depth", depth), ("targets", targets)):
        if not jnp.issubdtype(x.dtype, jnp.floating):
            raise ValueError(
                f"{name} must be floating point (linear light / metres), got dtype {x.dtype}; "
                f"convert it first, e.g. {name}.astype(numpy.float32)"
            )
    dtype = jnp.result_type(image.dtype, targets.dtype)
    base = _base(xp, init, targets.shape[0]).astype(dtype)
    sqrt_w = _sqrt_weight(xp, weight, targets, photo, dtype)

    def as_dtype(x):
        # No copy where the dtype is right already (nothing downstream writes into these): a
        # 24 MP image and photo are 0.6 GB of copies each time a fit prepares them.
        return x if x.dtype == dtype else x.astype(dtype)

    return as_dtype(image), as_dtype(depth), as_dtype(targets), sqrt_w, base, single


def _stack_targets(xp, targets, photo: tuple[int, ...], of: str) -> tuple[_Arr, bool]:
    """Targets as one array `(T, *photo)`, and whether a single image was given."""
    single = not isinstance(targets, (list, tuple))
    if single:
        targets = _asarray(xp, targets)
        if targets.shape == photo:
            return targets[None], True
        if targets.shape[1:] == photo:
            return targets, False
        raise ValueError(
            f"targets must be one image of {of} {photo}, a sequence of them, or an array "
            f"(T, *{photo}); got shape {targets.shape}"
        )
    if len(targets) == 0:
        raise ValueError("targets is an empty sequence; pass at least one photo")
    targets = [_asarray(xp, t) for t in targets]
    for i, t in enumerate(targets):
        if t.shape != photo:
            raise ValueError(
                f"targets[{i}] has shape {t.shape}; every target must have {of} "
                f"{photo} (same scene, same framing)"
            )
    return xp.stack(targets), False


def _base(xp, init, n_t: int):
    """The init lens rows `(T, 4)` of `(f, N, d_f, pitch)`."""
    if isinstance(init, ThinLens):
        inits = [init]
    elif isinstance(init, (list, tuple)) and all(isinstance(x, ThinLens) for x in init):
        inits = list(init)
    else:
        raise ValueError(
            f"init must be a ThinLens or a sequence of them, got {type(init).__name__}"
        )
    fields = [[_asarray(xp, getattr(x, name)) for name in ALL_FIELDS] for x in inits]
    if len(inits) == 1 and all(v.ndim == 1 for v in fields[0]) and fields[0][0].shape[0] == n_t:
        return xp.stack(fields[0], axis=-1)  # one batched ThinLens with a (T,) axis
    for x in fields:
        if any(v.ndim != 0 for v in x):
            raise ValueError(
                "init must be scalar ThinLens(es) (one, or one per target) or one ThinLens "
                f"with fields of shape (T,) = ({n_t},)"
            )
    base = xp.stack([xp.stack(x) for x in fields])
    if base.shape[0] == 1:
        return xp.broadcast_to(base, (n_t, 4))
    if base.shape[0] != n_t:
        raise ValueError(
            f"init has {base.shape[0]} lenses but there are {n_t} targets; pass one or {n_t}"
        )
    return base


def _sqrt_weight(xp, weight, targets, photo: tuple[int, ...], dtype):
    """`sqrt(weight)` at the targets' shape, checked.

    The weight is always materialised at the targets' shape, so that weighted and unweighted
    fits share one compiled solve.
    """
    n_t = targets.shape[0]
    if weight is None:
        return xp.ones(targets.shape, dtype)
    weight = _asarray(xp, weight)
    shape_ok = weight.shape in (photo[:2], (n_t, *photo[:2]), photo, targets.shape)
    if not shape_ok:
        raise ValueError(
            f"weight must have the targets' pixels: shape (H, W) = {photo[:2]}, (T, H, W), "
            f"{photo} or {targets.shape}; got {weight.shape}"
        )
    if is_concrete(weight):
        w = np.asarray(weight)
        if np.any(~np.isfinite(w)) or np.any(w < 0):
            raise ValueError("weight must be finite and >= 0 (0 masks a pixel out)")
        if not np.any(w > 0):
            raise ValueError("weight is zero everywhere: nothing left to fit")
    colour = targets.ndim == 4
    if weight.shape == photo[:2]:
        weight = weight[None, ..., None] if colour else weight[None]
    elif weight.shape == (n_t, *photo[:2]):
        weight = weight[..., None] if colour else weight
    elif weight.shape == photo:
        weight = weight[None]
    return xp.broadcast_to(xp.sqrt(weight.astype(dtype)), targets.shape)


def _asarray(xp, x) -> _Arr:
    """`jnp.asarray`, or its numpy twin keeping jax's dtype rules (`float64` -> `float32` without
    x64), so that both paths of `_prepare` see the same dtypes and say the same in messages."""
    if xp is jnp:
        return jnp.asarray(x)
    x = np.asarray(x)
    return x.astype(jax.dtypes.canonicalize_dtype(x.dtype), copy=False)
