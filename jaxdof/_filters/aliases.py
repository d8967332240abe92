"""The built-in methods' short names: `"soft"` for `Soft()`, and `as_method` that resolves them."""

from __future__ import annotations

from .aperture import Aperture
from .auto import Auto
from .base import AbstractMethod
from .hard import Hard
from .jitter import Jitter
from .layered import Layered
from .local_occlusion import LocalOcclusion
from .occlusion import Occlusion
from .soft_method import Soft
from .supersample import Supersample


# Each alias is the class with its default options. Not a table of behaviour: that lives on the
# classes (`differentiable_in_radius`, `uses_depth`, their own checks).
_ALIASES: dict[str, type[AbstractMethod]] = {
    "soft": Soft,
    "hard": Hard,
    "supersample": Supersample,
    "jitter": Jitter,
    "aperture": Aperture,
    "layered": Layered,
    "auto": Auto,
    "occlusion": Occlusion,
    "local_occlusion": LocalOcclusion,
}

#: The names `as_method` accepts (the command line's `--method` choices).
METHOD_ALIASES: tuple[str, ...] = tuple(_ALIASES)


def as_method(method: str | AbstractMethod) -> AbstractMethod:
    """The method object for `method`: an `AbstractMethod` instance as it is, an alias string as
    its class with the default options (`"soft"` -> `Soft()`, `"aperture"` -> `Aperture()`).

    **Raises:** `ValueError` for anything else (listing the aliases), and for the alias of a method
    that cannot run with its defaults (`"jitter"` needs a key: the message says
    `jaxdof.Jitter(key=jax.random.key(0))`).
    """
    if isinstance(method, AbstractMethod):
        return method
    if isinstance(method, str) and method in _ALIASES:
        return _ALIASES[method]()
    raise ValueError(
        f"{method=} is not a filter method: pass an instance of a jaxdof.AbstractMethod subclass "
        f"(e.g. jaxdof.Soft(), jaxdof.Aperture(pattern='ring')) or one of {METHOD_ALIASES}"
    )
