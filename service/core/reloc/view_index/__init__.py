"""Candidate viewpoints and the per-map view index of global localisation.

:func:`candidate_viewpoints` (a grid over the free space, :mod:`.viewpoints`),
:class:`ViewIndex` (per viewpoint the map view reduced to its units, plus a distance field,
:mod:`.index`), :func:`build_index` (:mod:`.build`) and the on-disk cache
(:func:`load_or_build_index`, keyed by map content, extraction parameters and
:data:`FORMAT_VERSION`, :mod:`.cache`). See :mod:`service.core.reloc.global_localization` for the
whole method."""

from service.core.reloc.view_index.build import build_index, index_key
from service.core.reloc.view_index.cache import (
    cache_path,
    clear_memory_cache,
    load_index,
    load_or_build_index,
    save_index,
)
from service.core.reloc.view_index.index import FORMAT_VERSION, ViewIndex
from service.core.reloc.view_index.viewpoints import candidate_viewpoints

__all__ = [
    "FORMAT_VERSION",
    "ViewIndex",
    "build_index",
    "cache_path",
    "candidate_viewpoints",
    "clear_memory_cache",
    "index_key",
    "load_index",
    "load_or_build_index",
    "save_index",
]
