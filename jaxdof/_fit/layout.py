r"""The parameter layout of a fit and its unconstrained coordinates.

The solver's vector `y` holds `3 T` lens coordinates, field-major (`y[j T + t]` is field `j` of
target `t`), then `T` slots for each parameter of each fitted nuisance (`photo.NUISANCES`: with
`exposure`, `T` gains and `T` offsets, ...). Every iterate is a physical lens:

- focal length: `logit(f / fcap)`, with `fcap` just under the nearest depth (and under the focus
  distance when that is fixed), so `f < fcap` always;
- f-number: `log N`;
- focus distance: `y` with `w = |y| + w_min`, `d_f = f + fcap / w` (see below), so
  `f < d_f < inf` always, and focus at infinity is the ordinary point `y = 0` (up to `w_min`).

**The focus coordinate.** `w = fcap / (d_f - f)` is the focus power scaled to the scene
(dimensionless, `w in [0, inf)`, 0 at infinity; about `fcap / d_f`, so of order 1 for a focus
inside the scene, as the other coordinates). The circle of confusion is smooth in it, through
infinity: with `C = f^2 / (2 N p)` (pixels times metres) and `u = 1 / d_f = w / (fcap + f w)`,

$$r = C\,\frac{u - 1/d}{1 - f u} = \frac{C}{f}\left(\frac{f w}{\mathrm{fcap}}\left(1 -
  \frac{f}{d}\right) - \frac{f}{d}\right),\qquad
  \frac{\partial r}{\partial w} = \frac{C}{\mathrm{fcap}}\left(1 - \frac{f}{d}\right),$$

the blur of a point at the nearest depth focused at infinity: of the size of the circles
themselves, and non-zero at `w = 0`. The solver's `y` covers `w` twice,
`|y| = where(y >= 0, y, -y)` (`_fold`; not `abs`, whose JAX derivative at 0 is 0 and would freeze
a start at infinity): its derivative is `+-1`, never 0, so the Jacobian and the statistics are
regular at infinity. Where the data pull the focus beyond infinity (`dL/dw > 0` at `w = 0`) the
loss has a kink at `y = 0` that an unconstrained solver cannot settle on (measured: from N = 3,
d_f = 30 m with the truth at N = 2, infinity, Levenberg-Marquardt cycled at `y = +-2e-8` with N
stuck at 2.84); `fit_lens` then treats infinity as an active bound (`path._settle_at_infinity`).
A smooth fold (`w = y^2`) has no kink but a zero derivative at infinity, where the solver then
crawls (the same fit: `d_f` from 4e6 to 7e6 m in the last 10 of 100 steps).

`w_min = 1e-12` (`_W_MIN`) keeps the lens finite (`d_f - f <= 1e12 fcap`): a forward model
receives a `ThinLens`, and differentiating through `d_f = f + fcap / w` at `w = 0` exactly is
`0 * inf` (NaN in reverse mode, 0 in forward mode), and `fcap / w^2` overflows float32 below
`w ~ 1e-19`. `pack` subtracts it again, so every lens closer than `1e12 fcap` round-trips exactly
and the reported lens is the one the model saw; a focus at infinity is reported as about
`1e12 fcap` (circles within `1e-12` of the largest from infinity's), and its statistics say it
is consistent with infinity.

A shared field reads slot `j T` for every target; a fixed field reads `base`; unread slots have zero
Jacobian columns: they are neither differentiated nor in the statistics. Results and standard
errors are mapped back to each field's own units (metres, or dimensionless for `N`).
"""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Bool, Float, Int

from .._lens import ThinLens
from .photo import NUISANCES, NULL


LENS_FIELDS = ("focal_length", "f_number", "focus_distance")
ALL_FIELDS = ("focal_length", "f_number", "focus_distance", "pixel_pitch")

# Unconstrained coordinates are clipped to this range before they are mapped to a lens, so that no
# iterate overflows to an infinite or zero field (exp(40) ~ 2e17 is far outside any real lens; for
# the focus, w <= 40 is d_f >= f + fcap / 40, closer than any focus that keeps the scene sharp).
_CLIP = 40.0
# The floor of the focus coordinate `w` (see the module docstring): the lens the model sees is
# focused at most 1e12 fcap away (tests/test_fit.py::test_focus_coordinate_jacobian measures the
# Jacobian there against finite differences).
_W_MIN = 1e-12

# An array on the host (numpy: `fit_lens` builds its layout and starts without device calls) or a
# jax array (under jit).
_Arr = Array | np.ndarray


class _Layout(eqx.Module):
    """Which entry of the parameter vector drives which lens field of which target: data, not code.

    Keeping this in arrays (passed through `args`) means every free/shared choice with the same
    number of targets, number of free parameters, image shape and window runs the same compiled
    solve.

    - `base`: `(T, 4)` init values of `(f, N, d_f, pitch)`, used for the fields that are not free.
    - `src`: `(T, 3)` index into `y` of the coordinate of `(f, N, d_f)` for each target.
    - `use`: `(T, 3)` whether that field is free (else `base` is used).
    - `fcap`: `(T,)` upper bound on the focal length (metres): just under the nearest depth and,
      with the focus distance fixed, under the focus distance.
    - `live`: `(p,)` the slots of `y` that some field reads (the free parameters): the only
      Jacobian columns that are not zero by construction, so the only ones computed.
    - `frame_vu`: `(2, H, W)` where each photo pixel is in the whole frame (`photo.frame`'s
      units), on a mosaic of tiles, for the gains that depend on it; `None` on the whole frame.
    """

    # numpy arrays in `fit_lens` (built without device calls), jax arrays under jit.
    base: Float[_Arr, "t 4"]
    src: Int[_Arr, "t 3"]
    use: Bool[_Arr, "t 3"]
    fcap: Float[_Arr, " t"]
    live: Int[_Arr, " p"]
    frame_vu: Float[_Arr, "2 h w"] | None = None


class _Spec:
    """Python-side description of a fit: free/shared fields, targets, the fitted nuisances (in
    `photo.NUISANCES` order) -> slots and names."""

    def __init__(
        self, free, shared, n_targets: int, nuisances: tuple[str, ...] = (), luma: bool = False
    ):
        self.free, self.shared, self.n_targets = free, shared, n_targets
        self.nuisances, self.luma = tuple(nuisances), bool(luma)
        used, names = [], []
        multi = n_targets > 1
        for j, name in enumerate(LENS_FIELDS):
            if name not in free:
                continue
            ts = [0] if name in shared else range(n_targets)
            for t in ts:
                used.append(j * n_targets + t)
                names.append(name if (name in shared or not multi) else f"{name}[{t}]")
        for k, name in enumerate(nuisance_names(self.nuisances), start=3):
            for t in range(n_targets):
                used.append(k * n_targets + t)
                names.append(f"{name}[{t}]" if multi else name)
        self.used, self.names = tuple(used), tuple(names)

    # A spec is static data of the compiled fit: equal specs must share one compilation.
    def _key(self):
        return (self.free, self.shared, self.n_targets, self.nuisances, self.luma)

    def __eq__(self, other):
        return isinstance(other, _Spec) and self._key() == other._key()

    def __hash__(self):
        return hash(self._key())

    def layout(self, base, depth) -> _Layout:
        """The `_Layout` of this fit: in numpy for numpy `base` and `depth` (no device calls),
        else in jax (works on tracers)."""
        xp = np if isinstance(base, np.ndarray) and isinstance(depth, np.ndarray) else jnp
        t = self.n_targets
        shared = np.array([n in self.shared for n in LENS_FIELDS])
        use = np.broadcast_to(np.array([n in self.free for n in LENS_FIELDS]), (t, 3))
        src = np.arange(3)[None, :] * t + np.where(shared[None, :], 0, np.arange(t)[:, None])
        cap = xp.broadcast_to(xp.min(depth).astype(base.dtype), (t,))
        if "focus_distance" not in self.free:
            cap = xp.minimum(cap, base[:, 2])
        # Everything at infinity and the focus distance free: no bound from the scene.
        cap = xp.where(xp.isfinite(cap), cap, 1e3 * base[:, 0])
        # Just under the bound: a focal length equal to the nearest depth is not a lens for it.
        cap = (cap * (1 - 1e-3)).astype(base.dtype)
        return _Layout(
            base=base,
            src=xp.asarray(src, np.int32),
            use=xp.asarray(use),
            fcap=cap,
            live=xp.asarray(np.array(self.used, np.int32)),
        )


# ---------------------------------------------------------------------------------------------
# The coordinates: y <-> lens fields.
# ---------------------------------------------------------------------------------------------


def _fold(y: Array) -> Array:
    """`|y|` with derivative `+1` at 0 (JAX's `abs` has 0 there), so `y = 0` is not a stationary
    point of the map: a start focused at infinity moves."""
    return jnp.where(y >= 0, y, -y)


def _fields(y: Float[Array, " P"], layout: _Layout) -> tuple[Array, Array, Array]:
    """`(f, N, w)` of every target, `(T,)` each; `w = |y| + _W_MIN` the scaled focus power."""
    y = jnp.where(jnp.isfinite(y), jnp.clip(y, -_CLIP, _CLIP), 0)
    u = y[layout.src]
    base = layout.base
    f = jnp.where(layout.use[:, 0], layout.fcap * jax.nn.sigmoid(u[:, 0]), base[:, 0])
    n = jnp.where(layout.use[:, 1], jnp.exp(u[:, 1]), base[:, 1])
    return f, n, _fold(u[:, 2]) + _W_MIN


def natural(y: Float[Array, " P"], layout: _Layout) -> Float[Array, "t 4"]:
    """Lens fields `(f, N, d_f, pitch)` of every target: the lens the forward model is evaluated
    at, and the one reported (a free focus is at most `1e12 fcap` away; see `_W_MIN`)."""
    f, n, w = _fields(y, layout)
    base = layout.base
    d_f = jnp.where(layout.use[:, 2], f + layout.fcap / w, base[:, 2])
    return jnp.stack([f, n, d_f, base[:, 3]], axis=-1)


def nuisance_names(nuisances: tuple[str, ...]) -> tuple[str, ...]:
    """The parameters of the fitted `nuisances`, in slot order."""
    return tuple(n for k in nuisances for n in NUISANCES[k])


def nuisance_params(y: Float[Array, " P"], n_targets: int, nuisances: tuple[str, ...]) -> dict:
    """Every nuisance parameter per target, `(T,)` each: the fitted ones read from `y`, the
    others at their null (a gain of 1, else 0)."""
    t = n_targets
    out = {n: jnp.full((t,), NULL.get(n, 0.0), y.dtype) for k in NUISANCES for n in NUISANCES[k]}
    for k, name in enumerate(nuisance_names(nuisances), start=3):
        out[name] = y[k * t : (k + 1) * t]
    return out


def exposure_params(y: Float[Array, " P"], n_targets: int, nuisances: tuple[str, ...]):
    """Gain and offset per target (ones and zeros without the exposure nuisance)."""
    p = nuisance_params(y, n_targets, nuisances)
    return p["gain"], p["offset"]


def pack(
    params: Float[_Arr, "*s t 4"], layout: _Layout, nuisances: tuple[str, ...] = ()
) -> Float[_Arr, "*s P"]:
    """Inverse of `natural` (a shared field takes the first target's value; `d_f = inf`, and any
    focus beyond `1e12 fcap`, is `y = 0`).

    Works on numpy arrays too (in numpy: `fit_lens` packs its starts without device calls),
    and on a leading batch of starts.
    """
    xp = np if isinstance(params, np.ndarray) else jnp
    f, n, d_f = params[..., 0], params[..., 1], params[..., 2]
    w = xp.maximum(layout.fcap / (d_f - f) - _W_MIN, 0)  # fcap / inf = 0
    coords = [xp.log(f) - xp.log(layout.fcap - f), xp.log(n), w.astype(f.dtype)]
    for name in nuisance_names(nuisances):
        coords.append(xp.full_like(f, NULL.get(name, 0.0)))
    return xp.concatenate(coords, axis=-1)


def theta(y: Float[Array, " P"], layout: _Layout, nuisances: tuple[str, ...] = ()) -> Array:
    """The value of every slot in its statistical units: focal length (m), f-number, focus power
    `u = 1 / d_f` (diopters, 1/m: finite and smooth through infinity, where `d_f` is not), then
    the nuisances' parameters (gain, offset, ...). The statistics are computed in these; `solve._assemble` maps the focus power
    to the focus distance at the end."""
    f, n, w = _fields(y, layout)
    free = layout.use[:, 2]
    # u = 1 / (f + fcap / w) = w / (fcap + f w), without the round trip through d_f.
    u = jnp.where(free, w / (layout.fcap + f * w), 1 / layout.base[:, 2])
    out = [f, n, u]
    t = f.shape[0]
    for k in range(len(nuisance_names(nuisances))):
        out.append(y[(3 + k) * t : (4 + k) * t])
    return jnp.concatenate(out)


def theta_floor(layout: _Layout, nuisances: tuple[str, ...] = ()) -> Float[_Arr, " P"]:
    """An absolute scale under which a slot's value counts as 0, per slot of `theta`: `1 / fcap`
    (diopters, the power of the nearest depth) for the focus power, which is 0 at infinity, and
    the smallest normal number for the others. Comparisons of solutions and the test for
    undetermined fields measure a change against `max(|theta|, floor)`."""
    xp = np if isinstance(layout.fcap, np.ndarray) else jnp
    tiny = xp.full_like(layout.fcap, jnp.finfo(layout.fcap.dtype).tiny)
    out = [tiny, tiny, 1 / layout.fcap]
    out += [tiny] * len(nuisance_names(nuisances))
    return xp.concatenate(out)


def lenses(y: Float[Array, " P"], layout: _Layout) -> ThinLens:
    """The lens of every target, a `ThinLens` with fields `(T,)`."""
    p = natural(y, layout)
    return ThinLens(p[:, 0], p[:, 1], p[:, 2], p[:, 3])
