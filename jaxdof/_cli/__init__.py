"""The `jaxdof` command line: `demo`, `render`, `fit`, `info`, `chart` (a calibration chart's
files) and `calibrate` (a lens from photos of it), a thin layer over `_io`, `_exif` and the
library.

`parse` builds the parser, `commands` runs a command, `report` prints results, `progress` shows
what a command is doing while it works (a live line on a terminal, plain lines in a log),
`plot` draws the figures, `demo` makes the demo's scene. Every problem with the user's files or
options ends in one line on stderr that names the file or option and the problem, and exit
status 2: an `InputError` (raised by `_io` and by the CLI's own checks), or the library's
`ValueError` turned into one (`commands.library_checks`).

`main` lives here, the entry point of the `jaxdof` script (`jaxdof._cli:main`) and of
`python -m jaxdof`.
"""

from __future__ import annotations

import sys
from collections.abc import Sequence

from .._allocator import retain_freed_memory
from .._compiled import enable_compilation_cache
from .._io import InputError
from .commands import run_calibrate, run_chart, run_demo, run_fit, run_info, run_render
from .parse import build_parser


_COMMANDS = {
    "demo": run_demo,
    "render": run_render,
    "fit": run_fit,
    "info": run_info,
    "chart": run_chart,
    "calibrate": run_calibrate,
}


def _compilation_cache(command: str) -> None:
    """The persistent compilation cache (`jaxdof.enable_compilation_cache`), unless one is set
    up already (JAX's `JAX_COMPILATION_CACHE_DIR`, or a test session's); a folder that cannot be
    written costs the speed, not the command: one line on stderr."""
    import jax

    if getattr(jax.config, "jax_compilation_cache_dir", None) is not None:
        return
    try:
        enable_compilation_cache()
    except ValueError as err:
        print(f"jaxdof {command}: warning: {err}", file=sys.stderr)


def main(argv: Sequence[str] | None = None) -> int:
    """Entry point of the `jaxdof` script and of `python -m jaxdof`; returns the exit status."""
    parser = build_parser()
    try:
        args = parser.parse_args(None if argv is None else list(argv))
    except SystemExit as exc:  # --help, --version, or a one-line usage error
        return int(exc.code or 0)
    if getattr(args, "cache", False):
        _compilation_cache(args.command)
    if args.command not in ("render", "fit", "calibrate"):  # those decide by the frame's size
        # the application's call (see `jaxdof.retain_freed_memory`): XLA's per-call scratch is
        # then reused instead of faulted in anew, up to 2x on megapixel images
        retain_freed_memory()
    try:
        return _COMMANDS[args.command](args)
    except InputError as err:
        print(f"jaxdof {args.command}: error: {err}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print("jaxdof: interrupted", file=sys.stderr)
        return 130
