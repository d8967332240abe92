import importlib.util
import os
import pathlib


# The default run is compile-bound (hundreds of small programs, each run a few times): XLA's
# backend at optimisation level 0 compiles them faster. The default run on 2 cores: 402 s, 336 s
# with the compilation cache below, 266 s with both (all passing). Set before JAX starts its
# backend; an XLA_FLAGS already set is kept (.ci/run's last step sets it empty, so that the
# default level, which users run, is tested too). The slow run compiles at level 0 as well: it
# reuses the default run's programs from the cache below.
os.environ.setdefault("XLA_FLAGS", "--xla_backend_optimization_level=0")

import jax  # noqa: E402
import jax.random as jr  # noqa: E402
import pytest  # noqa: E402


# The whole session runs with x64 on, rank promotion raising and strict dtype promotion: float32
# behaviour is tested with explicit float32 arrays (strict promotion raises on any silent mix with
# float64), and what needs JAX's default config (x64 off: float32 defaults, int32 indices) runs in
# a subprocess. Switching x64 mid-session recompiles everything compiled under the other setting.
jax.config.update("jax_enable_x64", True)
jax.config.update("jax_numpy_rank_promotion", "raise")
jax.config.update("jax_numpy_dtype_promotion", "strict")

# Compiled executables kept on disk (`.jax_cache/` beside `tests/`, or JAX_COMPILATION_CACHE_DIR):
# the two xdist workers compile many of the same programs, a test re-jits what another compiled
# under a new wrapper, and the mapping fixture below drops the in-memory caches (from a cold cache:
# test_fit + test_adequacy + test_treatment 136 s without, 104 s with). The size bound turns on
# JAX's file lock (`filelock`), which keeps one worker from reading an entry the other is still
# writing; entries are keyed by the program, the compile options (XLA_FLAGS) and jax's version.
# Without `filelock` (an environment installed before the `test` extra listed it) no cache: JAX
# refuses the bound without the lock, and unlocked entries could be read half written.
if importlib.util.find_spec("filelock") is not None:
    if jax.config.jax_compilation_cache_dir is None:
        jax.config.update(
            "jax_compilation_cache_dir", str(pathlib.Path(__file__).parents[1] / ".jax_cache")
        )
    jax.config.update("jax_persistent_cache_min_compile_time_secs", 0.05)
    jax.config.update("jax_compilation_cache_max_size", 2 * 2**30)


@pytest.fixture
def getkey():
    """A fresh, deterministic PRNG key per call."""
    keys = iter(jr.split(jr.PRNGKey(5678), 1000))
    return lambda: next(keys)


@pytest.fixture(autouse=True)
def _x64_stays_on():
    """Fail the test that leaves x64 off (and switch it back), rather than the tests after it."""
    yield
    if not jax.config.jax_enable_x64:
        jax.config.update("jax_enable_x64", True)
        pytest.fail("the test left jax_enable_x64 off; run float32 code on float32 arrays instead")


@pytest.fixture(autouse=True)
def _release_compiled_code():
    """After a test, drop the compiled executables once the worker holds over 20,000 memory
    mappings (`jaxdof.internal.release_compiled_code`): two slow-run workers that kept them all
    segfaulted inside the compiler at the kernel's limit (vm.max_map_count 65530)."""
    yield
    # imported here: the config above is set before anything of jaxdof is imported
    from jaxdof.internal import release_compiled_code

    release_compiled_code(max_maps=20_000)


def _listed(name: str) -> frozenset[str]:
    """The test ids of a list beside this file: file::function (every parametrisation) or
    file::function[id], one per line; `#` starts a comment line."""
    text = (pathlib.Path(__file__).parent / name).read_text()
    return frozenset(t.strip() for t in text.splitlines() if t.strip() and not t.startswith("#"))


# The `slow` marker, from one list (tests/slow_tests.txt: file::function, with its provenance).
_SLOW = _listed("slow_tests.txt")


# The `extended` marker (also `slow`): long validations that CI's 90 minutes leave out, run by
# hand with `-m extended` (tests/extended_tests.txt says why each is out and what in CI covers it).
_EXTENDED = _listed("extended_tests.txt")


@pytest.hookimpl(tryfirst=True)  # before `-m` deselects by marker
def pytest_collection_modifyitems(items):
    for item in items:
        function = item.nodeid.split("[")[0]
        if function in _SLOW:
            item.add_marker(pytest.mark.slow)
        if function in _EXTENDED or item.nodeid in _EXTENDED:
            item.add_marker(pytest.mark.slow)
            item.add_marker(pytest.mark.extended)


# Each test's duration as it ends, appended to the file named by JAXDOF_TEST_TIMES (tab-separated:
# seconds, outcome, test id): the figures for choosing the slow set, and for CI's budget, survive a
# run that is stopped before pytest's own `--durations` report (printed only at the end).
# (xdist's workers call the hook too, and send the same reports on: only the controller writes.)
_TIMES = None if "PYTEST_XDIST_WORKER" in os.environ else os.environ.get("JAXDOF_TEST_TIMES")


def pytest_runtest_logreport(report):
    # every call, and a set-up or tear-down that took a second (a module's fixture) or failed
    if _TIMES and (report.when == "call" or report.duration > 1 or report.outcome == "failed"):
        with open(_TIMES, "a", encoding="utf-8") as out:
            out.write(f"{report.duration:.1f}\t{report.when}:{report.outcome}\t{report.nodeid}\n")
