"""Traced programs that a process keeps on disk, beside the compiled ones.

JAX's persistent compilation cache (`jaxdof.enable_compilation_cache`) skips XLA's compiler, but
its key is the lowered program, so every process still traces each stage of a fit (the Python
of the solver, the filters and their derivatives, under `vmap` and `jvp`) and lowers it before
it can look the executable up: most of a warm run on a photo of a few megapixels. Here a
compiled stage of `fit_lens` (`run_stage`) is kept as a `jax.export.Exported`, keyed by
everything the trace depends on:

- the stage (module and name) and every argument that is not an array, described in full (the
  types, fields and values of the equinox modules, solvers and layouts; functions by name);
- the shapes and dtypes of the array arguments;
- the source of the jaxdof package (a digest of its files), the versions of JAX, jaxlib, equinox,
  optimistix, lineax and numpy, the JAX settings that change a trace (x64, default precisions,
  promotion rules), the backend, and the tuning constants as they are (`_tuning.override`).

A second process with the same key deserializes the program and calls it (its executable then
comes from the compilation cache): no tracing. Only what can be named exactly is keyed: a class
or function from outside the packages above (a caller's own forward model, a `verbose`
callback), a closure or a lambda, or an object of an unknown kind makes the stage run as before,
as does a stage whose program cannot be exported (a host callback) and `jax_debug_nans`,
`jax_debug_infs` and `jax_disable_jit`, which change how programs run.
"""

from __future__ import annotations

import dataclasses
import functools
import hashlib
import importlib
import json
import os
import types
from collections.abc import Callable
from pathlib import Path
from typing import Any

import equinox as eqx
import jax
import numpy as np


#: The modules whose classes and functions a key may name: their code is part of the key through
#: the jaxdof digest and the packages' versions.
_TRUSTED = ("jaxdof", "equinox", "optimistix", "lineax", "jax", "jaxlib", "numpy", "builtins")
#: The traced programs' bound (bytes), least recently used evicted beyond it.
TRACED_MAX_BYTES = 512 * 2**20
_SUFFIX = ".traced"

_folder: Path | None = None
_max_bytes = TRACED_MAX_BYTES
_loaded: dict[str, tuple[Callable, object] | None] = {}  # None: not exportable


class _Unkeyable(Exception):
    """An argument the key cannot name exactly: the stage runs untouched."""


def use_folder(folder: Path | None, max_bytes: int = TRACED_MAX_BYTES) -> None:
    """Keep traced stages in `folder` (`None`: not at all)."""
    global _folder, _max_bytes
    _folder, _max_bytes = folder, int(max_bytes)
    _loaded.clear()


def folder() -> Path | None:
    """Where traced stages are kept (`None`: they are not)."""
    return _folder


def call(stage: Callable, *args) -> Any:
    """`stage(*args)` (an `equinox.filter_jit` function), its traced program from disk where one
    is kept under the same key, else traced, exported and kept."""
    if _folder is None or _config_changes_runs():
        return stage(*args)
    leaves: list = []
    try:
        inputs = _walk(args, leaves)
        described = [_named(getattr(stage, "__wrapped__", stage)), inputs]  # filter_jit's
    except _Unkeyable:
        return stage(*args)
    key = hashlib.sha256(json.dumps([_environment(), described]).encode()).hexdigest()
    if key not in _loaded:
        _loaded[key] = _read(key) or _export(stage, inputs, leaves, key)
    entry = _loaded[key]
    if entry is None:
        return stage(*args)
    run, template = entry
    try:
        return _rebuild(template, list(run(*leaves)))
    except Exception:  # noqa: BLE001 - a kept stage that does not run or rebuild: as before
        _loaded[key] = None
        return stage(*args)


def _setting(name: str):
    return getattr(jax.config, name)


def _config_changes_runs() -> bool:
    return any(_setting(f"jax_{k}") for k in ("debug_nans", "debug_infs", "disable_jit"))


# ---------------------------------------------------------------------------------------------
# The key.
# ---------------------------------------------------------------------------------------------


@functools.cache
def _source_digest() -> str:
    """A digest of every file of the jaxdof package: an edit makes new keys."""
    root = Path(__file__).parent
    h = hashlib.sha256()
    for path in sorted(root.rglob("*.py")):
        h.update(str(path.relative_to(root)).encode())
        h.update(path.read_bytes())
    return h.hexdigest()


@functools.cache
def _installed() -> list:
    """The source digest, the libraries' versions and the device: fixed for a process."""
    from importlib.metadata import version

    packages = [version(p) for p in ("jax", "jaxlib", "equinox", "optimistix", "lineax", "numpy")]
    device = jax.devices()[0]
    return [_source_digest(), packages, device.platform, device.device_kind]


def _environment() -> list:
    """What a trace reads besides its arguments: the installed code, the JAX settings, and the
    tuning constants (`_tuning.override` replaces them for a while; the filters read them as they
    are traced)."""
    from . import _tuning

    names = ("enable_x64", "default_matmul_precision", "numpy_rank_promotion")
    settings = [str(_setting(f"jax_{k}")) for k in (*names, "numpy_dtype_promotion")]
    return [_installed(), settings, [repr(getattr(_tuning, k)) for k in _tuning._NAMES]]


def _named(obj) -> list:
    """A class or function by its module and name, where the key can trust the name."""
    module = getattr(obj, "__module__", None) or ""
    name = getattr(obj, "__qualname__", None) or ""
    if module.split(".")[0] not in _TRUSTED or "<" in name or not name:
        raise _Unkeyable(obj)
    return [module, name]


def _walk(x, leaves: list):
    """`x` as JSON data that names it exactly, each array replaced by its place in `leaves`
    (where it is appended), its shape and dtype: the key of the inputs (with the stage), and the
    template that `_rebuild` fills with a program's outputs or inputs."""
    if eqx.is_array(x):
        leaves.append(x)
        weak = bool(getattr(getattr(x, "aval", x), "weak_type", False))
        return ["leaf", len(leaves) - 1, list(np.shape(x)), str(x.dtype), weak]
    # Exact types only: a subclass (an IntEnum, a namedtuple) would come back as its base.
    kind = type(x)
    if x is None or kind in (bool, int, str):
        return [type(x).__name__, x]
    if kind is float:
        return ["float", repr(x)]  # exact: the shortest repr round-trips
    if kind in (tuple, list):
        return [type(x).__name__, [_walk(v, leaves) for v in x]]
    if kind is dict:
        if not all(isinstance(k, str) for k in x):
            raise _Unkeyable(x)
        return ["dict", [[k, _walk(x[k], leaves)] for k in sorted(x)]]
    if kind is frozenset:
        if any(eqx.is_array(v) for v in x):
            raise _Unkeyable(x)
        items = [_walk(v, leaves) for v in x]
        return ["frozenset", sorted(items, key=json.dumps)]
    if isinstance(x, np.dtype):
        return ["dtype", str(x)]
    if isinstance(x, functools.partial):
        return ["partial", _walk([x.func, list(x.args), x.keywords], leaves)]
    if isinstance(x, (type, types.FunctionType, types.BuiltinFunctionType)):
        return ["named", _named(x)]
    if _named(type(x))[0].split(".")[0] == "jaxdof" and not dataclasses.is_dataclass(x):
        # jaxdof's own plain classes (`_Spec`): their attributes are all they hold
        attributes = getattr(x, "__dict__", None)
        if not isinstance(attributes, dict):
            raise _Unkeyable(x)
        items = [[k, _walk(attributes[k], leaves)] for k in sorted(attributes)]
        return ["attributes", _named(type(x)), items]
    if dataclasses.is_dataclass(x) and not isinstance(x, type):
        fields = []
        for f in _fields(x):
            value = getattr(x, f.name)
            if f.metadata.get("static") and any(eqx.is_array(v) for v in jax.tree.leaves(value)):
                raise _Unkeyable(x)  # values baked into the trace: not named by a shape
            fields.append([f.name, _walk(value, leaves)])
        return ["object", _named(type(x)), fields]
    raise _Unkeyable(x)


def _fields(x) -> tuple:
    return tuple(f for f in dataclasses.fields(x) if hasattr(x, f.name))


def _resolve(named: list) -> Any:
    module, name = named
    obj = importlib.import_module(module)
    for part in name.split("."):
        obj = getattr(obj, part)
    return obj


def _rebuild(t, leaves: list) -> Any:
    """The object that `_walk` described by `t`, with `leaves` in the arrays' places."""
    kind, value = t[0], t[1]
    if kind == "leaf":
        return leaves[value]
    if kind == "float":
        return float(value)
    if kind in ("tuple", "list"):
        items = [_rebuild(v, leaves) for v in value]
        return tuple(items) if kind == "tuple" else items
    if kind == "dict":
        return {k: _rebuild(v, leaves) for k, v in value}
    if kind == "frozenset":
        return frozenset(_rebuild(v, leaves) for v in value)
    if kind == "dtype":
        return np.dtype(value)
    if kind == "partial":
        func, args, keywords = _rebuild(value, leaves)
        return functools.partial(func, *args, **keywords)
    if kind == "named":
        return _resolve(value)
    if kind == "attributes":
        obj = object.__new__(_resolve(value))
        obj.__dict__.update({name: _rebuild(v, leaves) for name, v in t[2]})
        return obj
    if kind == "object":
        # as equinox's and dataclasses' own unflattening: the fields set, no __init__ run
        obj = object.__new__(_resolve(value))
        for name, v in t[2]:
            object.__setattr__(obj, name, _rebuild(v, leaves))
        return obj
    return value  # None, bool, int, str


# ---------------------------------------------------------------------------------------------
# Export, files.
# ---------------------------------------------------------------------------------------------


def _export(stage: Callable, inputs, leaves: list, key: str):
    """Trace `stage` on the arguments that `inputs` describes (with `leaves`), export it and keep
    it under `key`; `None` where the program or its outputs cannot be kept (the stage then runs
    as before)."""
    box: dict = {}

    def flat_stage(*arrays):
        out = stage(*_rebuild(inputs, list(arrays)))
        outputs: list = []
        box["template"] = _walk(out, outputs)
        return outputs

    try:
        # LAPACK and other custom calls carry no promise across jaxlib versions; these programs
        # are read back only by the jaxlib and the platform in their key.
        checks = [jax.export.DisabledSafetyCheck.custom_call(n) for n in _custom_calls()]
        exported = jax.export.export(jax.jit(flat_stage), disabled_checks=checks)(*leaves)
        data = json.dumps(box["template"]).encode()
        blob = bytes(exported.serialize())
    except Exception:  # noqa: BLE001 - any reason not to keep it: run the stage as it is
        return None
    _write(key, data, blob)
    return jax.jit(exported.call), box["template"]


@functools.cache
def _custom_calls() -> tuple[str, ...]:
    """The custom-call targets of jaxlib's linear algebra (LAPACK on the CPU)."""
    try:
        from jaxlib import lapack

        return tuple(name for rows in lapack.registrations().values() for name, *_ in rows)
    except (ImportError, AttributeError):
        return ()


def _path(key: str) -> Path:
    assert _folder is not None
    return _folder / f"{key}{_SUFFIX}"


def _read(key: str):
    try:
        raw = _path(key).read_bytes()
        n = int.from_bytes(raw[:8], "little")
        template = json.loads(raw[8 : 8 + n])
        exported = jax.export.deserialize(bytearray(raw[8 + n :]))
        os.utime(_path(key))  # recently used
    except Exception:  # noqa: BLE001 - missing, cut short or foreign: traced again and rewritten
        return None
    return jax.jit(exported.call), template


def _write(key: str, template: bytes, blob: bytes) -> None:
    """Written whole or not at all (a temporary file renamed), then the folder trimmed to its
    bound, oldest use first; a folder that cannot be written costs the speed only."""
    path = _path(key)
    tmp = path.with_suffix(f".{os.getpid()}.tmp")
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        tmp.write_bytes(len(template).to_bytes(8, "little") + template + blob)
        os.replace(tmp, path)
        _trim(path.parent)
    except OSError:
        tmp.unlink(missing_ok=True)


def _trim(folder: Path) -> None:
    files = []
    for p in folder.glob(f"*{_SUFFIX}"):
        try:
            st = p.stat()
        except OSError:
            continue
        files.append((st.st_mtime, st.st_size, p))
    total = sum(size for _, size, _ in files)
    for _, size, p in sorted(files, key=lambda f: f[0]):
        if total <= _max_bytes:
            break
        p.unlink(missing_ok=True)
        total -= size
