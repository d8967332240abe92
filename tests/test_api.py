"""API conventions (as in dm_pix's api_test): documented exports, keyword-only options."""

import inspect

import pytest

import jaxdof


PUBLIC = sorted(
    n for n in dir(jaxdof) if not n.startswith("_") and not inspect.ismodule(getattr(jaxdof, n))
)
FUNCTIONS = [n for n in PUBLIC if inspect.isfunction(getattr(jaxdof, n))]


@pytest.mark.parametrize("name", PUBLIC)
def test_every_export_is_documented(name):
    obj = getattr(jaxdof, name)
    if isinstance(obj, (tuple, dict, str)):
        return  # constants: METHODS, DIFFERENTIABLE_IN_RADIUS, __version__-like values
    assert inspect.getdoc(obj), f"jaxdof.{name} has no docstring"


@pytest.mark.parametrize("name", FUNCTIONS)
def test_options_are_keyword_only(name):
    """Data are positional; every argument with a default (an option) is keyword-only."""
    params = inspect.signature(getattr(jaxdof, name)).parameters.values()
    positional_defaults = [
        p.name
        for p in params
        if p.default is not inspect.Parameter.empty
        and p.kind in (p.POSITIONAL_ONLY, p.POSITIONAL_OR_KEYWORD)
    ]
    assert not positional_defaults, (
        f"jaxdof.{name}: options {positional_defaults} should be keyword-only"
    )


def test_version():
    assert isinstance(jaxdof.__version__, str)


def test_methods_table_is_complete():
    assert set(jaxdof.DIFFERENTIABLE_IN_RADIUS) == set(jaxdof.METHODS)
