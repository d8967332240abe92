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
        return  # constants: __version__-like values
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


METHOD_CLASSES = [
    n
    for n in PUBLIC
    if inspect.isclass(getattr(jaxdof, n)) and issubclass(getattr(jaxdof, n), jaxdof.AbstractMethod)
]


def test_filter_methods_are_exported_objects():
    """The method family is public as classes (no string tables): the base and every built-in."""
    expected = {"Soft", "Hard", "Supersample", "Jitter", "Aperture", "Layered", "Occlusion", "Auto"}
    expected |= {"LocalOcclusion"}
    assert set(METHOD_CLASSES) == expected | {"AbstractMethod"}
    assert not hasattr(jaxdof, "METHODS") and not hasattr(jaxdof, "DIFFERENTIABLE_IN_RADIUS")


@pytest.mark.parametrize("name", METHOD_CLASSES)
def test_method_options_are_keyword_only(name):
    """A method's options are keyword-only, as a function's are."""
    params = inspect.signature(getattr(jaxdof, name)).parameters.values()
    assert all(p.kind == p.KEYWORD_ONLY for p in params), name
