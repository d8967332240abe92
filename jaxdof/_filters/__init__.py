from .auto import choose_method as choose_method
from .coc_filter import (
    coc_filter as coc_filter,
    DIFFERENTIABLE_IN_RADIUS as DIFFERENTIABLE_IN_RADIUS,
    METHODS as METHODS,
)
