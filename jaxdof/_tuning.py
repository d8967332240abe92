"""Every measured crossover and cost constant of jaxdof, with its provenance (STYLE.md, item 18).

**What belongs here.** A constant that changes only how fast (or in how much memory) a result is
computed, never the result beyond float rounding, and whose value was read off a measurement: the
radius from which row spans beat the dense gather, the cost of one FFT level in gather taps, the
size up to which a loop is written out. Definitions stay with their code: mathematical constants
(`_overlap._SERIES_BELOW`, `_filters/soft._T2_MAX`), constants a proof fixes
(`_filters/spans.TAPS`), constants that change the numbers (`_filters/jitter.PATTERNS`,
`_corrections._TABLE_MAX`, `_corrections._VARIANCE_COLUMNS`, `_filters/occlusion.DEFAULT_JUMP`),
and the fitting policy (`_fit/strategies.py`: `_WINDOWS`, `_PYRAMID_*`, `_COARSE_TOL`;
`_fit/layout._CLIP`), which changes which lens a fit returns or when it stops. One exception,
at the end: the rules by which `fit_lens` chooses its treatment of a scene (`TREATMENT_*`),
which change the result and are measured on the tuning half of the ray-traced scenes
(`python fits/treatments.py`), not by `fits/tune.py`.

**Re-measuring.** `python fits/tune.py` asks each constant's question again on the current machine
and prints a table (name, old value, measured value) and the lines to paste here;
`python fits/tune.py --only NAME` re-measures one. After pasting, update the constant's comment
with the new figures and the run's conditions (the script prints them). Semi-internal access:
`jaxdof.internal.tuning`.

**Where they were measured.** Unless a comment says otherwise: a 2-core AMD EPYC CPU shared with
other jobs, jax/jaxlib 0.10.2, float32, jitted; "one run" means one interleaved run whose ratios,
not absolute times, are what to read.

Measured choices that are code rather than a number (no constant to re-measure; their figures stay
beside the code): the residual's Jacobian-materialising JVP (`_fit/residual.py`: 1.5-1.9x less
time per solve, 24 x 24 scene of `fits/recover.py`); no coarse pyramid level from one start
(`_fit/fit.py`, `_set_up`: 0.5-0.7x the speed otherwise); one scattered index per source in
`_filters/aperture.py` (0.4-0.45x the forward time); channels first in
`tabulated._classes_written_out` and in `layered`'s FFTs; a weight ending in a division in
`soft._weight_and_slope` (2.8-3.4x slower otherwise); the supersample count's sub-rows summed one
at a time (3.5-5x slower as an array); layered's level search by min-reductions instead of a sort
(14 ms of 21 ms at 256^2 before).
"""

from __future__ import annotations

import contextlib
import math
from collections.abc import Iterator


# --------------------------------------------------------------------------------------------
# Row spans against the dense gather (`_filters/spans.py`, `jitter.py`, `supersample.py`)
# --------------------------------------------------------------------------------------------

#: The soft filter (`method="soft"`, no blades) takes row spans when `max_radius >=` this, the dense
#: gather below it. Read by `jaxdof/_filters/spans.py` (`exact_soft_filter`, and through it
#: `coc_filter`, `render` and `fit_lens`).
#:
#: Measured 2026-12-01 (`python fits/tune.py --only SPANS_MIN_RADIUS --rounds 9`;
#: 2-core AMD EPYC shared with other jobs, load average 4-12; jax 0.10.2, git 7ae13c6): 256^2 RGB
#: float32, radii uniform in [R/2, R], jitted forward, medians of 9 interleaved rounds of wall time.
#: spans / dense time, three runs:
#:
#:     R     8    12    16    20    24    32    36    40    44    48    64
#:     a   5.74  3.03  2.37  2.05  1.73  0.85   -    0.83   -    0.58  0.42
#:     b   4.31  3.44  2.39  1.77  1.56  1.08   -    0.60   -    0.73  0.37
#:     c     -     -   2.41    -     -   1.11  0.70  0.81  0.67  0.72    -
#:
#: The spans are not slower from R = 40 on in every run; at R = 16 the default is now the dense
#: gather, the faster path (with 12 it took the spans, 2.4x the dense gather's time). Smaller
#: frames cross earlier, larger ones no later (`--size`): 64^2: 20 (spans / dense 1.33 at 16, 0.84
#: at 20, 0.38 at 32); 128^2: 24 (1.29 at 20, 0.94 at 24, 0.67 at 32); 1024^2, two runs: 40 (1.41,
#: 1.26 at 32; 0.84 at 40; 0.86, 0.83 at 48; 0.53 at 64). A JVP along the image and the radius map
#: (`--mode jvp`, 256^2) crosses earlier: 1.15 at 24, 0.72 at 32.
#:
#: History: 12 from `python fits/bench_speed.py --paths-only` (commit bbb9139, 2026-11-23; 256^2
#: RGB, radii uniform in [0, R], CPU time: spans lost at R = 8 and won forward and fwd+grad from
#: 12 on), measured before the dense gather became ~13x faster. Later, on a quiet
#: 2-core machine (256^2, radii in [R/2, R], forward, dense vs spans): R = 12: 12 vs 48 ms, 16: 19
#: vs 69, 32: 68 vs 151, 48: 190 vs 165, 64: 329 vs 211 (R = 16's default 3.7x the faster path).
SPANS_MIN_RADIUS = 40.0

#: Inside a Jacobian of renders (`jaxdof/_filters/spans.in_jacobian`: `fit_lens`'s residual builds
#: one per solver step, the free fields' tangents sharing one primal), the soft filter takes row
#: spans from this window radius on, by the image's channels `C` (the entry of the first key
#: `>= C`). The dense gather's tangent differentiates the exact area of every tap of the window;
#: the spans' only of the boundary taps, so spans win far earlier than forward; but their scatters
#: carry every channel, while the dense gather's weights serve all channels at once.
#:
#: Measured 2026-12-06 (`python fits/fit_spans.py`, report `fits/results/fit_spans.md`; 2-core
#: AMD EPYC shared with other jobs; jax 0.10.2, git da520f6; float32): `jax.jacfwd` of
#: `jaxdof.render(..., method="soft")` with respect to (N, d_f) on a mosaic of 25 tiles with halos
#: of the window, circles from 0 to (W - 1) / 1.5 px, medians of 5 rounds in turns. Spans / dense
#: time, two runs (a: the report; b: an earlier run of the same study):
#:
#:     W        8     12    16    20    24    32    40    48
#:     C=1 a  1.11  1.21  0.70  0.86  0.54  0.40  0.37  0.28
#:     C=1 b  1.29  1.01  0.90  0.61  0.61  0.40  0.35  0.28
#:     C=3 a  2.43  2.00  2.15  1.82  1.51  1.05  0.81  0.55
#:     C=3 b  3.95  3.00  2.62  1.65  1.31  1.05   -    0.64
#:
#: The forward render alone is within 0.82-1.33x between the paths at every one of these windows.
SPANS_MIN_RADIUS_JACOBIAN: dict[int | float, float] = {1: 16.0, math.inf: 40.0}

#: `method="jitter"` takes row spans from this window radius on, by the number of points `n`
#: (`spans.crossover_for`: the entry of the first key `>= n`). The dense gather compares `n`
#: thresholds at `~pi R^2` taps, the spans only at `O(R)` boundary taps but pay scatters that do not
#: shrink with `n`: the more points, the smaller the crossover. Read by `jaxdof/_filters/jitter.py`
#: (`jitter_filter`).
#:
#: Measured in commit 2547ad6 (2026-11-23), 2-core CPU, smooth depth, RGB float32, 48^2 and 256^2,
#: one run, spans / dense time: n = 4: 2.6-4.4 at R = 8, 1.2-1.6 at 16, 0.8-1.1 at 24; n = 16:
#: 1.3-1.6 at 8, 0.7-1.1 at 12, 0.5-0.8 at 16; n = 64: 0.7-1.3 at 8, 0.5-0.8 at 12. (Also measured
#: before the dense gather's speed-up; `fits/tune.py` re-measures it.)
#:
#: Re-measured 2026-12-01 (`python fits/tune.py`, one run, load average 6-14; not adopted:
#: one loaded run): 256^2, spans / dense: n = 4: 1.69 at R = 16, 1.10 at 20, 1.03 at 24, 0.78 at
#: 32; n = 16: 1.13 at 12, 0.82 at 16, 0.91 at 20; n = 64: 1.17 at 12, 0.88 at 16, 0.65 at 20. Read
#: off: {4: 24 (24 a tie), 16: 14, inf: 16}.
JITTER_SPANS_MIN_RADIUS = {4: 24.0, 16: 14.0, math.inf: 10.0}

#: `method="supersample"` (the disc; a polygon is always gathered) takes row spans from this window
#: radius on, by `n` (`spans.crossover_for`). The dense gather counts `n` sub-rows per mirror class,
#: the spans only at `O(R)` boundary taps but pay scatters. Read by `jaxdof/_filters/supersample.py`
#: (`supersample_filter`).
#:
#: Measured in commit c57b8e4 (2026-11-23), 2-core CPU, smooth depth, RGB float32, one run, spans /
#: dense time at 256^2: n <= 4: 2.0-2.2 at R = 24; n = 8: 1.5 at 16, 0.88 at 24; n = 16: 1.1 at 16,
#: 0.67 at 24. At 48^2 the spans win earlier (n = 2-4: 0.65-0.78 at R = 24; n = 8: 0.52 at 16): the
#: thresholds follow the larger frame.
#:
#: Re-measured 2026-12-01 (`python fits/tune.py`, one run, load average 6-14; not adopted:
#: one loaded run): 256^2, spans / dense: n = 4: 2.28 at R = 32, 1.32 at 40, 1.17 at 48, 0.79 at
#: 64; n = 8: 3.09 at 24, 1.63 at 32, 1.27 at 48, 0.65 at 64; n = 16: 1.89 at 20, 1.19 at 32, 0.91
#: at 40; n = 32: 1.86 at 16, 1.12 at 24, 0.79 at 32. Read off: {4: 64, 8: 64, 16: 40, inf: 32}: the
#: dense gather's speed-up moved every crossover up; the old table takes spans up to 3.1x slower.
SUPERSAMPLE_SPANS_MIN_RADIUS = {4: 32.0, 8: 24.0, 16: 20.0, math.inf: 16.0}

# --------------------------------------------------------------------------------------------
# Written out against looped
# --------------------------------------------------------------------------------------------

#: `count_below` compares against every threshold of the pixel's pattern (one gather of a row) up
#: to this many points per pattern, and runs a binary search beyond. Read by
#: `jaxdof/_filters/jitter.py` (`hit_thresholds`, `count_below`).
#:
#: Measured in commit 2547ad6 (2026-11-23), 2-core CPU, 256^2 RGB float32, R = 8, one run, compare
#: / binary-search time: 0.34x at n = 4, 0.37x at 16, 0.44x at 32, 1.36x at 64.
#:
#: Re-measured 2026-12-01 (`python fits/tune.py`, one run, load average 6-14; not adopted:
#: one loaded run): compare / search 0.45 at n = 4, 0.36 at 16, 1.03 at 32, 1.48 at 64: 32 stays.
COMPARE_ALL_MAX = 32

#: Up to this many sub-rows per pixel supersample's count writes its rows out (one fused
#: elementwise pass); beyond, a `fori_loop` over them keeps the program small. Read by
#: `jaxdof/_filters/supersample.py` (`_count_rows`).
#:
#: Measured in commit 2b49304 (2026-11-23), CPU, 32^2, R = 6: n = 64 written out compiled ~10x
#: slower (15.6 s against 1.5 s before the fused counts; 1.1 s with the loop).
#:
#: Re-measured 2026-12-01 (`python fits/tune.py`, one run, load average 6-14; not adopted:
#: one loaded run): 128^2, R = 4, written out / loop, run time: 1.32 at n = 4, 1.67 at 8, 1.36 at
#: 16, 29 at 32, 83 at 64; compile 1.3 / 1.2 s at 4, 4.8 / 1.8 s at 16, 11.1 / 2.1 s at 64. Read
#: off: 0 (the loop at every n).
UNROLL_ROWS = 16

#: Up to this many FFT levels `layered`'s level loop is written out (XLA overlaps the levels'
#: FFTs); beyond, a `lax.scan` keeps one spectrum live at a time. Read by
#: `jaxdof/_filters/layered.py` (`layered_filter`).
#:
#: Measured in commit 3898a3a (2026-11-23), CPU, 256^2 RGB float32, three planes, R = 8: written out
#: 0.8x the time of the scan. (Only three levels were timed; 8 bounds the live spectra.)
#:
#: Re-measured 2026-12-01 (`python fits/tune.py`, one run, load average 6-14; not adopted:
#: one loaded run): 256^2, R = 8, written out / scan 0.84 at L = 3, 0.89 at 8, 1.34 at 12, 0.88
#: at 16 (compile 5-7 s against 0.5 s): 8 stays.
UNROLL_LEVELS = 8

#: Up to this many taps (radius <= 2.5: a 5 x 5 window) the tabulated gather writes its loop over
#: mirror classes out (one weighted source per class read at each of its mirrored offsets) for XLA
#: to schedule as one program; beyond, a scanned class loop. Read by
#: `jaxdof/_filters/tabulated.py` (`tabulated_filter`).
#:
#: Measured in commits 3898a3a and a0598ee (2026-11-23), CPU, R = 2, three levels, RGB float32,
#: 256^2 and 1024^2, one run each: 0.75x the scanned class loop's time and 0.6-0.7x that of every
#: tap written out with its own look-up; with 37 taps or more the written-out program was slower
#: than the loop.
#:
#: Re-measured 2026-12-01 (`python fits/tune.py`, one run, load average 6-14; not adopted:
#: one loaded run): 256^2, written out / scanned 0.57 at 21 taps, 1.00 at 25, 6.3 at 37 and 45:
#: 25 stays.
FUSED_MAX_TAPS = 25

#: Up to this many levels the tabulated gather picks each pixel's weight by a chain of selects
#: (fused by XLA into the weighting pass); beyond, by `jnp.take` (a gather). Read by
#: `jaxdof/_filters/tabulated.py` (`_look_up`).
#:
#: Measured in commit 6f8a2aa (2026-11-23), CPU, R = 2, 512^2 and 1024^2, one run: the chain takes
#: 0.45-0.7x the time of `take` for L = 3 and 8, 0.9x for L = 16.
#:
#: Re-measured 2026-12-01 (`python fits/tune.py`, one run, load average 6-14; not adopted:
#: one loaded run): 512^2, R = 2, select / take 0.94 at L = 3 and 8, 1.22 at 16, 0.93 at 24, 1.01
#: at 32 (CPU time 0.88-1.06): no difference above the noise.
SELECT_MAX_LEVELS = 16

#: Up to this many distinct values an index map is built on the host by one comparison pass per
#: value; beyond, by `np.unique(..., return_inverse=True)` (an argsort). Read by
#: `jaxdof/_filters/common.py`, there as `_COMPARE_MAX_LEVELS` (`level_index`, through
#: `unique_with_index`: `auto`, `tabulated`, `layered`).
#:
#: Measured in commit 19460d0 (2026-11-23), CPU, a 1024^2 map of three levels: 1-2 ms, against
#: 20 ms for `np.unique`'s argsort and 8 ms for `np.searchsorted`; auto's inspection of a 1024^2
#: three-plane map 25.6 -> 9.5 ms (tabulated, R = 2), 31.4 -> 13.2 ms (layered, R = 8).
#:
#: Re-measured 2026-12-01 (`python fits/tune.py`, one run, load average 6-14; not adopted:
#: one loaded run): 1024^2, compare / argsort 0.11 at L = 3, 0.45 at 16, 0.64 at 24, 0.66 at 32,
#: 0.90 at 48, 1.00 at 64. Read off: 48.
COMPARE_MAX_LEVELS = 16

# --------------------------------------------------------------------------------------------
# FFT against gather (`layered`, `auto`)
# --------------------------------------------------------------------------------------------

#: One FFT level of `layered` costs about this many taps of its direct sum with a two-level table;
#: a tap costs `1 + L / 5` such taps with an `L`-level table (its look-up is a chain of `L`
#: selects). `layered` takes the direct sum when `taps (1 + L / 5) < FFT_LEVEL_COST_IN_TAPS * L`.
#: Read by `jaxdof/_filters/layered.py` (`direct_is_cheaper`).
#:
#: Measured in commit 0d53977 (2026-11-23), CPU, traced radius, RGB float32, direct / FFT time at
#: 256^2 (48^2 in brackets): R = 2 (21 taps): 0.57 (0.88) at L = 2, 0.15-0.34 (0.30-0.50) at
#: L = 4-16; R = 6 (137 taps): 1.04 (1.20) at L = 2, 0.44-0.65 (0.66-1.04) at L = 4-16; R = 8
#: (241 taps): 1.67 (1.70) at L = 2, 0.88 (1.06) at L = 8, 1.04 (1.83) at L = 16.
#:
#: Re-measured 2026-12-01 (`python fits/tune.py`, one run, load average 6-14; not adopted:
#: one loaded run): 256^2, R = 2-16, L = 2-16, direct / FFT: R = 2: 0.12-0.34 at L = 2-8, 1.53 at
#: 16; R = 4: 0.18-0.40; R = 8: 0.42-0.76 at L = 2-8, 1.21 at 16; R = 12: 1.39 at L = 2, 0.60 at 8,
#: 1.92 at 16; R = 16: 1.47-2.79. The rule with 56 errs at 5 of 20 points (worst 2.4x, R = 8,
#: L = 2), with 170 at 3 (worst 1.9x): the direct sum got cheaper, and FFTs of 16 levels (scanned)
#: cost less than of 8 (written out), which the rule's form does not follow. Read off: 170.
FFT_LEVEL_COST_IN_TAPS = 56.0

#: `method="auto"` takes FFT layers when the blurred levels number at most `taps /` this (one FFT
#: layer costs about this many taps of the tabulated gather). Read by `jaxdof/_filters/auto.py`
#: (`max_layers`, `choose_method`).
#:
#: Measured in commit 8d4e187 (2026-11-23), CPU, float32 RGB, 4 levels, 2-core machine at load ~5:
#: at 256 x 256 one layer cost ~60 taps (R = 8: 4 layers 9.1 ms, 241 taps 10.0 ms; R = 24:
#: 10.3 ms against 71 ms), at 64 x 64 ~70 taps (R = 8: 0.79 ms against 0.66 ms).
#:
#: Re-measured 2026-12-01 (`python fits/tune.py`, one run, load average 6-14; not adopted:
#: one loaded run): FFT / tabulated at 64^2: 1.45 at R = 4, 0.51 at 8, 0.27 at 16, 0.17 at 24; at
#: 256^2: 1.84, 2.51 (CPU time 0.90), 0.23, 0.17: a layer costs 25-82 taps (geometric mean 54), and
#: R = 8 falls on either side by frame: 64 stays.
LAYER_COST_IN_TAPS = 64.0

#: `method="auto"` never takes more FFT layers than this, whatever the window (the level
#: assignment and the spectra grow with it). Not a measurement: a cap (set in commit 8faa32a,
#: 2026-11-22); `LAYER_COST_IN_TAPS` decides below it. Read by `jaxdof/_filters/auto.py`
#: (`max_layers`).
MAX_LAYERS = 32

#: `method="auto"` takes the tabulated gather (weights computed once per distinct radius, looked
#: up per pixel) while the distinct radii number at most this fraction of the image's pixels, the
#: soft filter beyond. Not measured when it was set (commit 8d4e187, 2026-11-23: "the table is
#: small against the image"); `fits/tune.py` measures the tabulated gather against the soft filter
#: as the fraction grows. Read by `jaxdof/_filters/auto.py` (`choose_method`).
#:
#: Re-measured 2026-12-01 (`python fits/tune.py`, one run, load average 6-14; not adopted:
#: one loaded run): 256^2, R = 8, tabulated / soft 0.55 at L = HW/256, 1.00 at HW/32, 1.21 at
#: HW/8, 1.25 at HW/2, 1.67 at HW. Read off: 1 / 32.
TABLE_LEVELS_PER_PIXEL = 1 / 8


# --------------------------------------------------------------------------------------------
# Memory (`jaxdof.internal.estimate_memory`, the CLI's `render --memory`)
# --------------------------------------------------------------------------------------------

#: What `jaxdof.render` needs on top of its inputs, by kind of method: bytes per input pixel of
#: an RGB float32 frame (`"per_pixel"`), plus `"per_channel"` for every channel more or less than
#: three (the ones channel of `normalize` included), `"footprint"` per pixel with the footprint
#: correction, and `"fixed"` bytes once (compiled code, XLA's scratch). A banded render (each
#: band compiled, as `render` runs them) needs `"band_scale"` times the per-pixel bytes (by
#: kind; `"other"` for the kinds not measured) for the pixels of one band with its halo,
#: `"band_fixed"` bytes once, and `"band_frame"` per pixel of the whole frame (the output); a
#: method that prepares on the radius map (`Auto`, `Layered`) keeps that map (4 bytes per pixel)
#: besides. Read by `jaxdof/_render.py` (`estimate_memory`) and through it by the CLI's
#: `render --memory`.
#:
#: Measured 2026-12-02: peak resident memory (`ru_maxrss`) of one `jaxdof.render`
#: call in a fresh process, minus the process's before the call (JAX imported, inputs made), on
#: a 2-core AMD EPYC shared with other jobs, jax 0.10.2, float32, a random RGB image, depth 1-10 m,
#: largest circle `R`. Whole frames with `jaxdof.retain_freed_memory()` (as the CLI renders a
#: frame that fits); the per-pixel figures are the slopes between 1000 x 1500 and 2000 x 3000
#: (MB at 1.5 / 6 MP):
#:
#:     soft R = 8      300 / 855  -> 123       hard R = 8         259 / 618  -> 80
#:     soft R = 24         - / 907  (132)      supersample R = 8  343 / 887  -> 121
#:     soft R = 48     649 / 1996 -> 299       aperture R = 8     441 / 1280 -> 186
#:     soft R = 96     603 /  -   (at most)    layered R = 8      631 / 1817 -> 264
#:     Soft(blades=6)  780 /  -   (443)        auto R = 8         345 / 833  -> 108
#:
#: intercepts 100-200 MB (`fixed`). At 6 MP, soft R = 8: one channel 718 MB (11 bytes per pixel
#: per channel), `normalize` 1181 MB (+54 per pixel: more than a channel), `footprint` 2941 MB
#: (+348 per pixel). Bands (without the allocator setting, as the CLI renders bands), 2000 x 3000,
#: R = 8, bands of 250 / 1000 rows: soft 414 / 546 MB (59 per band pixel, 0.48 of the whole
#: frame's), layered 598 / 1058 (204, 0.77), aperture 408 / 757 (155, 0.83); soft at 6000 x 4000,
#: R = 15, `jaxdof render` sampled at each stage: bands of 1701 rows 1208 MB over the process
#: when the render started, so with the 6 MP intercept (366 MB) `band_fixed` about 290 MB and
#: `band_frame` 13 per frame pixel (the RGB output's 12); bands of 1334 rows 1346 MB, which with
#: those leaves 92 per band pixel (0.68 of the whole frame's): soft's `band_scale` is 0.75.
#: Re-measured 2026-12-07 (`tests/test_bands.py`'s measurement, VmHWM, soft, bands of 100 rows, at
#: 1.5 / 3 / 6 / 12 MP, R = 9.5 / 9.5 / 19 / 19): 171 / 185 / 285 / 372 MB, an intercept of about
#: 130 MB over the band's work and the frame's share; with `band_fixed` 300 MB the 1.5 and 3 MP
#: peaks were half the estimate. At 200 MB: 0.70-0.88 of it, and the 24 MP bands above 0.73 and
#: 0.95 of it (still under). `soft` below `SPANS_MIN_RADIUS` is the
#: dense gather, `soft_spans` from there on (R = 48 and 96 measured); `auto` is the largest of its
#: choices (soft, layered); `other` (a method of your own) the largest of the table.
RENDER_MEMORY = {
    "per_pixel": {
        "soft": 135.0,
        "soft_spans": 300.0,
        "soft_polygon": 450.0,
        "hard": 85.0,
        "supersample": 125.0,
        "aperture": 190.0,
        "layered": 265.0,
        "auto": 300.0,
        "other": 450.0,
    },
    "per_channel": 11.0,
    "normalize": 54.0,
    "footprint": 350.0,
    "fixed": 200 * 2**20,
    "band_scale": {"soft": 0.75, "layered": 0.8, "aperture": 0.85, "other": 1.0},
    "band_fixed": 200 * 2**20,
    "band_frame": 16.0,
}

#: What the `jaxdof` command holds while it renders, besides the render (`jaxdof/_cli/commands.py`,
#: `band_rows`): `"process"` bytes (Python, JAX and jaxdof imported, and what reading the files
#: leaves) and `"per_pixel"` bytes per input pixel (the image and depth as read: 16 for RGB
#: float32). Reading and writing the files peak on their own, before and after the render
#: (`_io`'s float64 conversions: not counted here).
#:
#: Measured 2026-12-02, `jaxdof render` of a 6000 x 4000 RGB float32 `.npy` frame
#: and its depth, resident memory sampled at each stage: 173 MB after the imports, 753 MB when
#: the render starts (24 bytes per pixel over the imports).
CLI_MEMORY = {"process": 200 * 2**20, "per_pixel": 24.0}


#: What `jaxdof.fit_lens` needs besides the frames it is given (`jaxdof._fit.tiles.estimate_fit_memory`,
#: the CLI's `fit --memory`): `"fixed"` bytes (runtime, compiled stages), `"frame"` bytes per input
#: pixel (the problem's float64 depth, the scout's reductions, the depth edges of a tile choice:
#: work on the whole frame whether or not the fit runs on tiles) and `"fitted"` bytes per photo pixel
#: rendered in the solve, per photo (the whole frame, or the tiles with their halos: at most 4x the
#: tile budget).
#:
#: Measured 2026-12-02, `fits/fullres.py` (one photo, RGB, soft, windows of 8-16 px,
#: peak `ru_maxrss` of `jaxdof fit` in a fresh process, minus what the CLI holds after reading,
#: `CLI_MEMORY` plus 12 bytes per photo pixel): whole frame 1.5 MP 1.24-1.27 GiB, 6 MP 3.81-4.23 GiB
#: (two runs; the larger gives 627 bytes per fitted pixel beside the intercept); on tiles of 2^17
#: pixels 1.5 / 6 / 24 MP 0.59-0.66 / 0.63-0.64 / 1.86-1.89 GiB (the slope between 6 and 24 MP:
#: 75 bytes per input pixel). Rounded up: the measured peaks are 0.68-0.97 of the estimate.
FIT_MEMORY = {"fixed": 0.4 * 2**30, "frame": 75.0, "fitted": 640.0}


# --------------------------------------------------------------------------------------------
# The treatment rules of `fit_lens` and `render(method="auto")` (`jaxdof/_scene.py`): they
# change the lens a fit returns. Re-measured by `python fits/treatments.py` (the default call
# against forced treatments on 12 ray-traced scenes x 4 lenses, half held out), not by
# `fits/tune.py`.
# --------------------------------------------------------------------------------------------

#: The footprint correction is on when the starting lens's median circle over the fitted pixels is
#: under this (px). Spreading a pinhole pixel with the circle-pixel overlap adds a blur variance
#: of 1/6 px^2 (both axes) to the lens's r^2/2, so K comes out short by about 1/(6 r^2): 1e-4 at
#: 40 px. The bar is what a fit can detect, not the 5 % goal: on large photos the standard errors
#: are that small. Measured (`fits/fullres.py --sizes 1.5 6 --defaults-only`, 2026-12-02): with the
#: bar at 5.8 px (0.5 % of K) the 6 MP photo, which integrates over its pixels, was fitted without
#: the correction and came back `inconsistent` (K -0.37 %, N 0.35 % off, se 0.25 %). The
#: correction now costs 0.03-0.8x the soft filter it feeds (`fits/results/footprint_cost.md`) and
#: the default fit of an edge-free scene 1.07-1.09x the plain one (`fits/treatment_cost.py`).
#: Before (`fits/treatments.py`, tuning half): without it (`plain`) slant's K errors were
#: -5.0, -1.7, -1.3, -1.3 % (median starting circles 0.8-2.8 px), with it every slant lens within
#: 1.6 %; 4 of the 48 ray-traced fits had median circles over 5.8 px (all within the goal).
TREATMENT_FOOTPRINT_BELOW = 40.0

#: The occlusion render and the edge weight are on when the fitted pixels within a starting circle
#: of a depth edge that matters (a circle over half a pixel on either side) are more than this
#: share. Chosen so that one short edge (a few dozen pixels of a 128 x 128 frame) does not switch
#: the model; at the study's starts every tuning scene with occlusion edges is far above it
#: (planes 0.09-0.22, occluders 0.18-0.35, thin 0.54-0.86) and the edge-free ones at 0.
TREATMENT_EDGE_MIN_SHARE = 0.005

#: The edge weight is used only while it keeps this share of the fitted weight: where the edges
#: are the scene the occlusion render alone fits what is there. At the study's starts the weight
#: keeps 0.71-0.93 of the frame on every scene but `thin` (0.30-0.55; dropped at A = 0.1 m,
#: d_f = 1.8 m). Not tuned further.
TREATMENT_EDGE_KEEP_MIN = 0.3

#: The photo's say (`jaxdof/_fit/select.py`): a treatment the scene chose is dropped when the fit
#: without it lowers the chi-square (the sum of squares over the noise variance, same pixels, same
#: number of parameters) by more than this. 10 is a p-value of 0.0016 for one degree of freedom,
#: so noise alone rarely switches a model the photo cannot tell from the other; a photo the other
#: model made lowers it by orders of magnitude more (the README's example: about 1e9 in float32).
SELECT_CHI2 = 10.0

#: The level of the score test that turns a nuisance (a gain and an offset per photo) on
#: (`jaxdof/_fit/select.py`): its false-alarm rate on photos without the nuisance. On noisy renders
#: of a two-slope scene (sigma 1 % of the mean) the statistic was 0.8-2.3 on 2 dof without an
#: exposure error and 4395 with the photo at 0.85 of the exposure.
SELECT_ALPHA = 1e-3

#: A colour photo is compared in its sRGB luma when its colour detail at the pixel scale
#: (`_fit.photo.chroma_detail`) is under this share of the all-in-focus image's: a camera JPEG
#: keeps its chroma at half resolution. Measured on the 12 ray-traced default-study photos
#: (one lens each): 0.09-0.24 as JPEG 4:2:0 (quality 75-98, with and without 2 % noise),
#: 0.30-0.68 as JPEG 4:2:2, 0.98-1.17 linear, as 8-bit PNG, as JPEG 4:4:4 and with 2 % noise;
#: a render resampled by quintic splines by 0.7 px and 1 % (`fits/nuisance_rate.py`) 0.76. The
#: command line reads a JPEG's subsampling from its header instead.
LUMA_CHROMA = 0.5

#: The standard error (photo pixels) of the chart's corners as `jaxdof.detect_chart` places them:
#: the largest corner error over the 16 ray-traced chart photos of `fits/chart.py` (8 poses and
#: lenses, circles of 0-11 px, linear and 8-bit JPEG; median 0.18 px, largest 0.52 px). It sizes
#: the uncertainty of the focal length in pixels found from the homographies
#: (`_chart._geometry.focal_stderr`), which scales the chart's depth and so the focus distance.
CHART_CORNER_PX = 0.5

#: With the focal length and the pixel pitch given and no focus distance, the chart's camera
#: takes `f_px = s / p` at the fitted focus (`_chart._calibrate._focused`); where the fit after
#: the alignment moves `f_px` by more than this share, the scene and the fit are made once more
#: at the new one. The chart's depth, and with it the focus distance, scales with `f_px`, so
#: this leaves the focus distance about 0.1 %, a twentieth of the 2 % goal; set so, not tuned.
CHART_REFOCUS = 1e-3

_NAMES = (
    "SPANS_MIN_RADIUS",
    "SPANS_MIN_RADIUS_JACOBIAN",
    "JITTER_SPANS_MIN_RADIUS",
    "SUPERSAMPLE_SPANS_MIN_RADIUS",
    "COMPARE_ALL_MAX",
    "UNROLL_ROWS",
    "UNROLL_LEVELS",
    "FUSED_MAX_TAPS",
    "SELECT_MAX_LEVELS",
    "COMPARE_MAX_LEVELS",
    "FFT_LEVEL_COST_IN_TAPS",
    "LAYER_COST_IN_TAPS",
    "MAX_LAYERS",
    "TABLE_LEVELS_PER_PIXEL",
    "RENDER_MEMORY",
    "CLI_MEMORY",
    "FIT_MEMORY",
    "LUMA_CHROMA",
    "CHART_CORNER_PX",
    "CHART_REFOCUS",
)


@contextlib.contextmanager
def override(**values) -> Iterator[None]:
    """Run with some tuning constants replaced, e.g. `with override(SPANS_MIN_RADIUS=16.0): ...`.

    For measuring a crossover (`fits/tune.py`) and for tests that force one side of a rule. The
    filters read these constants when they are traced, so compile afresh inside the block: a
    function jitted before keeps the value it was traced with. Not thread-safe (process-wide).
    """
    unknown = sorted(set(values) - set(_NAMES))
    if unknown:
        raise ValueError(f"not tuning constants: {unknown}; the table holds {_NAMES}")
    here = globals()
    saved = {name: here[name] for name in values}
    here.update(values)
    try:
        yield
    finally:
        here.update(saved)
