"""The research API: `jit`, `vmap` and `grad` through `jaxdof.render` inside your own loss.

    python examples/research_api.py

Depth from defocus, written from scratch: given an all-in-focus image and a focus stack (three
photos of the same view focused at 1.5 m, 3 m and 6 m), recover the depth map. The depth map is
parameterised by inverse depth on a coarse 3 x 4 grid, upsampled bilinearly (a smooth surface
with 12 unknowns); the loss renders the whole stack with `jax.vmap` over a batched `ThinLens`,
and `jax.jit(jax.value_and_grad(loss))` drives a few hundred Adam steps.
"""

import jax
import jax.numpy as jnp
import numpy as np

import jaxdof


H, W = 24, 32
GRID = (3, 4)
MAX_RADIUS = 4.0  # static window (pixels): under jit the filter cannot size it from the data


def depth_map(inverse_grid):
    """Coarse inverse depth (1/m) -> a smooth (H, W) depth map in metres."""
    return 1.0 / jax.image.resize(inverse_grid, (H, W), method="linear")


def render_stack(image, depth, lenses):
    """One render per lens of a batched ThinLens (fields of shape (T,)) -> (T, H, W, C)."""
    return jax.vmap(lambda lens: jaxdof.render(image, depth, lens, max_radius=MAX_RADIUS))(lenses)


def loss(inverse_grid, image, lenses, photos):
    return jnp.mean((render_stack(image, depth_map(inverse_grid), lenses) - photos) ** 2)


def main():
    rng = np.random.default_rng(0)
    image = jnp.asarray(rng.uniform(0.1, 1.0, size=(H, W, 3)), jnp.float32)
    focus = np.array([1.5, 3.0, 6.0])
    ones = np.ones_like(focus)  # vmap maps every field, so each has the batch axis
    lenses = jaxdof.ThinLens(0.05 * ones, 2.0 * ones, focus, 0.006 / W * ones)  # 50 mm f/2
    # The unknown scene: a floor tilting away from 1.2 m to 8 m, with a dent (inverse depth, 1/m).
    truth = jnp.asarray(
        [[0.125, 0.14, 0.16, 0.18], [0.3, 0.5, 0.35, 0.3], [0.8, 0.7, 0.75, 0.83]], jnp.float32
    )
    photos = render_stack(image, depth_map(truth), lenses)

    step_fn = jax.jit(jax.value_and_grad(loss))
    x = jnp.full(GRID, 1 / 3.0, jnp.float32)  # start: everything at 3 m
    m = v = jnp.zeros_like(x)
    lr, b1, b2 = 0.02, 0.9, 0.999  # Adam: inverse depths are O(0.1-1) per metre
    for i in range(1, 301):
        value, g = step_fn(x, image, lenses, photos)
        m, v = b1 * m + (1 - b1) * g, b2 * v + (1 - b2) * g * g
        x = x - lr * (m / (1 - b1**i)) / (jnp.sqrt(v / (1 - b2**i)) + 1e-12)
        x = jnp.clip(x, 1 / 50, 1 / 0.5)  # stay in front of the lens, beyond the focal length
        if i % 50 == 0:
            print(f"step {i:3d}  loss {float(value):.3e}")
    err = np.abs(np.asarray(depth_map(x)) / np.asarray(depth_map(truth)) - 1)
    print(f"depth error: median {np.median(err):.2%}, max {err.max():.2%}")
    print("inverse depth (1/m), recovered:\n", np.round(np.asarray(x), 3))
    print("truth:\n", np.asarray(truth))
    assert np.median(err) < 0.05, "depth from defocus did not converge"


if __name__ == "__main__":
    main()
