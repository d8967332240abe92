from .aliases import METHOD_ALIASES as METHOD_ALIASES, as_method as as_method
from .aperture import Aperture as Aperture
from .auto import Auto as Auto, choose_method as choose_method
from .base import AbstractMethod as AbstractMethod
from .coc_filter import coc_filter as coc_filter
from .hard import Hard as Hard
from .jitter import Jitter as Jitter
from .layered import Layered as Layered
from .local_occlusion import LocalOcclusion as LocalOcclusion
from .occlusion import Occlusion as Occlusion
from .soft_method import Soft as Soft
from .supersample import Supersample as Supersample
