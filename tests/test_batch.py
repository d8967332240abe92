"""`render_batch` and `fit_batch` shard the batch over devices and give the single-device numbers.

Several devices on one CPU need `XLA_FLAGS=--xla_force_host_platform_device_count=4` before JAX
starts, so the multi-device check runs in a subprocess.
"""

import os
import subprocess
import sys
import textwrap

import jax
import numpy as np
import pytest

import jaxdof
from jaxdof import ThinLens


SCRIPT = textwrap.dedent(
    """
    import jax
    jax.config.update("jax_enable_x64", True)
    import numpy as np
    import jaxdof
    from jaxdof import ThinLens

    assert len(jax.devices()) == 4, jax.devices()
    rng = np.random.default_rng(0)
    H, W, R = 9, 8, 2.5
    images = rng.uniform(size=(8, H, W, 3))
    depths = rng.uniform(1.0, 4.0, (8, H, W))
    # pitch chosen so that the radii are a few pixels
    lenses = ThinLens(
        focal_length=np.full(8, 0.05), f_number=rng.uniform(2.0, 4.0, 8),
        focus_distance=rng.uniform(1.5, 3.0, 8), pixel_pitch=np.full(8, 2e-4),
    )
    cpu0 = jax.devices()[0]

    def single_device(images, depths, lens, lens_axis):
        f = jax.vmap(lambda i, d, l: jaxdof.render(i, d, l, max_radius=R), in_axes=(0, 0, lens_axis))
        put = lambda t: jax.device_put(t, cpu0)
        return np.asarray(jax.jit(f)(put(images), put(depths), put(lens)))

    # one lens per scene, 8 scenes on 4 devices: each device renders two
    out = jaxdof.render_batch(images, depths, lenses, max_radius=R)
    assert len(out.sharding.device_set) == 4, out.sharding
    np.testing.assert_allclose(
        np.asarray(out), single_device(images, depths, lenses, 0), rtol=0, atol=1e-13
    )
    # one lens for every scene, 6 scenes (padded to 8, padding dropped)
    shared = ThinLens(0.05, 2.0, 2.0, 2e-4)
    out = jaxdof.render_batch(images[:6], depths[:6], shared, max_radius=R)
    assert out.shape == (6, H, W, 3)
    np.testing.assert_allclose(
        np.asarray(out), single_device(images[:6], depths[:6], shared, None), rtol=0, atol=1e-13
    )
    # the opt-in footprint correction and a 2x input (8 x 8 -> 4 x 4), passed through
    kw = dict(max_radius=R, footprint=True, downsample=2)
    out = jaxdof.render_batch(images[:, :8, :8], depths[:, :8, :8], lenses, **kw)
    f = jax.vmap(lambda i, d, l: jaxdof.render(i, d, l, **kw))
    want = jax.jit(f)(*(jax.device_put(t, cpu0) for t in (images[:, :8, :8], depths[:, :8, :8], lenses)))
    assert out.shape == (8, 4, 4, 3)
    np.testing.assert_allclose(np.asarray(out), np.asarray(want), rtol=0, atol=1e-13)
    print("OK")
    """
)


def _run_on_four_cpu_devices(script: str) -> None:
    env = dict(
        os.environ, XLA_FLAGS="--xla_force_host_platform_device_count=4", JAX_PLATFORMS="cpu"
    )
    proc = subprocess.run(
        [sys.executable, "-c", script], env=env, capture_output=True, text=True, timeout=900
    )
    assert proc.returncode == 0, proc.stdout + proc.stderr
    assert proc.stdout.strip().endswith("OK")


def test_sharded_render_matches_single_device():
    _run_on_four_cpu_devices(SCRIPT)


FIT_SCRIPT = textwrap.dedent(
    """
    import jax
    jax.config.update("jax_enable_x64", True)
    import numpy as np
    import jaxdof
    from jaxdof import ThinLens

    assert len(jax.devices()) == 4, jax.devices()
    rng = np.random.default_rng(1)
    B, H, W, R = 6, 14, 14, 4.0
    images = rng.uniform(0.2, 0.8, (B, H, W))
    # a slanted plane wholly behind the focus plane: no near/far ambiguity for a single start
    depths = np.broadcast_to(np.linspace(2.2, 5.0, W), (B, H, W)).copy()
    truth = ThinLens(np.full(B, 0.05), rng.uniform(1.6, 2.4, B), rng.uniform(1.4, 1.7, B),
                     np.full(B, 1e-4))
    targets = np.asarray(jax.vmap(lambda i, d, l: jaxdof.render(i, d, l, max_radius=R))(
        images, depths, truth))
    # one start per scene, 15 % off in N and 8 % in focus distance (solve_lens has no multi-start:
    # from one shared start a scene can settle in the far-side basin, as fit_lens's starts avoid)
    init = ThinLens(truth.focal_length, truth.f_number * 1.15, truth.focus_distance * 0.92,
                    truth.pixel_pitch)

    # 6 scenes on 4 devices: padded to 8, the padding dropped
    got = jaxdof.fit_batch(images, depths, targets, init, max_radius=R, max_steps=60)
    assert got.lenses.f_number.shape == (B, 1)
    assert len(got.lenses.f_number.sharding.device_set) == 4
    one = lambda i, d, t, l: jaxdof.solve_lens(i, d, t, l, max_radius=R, max_steps=60)
    cpu0 = jax.devices()[0]
    put = lambda x: jax.device_put(x, cpu0)
    want = jax.jit(jax.vmap(one))(put(images), put(depths), put(targets), put(init))
    for field in ("f_number", "focus_distance"):
        a, b = getattr(got.lenses, field), getattr(want.lenses, field)
        # the same solve on other devices: float64 rounding, amplified by the solver's steps
        np.testing.assert_allclose(np.asarray(a), np.asarray(b), rtol=1e-9, atol=0)
        # and it recovered the truth (noise-free targets)
        np.testing.assert_allclose(np.asarray(a)[:, 0], getattr(truth, field), rtol=1e-6)
    assert np.asarray(got.success).all()
    print("OK")
    """
)


def test_sharded_fit_matches_single_device():
    _run_on_four_cpu_devices(FIT_SCRIPT)


def test_render_batch_takes_a_method_object():
    """A method object (here with a key, an array leaf) or its alias, as `render` takes them."""
    rng = np.random.default_rng(2)
    images, depths = rng.uniform(size=(3, 5, 6)), rng.uniform(1.0, 4.0, (3, 5, 6))
    lens = ThinLens(0.05, 2.0, 2.0, 2e-4)
    method = jaxdof.Jitter(samples=4, key=jax.random.key(3))
    out = jaxdof.render_batch(images, depths, lens, method=method, max_radius=2.0)
    for b in range(3):
        one = jaxdof.render(images[b], depths[b], lens, method=method, max_radius=2.0)
        # jit(vmap) and eager run the same operations; XLA may fuse them differently (a few ulp)
        np.testing.assert_allclose(np.asarray(out[b]), np.asarray(one), rtol=0, atol=1e-13)
    alias = jaxdof.render_batch(images, depths, lens, method="hard", max_radius=2.0)
    want = jaxdof.render_batch(images, depths, lens, method=jaxdof.Hard(), max_radius=2.0)
    np.testing.assert_array_equal(np.asarray(alias), np.asarray(want))


def test_bad_batches_are_rejected():
    images, depths = np.ones((2, 4, 4)), np.full((2, 4, 4), 2.0)
    lens = ThinLens(0.05, 2.0, 1.5, 2e-4)
    with pytest.raises(ValueError, match="same B, H, W"):
        jaxdof.render_batch(images, depths[:1], lens)
    three = ThinLens(np.full(3, 0.05), np.full(3, 2.0), np.full(3, 1.5), np.full(3, 2e-4))
    with pytest.raises(ValueError, match=r"shape \(2,\)"):
        jaxdof.render_batch(images, depths, three)
    with pytest.raises(ValueError, match="is not a filter method"):
        jaxdof.render_batch(images, depths, lens, method="nope")
    with pytest.raises(ValueError, match="no leading batch axis"):
        jaxdof.shard_batch(np.float64(1.0), jaxdof.batch_mesh())
    with pytest.raises(ValueError, match="same B, H, W"):
        jaxdof.fit_batch(images, depths, images[:1], lens, max_radius=2.0)
    with pytest.raises(ValueError, match=r"shape \(2,\)"):
        jaxdof.fit_batch(images, depths, images, three, max_radius=2.0)
