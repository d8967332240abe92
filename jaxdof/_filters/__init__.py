from .coc_filter import coc_filter as coc_filter
