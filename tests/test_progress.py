"""What the CLI shows while it works (`jaxdof._cli.progress`): the display's modes, a fit's solver
steps once each with the start, solve and lens they belong to, and the lens decoder against the
fit's own parameter layout. The commands' output itself: tests/test_cli.py."""

import io
import re
import sys

import numpy as np
import pytest

import jaxdof
from jaxdof._cli.progress import Display, FitProgress, fit_lens_decoder, lens_text


class _Terminal(io.StringIO):
    """A stderr that says it is a terminal."""

    def isatty(self) -> bool:
        return True


class _Recorder(Display):
    """A live display that records its calls instead of drawing them."""

    def __init__(self):
        super().__init__("live")
        self.statuses: list[tuple[str, int, int | None, bool]] = []
        self.printed: list[str] = []

    def status(self, text, *, completed=0, total=None, bound=False):
        self.statuses.append((text, completed, total, bound))

    def print(self, text):
        self.printed.append(text)


def test_modes(monkeypatch):
    """`--quiet`: off; stderr a terminal: live (rich, cleared on exit, kept lines stay); else
    plain lines (the long loops' records only)."""
    assert Display.for_stderr(quiet=True).mode == "off"
    monkeypatch.setattr(sys, "stderr", io.StringIO())
    assert Display.for_stderr().mode == "lines"
    with Display.for_stderr() as display:
        display.status("reading x.png")  # stages: not in a log
        display.log("  band 1/2")
        display.print("kept")
    assert sys.stderr.getvalue() == "  band 1/2\nkept\n"
    terminal = _Terminal()
    monkeypatch.setattr(sys, "stderr", terminal)
    with Display.for_stderr() as display:
        assert display.mode == "live"
        display.status("rendering", completed=1, total=4)
        display.log("not shown: the live line says it")
        display.print("a line that stays")
    text = terminal.getvalue()
    assert "a line that stays" in text and "not shown" not in text
    with Display.for_stderr(quiet=True) as display:
        display.print("nothing")
        display.log("nothing")
    assert "nothing" not in terminal.getvalue()


def test_clock():
    from jaxdof._cli.progress import _clock

    assert [_clock(t) for t in (0, 59.4, 61, 3599, 3661)] == [
        "0:00",
        "0:59",
        "1:01",
        "59:59",
        "1:01:01",
    ]


def test_lens_text():
    rows = np.array([[0.05, 2.8, 3.0, 1e-5]])
    assert lens_text(rows) == "f 50 mm  N 2.8  d_f 3 m"
    assert lens_text(rows, ("focus_distance", "f_number")) == "N 2.8  d_f 3 m"  # the free ones
    rows = np.array([[0.085, 1.4, 3.0, 1e-5], [0.085, 1.4, 2.5, 1e-5], [0.085, 1.4, np.inf, 1e-5]])
    assert lens_text(rows) == "f 85 mm  N 1.4  d_f 3/2.5/inf m"


def _toy_solve(y0s, verbose):
    """Rosenbrock from each of `y0s` at once (vmapped, as `fit_lens` solves its starts), with a
    constant residual `1000 i` that makes start `i`'s loss about `0.5e6 i^2`: the loss says which
    start a progress line is about. The steps do not see it (its Jacobian row is zero).
    Returns each start's number of solver steps."""
    import equinox as eqx
    import jax
    import jax.numpy as jnp
    import optimistix as optx

    def fn(y, c):
        return jnp.stack([10 * (y[1] - y[0] ** 2), 1 - y[0], c])

    solver = optx.LevenbergMarquardt(rtol=1e-8, atol=1e-8, verbose=verbose)

    @eqx.filter_jit
    def solve(y0s, cs):
        def one(y0, c):
            return optx.least_squares(fn, solver, y0, c, throw=False, max_steps=100)

        return eqx.filter_vmap(one)(y0s, cs).stats["num_steps"]

    cs = 1000.0 * jnp.arange(len(y0s), dtype=jnp.float64)
    steps = solve(jnp.asarray(y0s, dtype=jnp.float64), cs)
    jax.effects_barrier()  # every callback has run
    return np.asarray(steps)


_LINE = re.compile(
    r"^\s*solve (\d+) start (\d+)/(\d+)\s+step\s+(\d+)\s+loss (\S+)(?:\s+f (\S+) mm.*)?"
    r"\s+\((\S+) s\)$"
)
_Y0S = [[-1.2, 1.0], [0.5, 0.5], [3.0, -2.0]]


def _rows_of(y):
    """A stand-in decoder: the Rosenbrock point as a lens (f = 50 mm, N = 2 + y0, d_f = 3 + y1)."""
    y = np.asarray(y, np.float64)
    return np.array([[0.05, 2.0 + y[0], 3.0 + y[1], 1e-5]])


def test_each_step_once_with_its_start(capsys):
    """`FitProgress` (plain lines) on a vmapped solve whose starts finish after different numbers
    of steps: every line is about the start it names (its loss says so: starts from 1), once per
    accepted step, steps rising, and a start done early reports its final step; the same callable
    in a second solve says `solve 2`. With a decoder, the lens the step reached (the Rosenbrock
    minimum (1, 1) is N 3, d_f 4)."""
    progress = FitProgress(decode=_rows_of)
    steps = _toy_solve(_Y0S, progress)
    assert len(set(steps.tolist())) == len(_Y0S)  # the case that repeated lines: starts done early
    _toy_solve(_Y0S, progress)  # the next solve
    lines = capsys.readouterr().err.splitlines()
    assert len(lines) == len(set(lines)), "a step line is repeated"
    seen, last = {}, {}
    for line in lines:
        match = _LINE.match(line)
        assert match, line
        solve, start, starts, step, loss, f, _ = match.groups()
        assert int(starts) == len(_Y0S) and f == "50"
        assert round(np.sqrt(2 * float(loss)) / 1000) == int(start) - 1, line
        seen.setdefault((int(solve), int(start)), []).append(int(step))
        last[(int(solve), int(start))] = line
    assert sorted(seen) == [(k, i) for k in (1, 2) for i in range(1, len(_Y0S) + 1)]
    for (_, i), s in seen.items():
        assert s == sorted(set(s)), s
        if steps[i - 1] < steps.max():  # done early: its final state is reported once
            assert s[-1] == steps[i - 1], (i, s, steps)
    assert all("N 3  d_f 4 m" in line for line in last.values()), last


def test_live_display_of_a_fit():
    """In `live` mode the steps go to the status line (the solve's steps against `max_steps`, a
    bound) and each solve leaves one summary line: its starts, steps, best loss and lens."""
    display = _Recorder()
    progress = FitProgress(display, decode=_rows_of, max_steps=100)
    steps = _toy_solve(_Y0S, progress)
    _toy_solve(_Y0S, progress)
    progress.close()
    assert display.statuses, "no step shown"
    for text, completed, total, bound in display.statuses:
        match = re.match(
            r"solve [12], step (\d+): loss \S+, f 50 mm .* \(best of 3 starts\)$", text
        )
        assert match, text
        assert total == 100 and bound and 1 <= completed == int(match.group(1)) <= steps.max()
    assert "N 3  d_f 4 m" in display.statuses[-1][0]
    assert len(display.printed) == 2
    for k, line in enumerate(display.printed, start=1):
        match = re.match(rf"solve {k}: 3 starts, (\d+) steps, best loss \S+ \((.*)\), \S+ s$", line)
        assert match, line
        # the last step shown is the last accepted one (the solver may try one more)
        assert steps.max() - 2 <= int(match.group(1)) <= steps.max()
        assert match.group(2) == "f 50 mm  N 3  d_f 4 m"


def test_a_failing_decoder_only_drops_the_lens(capsys):
    """The display must never end a fit: a decoder that raises leaves the lens out."""

    def broken(y):
        raise RuntimeError("no lens")

    _toy_solve(_Y0S[:1], FitProgress(decode=broken))
    lines = capsys.readouterr().err.splitlines()
    assert lines and all(_LINE.match(line) and " mm" not in line for line in lines)


@pytest.mark.parametrize(
    "free, shared",
    [
        (("focus_distance", "f_number"), ()),
        (("focus_distance", "f_number", "focal_length"), ("focal_length", "f_number")),
        (("f_number",), ()),
    ],
)
def test_decoder_is_the_fits_own_map(free, shared):
    """`fit_lens_decoder` reads a parameter vector as `fit_lens` does: the same lens rows as the
    fit's own layout (`prepare_problem`, which `fit_lens` builds its solves from) for random
    vectors, one photo or a bracket of three."""
    import jax.numpy as jnp

    from jaxdof._fit.layout import natural
    from jaxdof._fit.prepare import forward_model, prepare_problem

    rng = np.random.default_rng(1)
    image = rng.uniform(size=(12, 10, 3)).astype(np.float32)
    depth = rng.uniform(1.0, 5.0, size=(12, 10)).astype(np.float32)
    init = jaxdof.ThinLens.from_sensor(0.05, 2.8, 3.0, sensor_width=0.036, image_width=10)
    t = 3 if "focal_length" in free else 1
    targets = np.stack([image] * t)
    p = prepare_problem(image, depth, targets, init, None, forward_model(None), free, shared)
    decode = fit_lens_decoder(init, depth, free, shared, t)
    for _ in range(5):
        y = rng.normal(size=3 * t).astype(np.float32)
        expect = np.asarray(natural(jnp.asarray(y), p.layout))
        np.testing.assert_allclose(decode(y), expect, rtol=1e-6)
