"""`render_batch` shards the batch over devices and gives the single-device numbers.

Several devices on one CPU need `XLA_FLAGS=--xla_force_host_platform_device_count=4` before JAX
starts, so the multi-device check runs in a subprocess.
"""

import os
import subprocess
import sys
import textwrap

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
    print("OK")
    """
)


def test_sharded_render_matches_single_device():
    env = dict(
        os.environ, XLA_FLAGS="--xla_force_host_platform_device_count=4", JAX_PLATFORMS="cpu"
    )
    proc = subprocess.run(
        [sys.executable, "-c", SCRIPT], env=env, capture_output=True, text=True, timeout=600
    )
    assert proc.returncode == 0, proc.stdout + proc.stderr
    assert proc.stdout.strip().endswith("OK")


def test_bad_batches_are_rejected():
    images, depths = np.ones((2, 4, 4)), np.full((2, 4, 4), 2.0)
    lens = ThinLens(0.05, 2.0, 1.5, 2e-4)
    with pytest.raises(ValueError, match="same B, H, W"):
        jaxdof.render_batch(images, depths[:1], lens)
    three = ThinLens(np.full(3, 0.05), np.full(3, 2.0), np.full(3, 1.5), np.full(3, 2e-4))
    with pytest.raises(ValueError, match=r"shape \(2,\)"):
        jaxdof.render_batch(images, depths, three)
    with pytest.raises(ValueError, match="no leading batch axis"):
        jaxdof.shard_batch(np.float64(1.0), jaxdof.batch_mesh())
