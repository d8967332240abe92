"""Check the derivatives of your own composition of jaxdof against finite differences.

    python examples/gradient_check.py

A loss built from `jaxdof.render` (here: a photometric loss between a render and a target, with
the lens, the image and the depth map all as inputs) is checked with `jax.test_util.check_grads`
in float64, forward and reverse mode. Two rules make the check meaningful:

- Give every length in a unit in which no argument is small next to the finite-difference step
  (`eps = 1e-4`): here millimetres (focal length 85, focus distance 3000, pixel pitch 0.15). In
  metres the focal length (0.085) would move by a tenth of a percent per step. The circle of
  confusion is a ratio of lengths, so the unit cancels.
- Keep the evaluation point away from the places where the blur is not differentiable: the focus
  plane (|1 - d_f/d| has a kink) and radii of half a pixel (below it a pixel is left as is).
"""

import jax
import jax.numpy as jnp
import numpy as np
from jax.test_util import check_grads

import jaxdof


MM = 1000.0  # metres -> millimetres
MAX_RADIUS = 5.0  # static filter window (pixels), larger than every circle below


@jax.jit
def loss(focal_length, f_number, focus, image, depth, target):
    """Your composition: render through a lens, compare with a photo, add a prior on N."""
    lens = jaxdof.ThinLens(focal_length, f_number, focus, 1.5e-4 * MM)
    rendered = jaxdof.render(image, depth, lens, max_radius=MAX_RADIUS)
    return jnp.mean((rendered - target) ** 2) + 1e-3 * jnp.log(f_number) ** 2


def main():
    jax.config.update("jax_enable_x64", True)  # finite differences need float64
    rng = np.random.default_rng(0)
    h, w = 10, 12
    image = jnp.asarray(rng.uniform(size=(h, w, 3)))
    # Depths 1.6 .. 2.4 m, all nearer than the 3 m focus: radii 1.0 .. 3.6 px, none at a kink.
    depth = jnp.asarray(np.linspace(1.6, 2.4, h * w).reshape(h, w)[::-1] * MM)
    target = jnp.asarray(rng.uniform(size=(h, w, 3)))
    focal_length, f_number, focus = jnp.asarray(0.085 * MM), jnp.asarray(2.0), jnp.asarray(3.0 * MM)

    r = jaxdof.coc_radius(depth, jaxdof.ThinLens(focal_length, f_number, focus, 1.5e-4 * MM))
    print(f"circle radii {float(r.min()):.2f} .. {float(r.max()):.2f} px (window {MAX_RADIUS})")

    args = (focal_length, f_number, focus, image, depth, target)
    # Tolerances: central differences with eps=1e-4 have truncation error ~eps^2 * f''' ~ 1e-8
    # relative; check_grads' default float64 tolerance (1e-5) has ample margin above that.
    check_grads(loss, args, order=1, modes=("fwd", "rev"), eps=1e-4)
    grads = jax.grad(loss, argnums=(0, 1, 2))(*args)
    print("d loss / d (f [1/mm], N, focus [1/mm]) =", ", ".join(f"{float(g):.3e}" for g in grads))
    print("gradients match finite differences (forward and reverse mode)")


if __name__ == "__main__":
    main()
