from .auto import choose_method as choose_method
from .coc_filter import (
    DIFFERENTIABLE_IN_RADIUS as DIFFERENTIABLE_IN_RADIUS,
    METHODS as METHODS,
    coc_filter as coc_filter,
)
