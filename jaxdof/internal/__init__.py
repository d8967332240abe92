"""Semi-internal jaxdof: the parts beneath the public API, for the studies in `fits/` and for
power users.

**No stability promise.** Anything here may change its signature, its numbers or its name, or go,
in any release and without deprecation (as `optimistix.internal` and `equinox.internal`). Code
that only renders or fits needs nothing from here: use `jaxdof` itself.

What is here (re-exports only):

- **Filter kernels**, with the switches that the method objects choose for you: the exact soft
  filter on a forced path (`exact_soft_filter(..., path="dense" | "spans" | "auto")`), the dense soft gather without the input checks of `jaxdof.coc_filter`
  (`soft_filter`), the gather loops it is built from (`gather`, `symmetric_gather`, over
  `tap_offsets(max_radius)`), and the kernels of the other methods (`supersample_filter`,
  `jitter_filter`, `layered_filter`, `tabulated_filter`, several with a `path=` switch), all on a channels-last image `(H, W, C)` and a radius map
  already clamped to `max_radius`; the level helpers `unique_with_index`, `level_index`.
- **Tuning**: `tuning`, the module of measured crossovers and cost constants
  (`jaxdof/_tuning.py`, re-measured by `fits/tune.py`; `tuning.override(NAME=value)` replaces
  constants for the duration of a block, for measurements and tests).
- **Fit helpers**: `auto_levels(shape, r_init)` (the automatic pyramid rule),
  `max_circle(lenses, depth)` (the largest circle of lenses over a depth map),
  `start_lenses(base, depth, *, free, starts, fcap=None)` (`fit_lens`'s starts),
  `record_stages()` (time the compiled stages of `fit_lens` calls:
  `with record_stages() as log: fit_lens(...)`).
- **Model adequacy**: `adequacy` (the between-tile test on a fit's residual and Jacobian),
  `ADEQUACY_ALPHA` (its default significance level).
- **Corrections**: `edge_distance` (distance to the nearest depth edge, under `jaxdof.edge_weight`),
  `kernel_variance` (the filter kernel's variance), `footprint_coefficient` (its table, which
  `jaxdof.footprint_prefilter` reads) and `fourth_order_coefficients` (the prefilter's two
  fourth-order terms, fitted to the lens's transfer function).
- **Memory and compiled code**: `estimate_memory` (a render's); `release_compiled_code` (drops
  the compiled executables once the process holds many memory mappings: for long loops of
  compiles).
- **Files**: `write_image`, the CLI's writer (linear light in; 16-bit PNG and TIFF, sRGB
  encoding), for studies that make their scenes as files.

Study-only code (the footprint candidates that lost, the textbook overlap) lives in `fits/`.
"""

# A renamed re-export is one ruff cannot tell from an unused import: hence the noqa below.
from .. import _tuning as tuning  # noqa: F401
from .._compiled import release_compiled_code as release_compiled_code
from .._corrections import (
    edge_distance as edge_distance,
    footprint_coefficient as footprint_coefficient,
    fourth_order_coefficients as fourth_order_coefficients,
    kernel_variance as kernel_variance,
)
from .._filters.common import (
    level_index as level_index,
    tap_offsets as tap_offsets,
    unique_with_index as unique_with_index,
)
from .._filters.jitter import jitter_filter as jitter_filter
from .._filters.layered import layered_filter as layered_filter
from .._filters.soft import (
    gather as gather,
    soft_filter as soft_filter,
    symmetric_gather as symmetric_gather,
)
from .._filters.spans import exact_soft_filter as exact_soft_filter
from .._filters.supersample import supersample_filter as supersample_filter
from .._filters.tabulated import tabulated_filter as tabulated_filter
from .._fit import (
    auto_levels as auto_levels,
    max_circle as max_circle,
    record_stages as record_stages,
    start_lenses as start_lenses,
)
from .._fit.adequacy import (  # noqa: F401
    ALPHA as ADEQUACY_ALPHA,
    adequacy as adequacy,
)
from .._io import write_image as write_image
from .._render import estimate_memory as estimate_memory
