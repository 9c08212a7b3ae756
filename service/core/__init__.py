"""Pure localisation core: numpy arrays in, poses out. No zenoh, no msgpack.

Entry point for users: :func:`service.core.factory.create_localizer`. The folders follow the
method (docs/architecture-core.md walks a scan through them):

- :mod:`service.core.shapes` -- the paper's shape primitives (polylines, DCE, the scan
  configuration and the map view, S*, the matching of §5);
- :mod:`service.core.sensor` -- the map and sensor model (one map model, the ray caster, the
  scoring of poses against the map for a scan) and the point-to-line solvers;
- :mod:`service.core.tracking` -- the shape tracker, the motion model and the odometry check;
- :mod:`service.core.reloc` -- relocalisation: the global search, hypotheses over a drive,
  and the localiser the factory returns for ``shape``;
- :mod:`service.core.baselines` -- the paper's comparison methods (ICP, lines);
- :mod:`service.core.kernels` -- the compiled inner loops (numba), warmed up by
  :mod:`service.core.warmup`.

Modules of the flat layout of earlier versions (``service.core.localizer``, ...) still import
under their old names (:data:`MOVED`): a localiser state pickled by an earlier version names
them.
"""

from __future__ import annotations

import importlib
import importlib.abc
import importlib.util
import sys
from types import ModuleType

#: Old flat module name -> where its code (or what replaced it) lives now, both under
#: ``service.core``.
MOVED: dict[str, str] = {
    "polylines": "shapes.polylines",
    "dce": "shapes.dce",
    "configuration": "shapes.configuration",
    "similarity": "shapes.similarity",
    "similarity_reference": "shapes.similarity_reference",
    "shape_cost": "shapes.shape_cost",
    "order_dp": "shapes.order_dp",
    "matching": "shapes.matching",
    "stacked": "shapes.stacked",
    "two_step": "shapes.two_step",
    "mapmodel": "sensor.mapmodel",
    "raycast": "sensor.raycast",
    "segment_grid": "sensor.mapmodel",
    "pose_scoring": "reloc.global_search",
    "refine": "sensor.refine",
    "pose_batch": "sensor.pose_batch",
    "localizer": "tracking.localizer",
    "shape_config": "tracking.shape_config",
    "motion": "tracking.motion",
    "scan_odometry": "tracking.scan_odometry",
    "laser_odometry": "tracking.laser_odometry",
    "global_localization": "reloc.global_localization",
    "global_search": "reloc.global_search",
    "view_index": "reloc.view_index",
    "hypotheses": "reloc.drive",
    "evidence": "reloc.drive",
    "probation": "reloc.states",
    "confirmation": "reloc.states",
    "window_refine": "reloc.drive",
    "drive_search": "reloc.states",
    "composite": "reloc.composite",
    "global_config": "reloc.config",
    "drive_config": "reloc.config",
}


class _MovedModules(importlib.abc.MetaPathFinder, importlib.abc.Loader):
    """Imports an old flat module name as the module that now holds its code (the same
    module object, so classes pickled under the old name load as today's classes)."""

    def find_spec(
        self, fullname: str, path: object = None, target: object = None
    ) -> importlib.machinery.ModuleSpec | None:
        head, _, tail = fullname.partition("service.core.")
        if head or tail not in MOVED:
            return None
        return importlib.util.spec_from_loader(fullname, self)

    def create_module(self, spec: importlib.machinery.ModuleSpec) -> ModuleType | None:
        return None

    def exec_module(self, module: ModuleType) -> None:
        # the import system returns what sys.modules holds under the name after this call
        new = importlib.import_module("service.core." + MOVED[module.__name__[13:]])
        sys.modules[module.__name__] = new


if not any(isinstance(f, _MovedModules) for f in sys.meta_path):
    sys.meta_path.append(_MovedModules())
