"""One default fit (`auto`) or one with the previous default forced (`plain`: soft, no footprint, no
edge weight) of a cached ray-traced scene, in this process; prints its wall time (compiling included)
as JSON. Issue 21's cost goal on scenes without depth edges is the ratio of the two, timed as whole
processes in turns:

    farm-bench -n 3 --warmup 0 --vs "python fits/treatment_cost.py slant 0.03 1.8 plain" \\
        -- python fits/treatment_cost.py slant 0.03 1.8 auto
"""

from __future__ import annotations

import json
import sys
import time

import jax
from _raytraced_fits import default_init
from _raytraced_scenes import default_inputs

import jaxdof


PLAIN = dict(method="soft", footprint=False, edge_weight=False)


def main(scene: str, a: float, d: float, variant: str) -> None:
    image, z, photo = default_inputs(scene, a, d)
    kw = {} if variant == "auto" else PLAIN
    t = time.perf_counter()
    res = jaxdof.fit_lens(image, z, photo, default_init(a, d), **kw)
    jax.block_until_ready(res.lenses.focus_distance)
    out = dict(scene=scene, a=a, d=d, variant=variant, seconds=time.perf_counter() - t)
    print(json.dumps({**out, "steps": int(res.num_steps), "treatment": str(res.treatment)}))


if __name__ == "__main__":
    main(sys.argv[1], float(sys.argv[2]), float(sys.argv[3]), sys.argv[4])
