"""What the CLI shows while it works (`jaxdof._cli.progress`): the display's modes, a fit's solver
steps once each with the start, solve and lens they belong to, and the lenses `fit_lens` hands its
`verbose` callable. The commands' output itself: tests/test_cli.py."""

import io
import re
import sys

import numpy as np
import pytest

import jaxdof
from jaxdof._cli.progress import Display, FitProgress, lens_text


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


def _with_lens(progress):
    """`progress` as `fit_lens` calls it: with `lenses`, here the Rosenbrock point as a lens
    (f = 50 mm, N = 2 + y0, d_f = 3 + y1), one photo."""
    import jax.numpy as jnp

    def verbose(**kwargs):
        y = kwargs["y_last_accepted_step"][1]
        one = jnp.ones((1,), y.dtype)
        lens = jaxdof.ThinLens(0.05 * one, 2.0 + y[0] * one, 3.0 + y[1] * one, 1e-5 * one)
        progress(**kwargs, lenses=("Lenses", lens))

    return verbose


def test_each_step_once_with_its_start(capsys):
    """`FitProgress` (plain lines) on a vmapped solve whose starts finish after different numbers
    of steps: every line is about the start it names (its loss says so: starts from 1), once per
    accepted step, steps rising, and a start done early reports its final step; the same callable
    in a second solve says `solve 2`. With the lenses `fit_lens` passes, the lens the step reached
    (the Rosenbrock minimum (1, 1) is N 3, d_f 4)."""
    progress = FitProgress()
    steps = _toy_solve(_Y0S, _with_lens(progress))
    assert len(set(steps.tolist())) == len(_Y0S)  # the case that repeated lines: starts done early
    _toy_solve(_Y0S, _with_lens(progress))  # the next solve
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
    progress = FitProgress(display, max_steps=100)
    steps = _toy_solve(_Y0S, _with_lens(progress))
    _toy_solve(_Y0S, _with_lens(progress))
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


def test_without_lenses_the_steps_only(capsys):
    """A solver's `verbose` without `lenses` (another caller than `fit_lens`): the steps alone."""
    _toy_solve(_Y0S[:1], FitProgress())
    lines = capsys.readouterr().err.splitlines()
    assert lines and all(_LINE.match(line) and " mm" not in line for line in lines)


@pytest.mark.parametrize(
    "free, shared",
    [(("focus_distance", "f_number", "focal_length"), ("focal_length", "f_number"))],
)
def test_verbose_receives_the_fits_lenses(free, shared):
    """`fit_lens`'s `verbose` callable receives the lens of every photo at each step, decoded by
    the fit's own map: the last accepted step's lenses are the fit's answer."""
    import jax

    rng = np.random.default_rng(1)
    image = rng.uniform(size=(16, 20, 3)).astype(np.float32)
    depth = np.linspace(1.0, 5.0, 20, dtype=np.float32)[None, :].repeat(16, 0)
    t = 3 if "focal_length" in free else 1
    truth = [
        jaxdof.ThinLens.from_sensor(0.05, 2.8, d, sensor_width=0.0048, image_width=20)
        for d in (2.0, 3.0, 4.0)[:t]
    ]
    photos = np.stack([np.asarray(jaxdof.render(image, depth, lens)) for lens in truth])
    start = jaxdof.ThinLens.from_sensor(0.05, 4.0, 2.5, sensor_width=0.0048, image_width=20)
    seen = []

    def verbose(**kwargs):
        lens = kwargs["lenses"][1]
        jax.debug.callback(
            lambda *a: seen.append([np.asarray(x) for x in a]),
            lens.f_number,
            lens.focus_distance,
            ordered=True,
        )

    fit = jaxdof.fit_lens(
        image,
        depth,
        photos[0] if t == 1 else photos,
        start,
        free=free,
        shared=shared,
        verbose=verbose,
        starts=1,
        # the photo's own model, nothing to decide: the last solve is the answer's
        method="soft",
        footprint=False,
        edge_weight=False,
        exposure=False,
        vignetting=False,
        registration=False,
        luma=False,
    )
    jax.effects_barrier()
    n, d_f = seen[-1]
    assert np.shape(n)[-1] == t
    np.testing.assert_allclose(np.reshape(n, -1), np.asarray(fit.lenses.f_number), rtol=1e-4)
    np.testing.assert_allclose(
        np.reshape(d_f, -1), np.asarray(fit.lenses.focus_distance), rtol=1e-4
    )
