"""S* as the matchers' shape cost (paper §5.1, in eq. 5 and in step 1 of §5.3).

:func:`service.core.shapes.matching.match_with_cost` and
:func:`service.core.shapes.two_step.step1_hypotheses` compare scan and map polylines (single or
joined features) by S* with the partial-matching
weights of their ``ShapeConfig``, and drop the pairs above a gate:

* :data:`ShapeCost`, the type of a shape cost; :func:`shape_cost_for`, S* with a config's
  weights;
* :func:`gated_shape_cost`, the same pruned at the gate, one pair per call;
* :func:`batched_shape_cost`, the same for many pairs of joined features in one compiled call
  (:func:`service.core.shapes.similarity.shape_distances`);
* :func:`shape_arcs`, the S*-prepared polylines, cached per scan.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from typing import TYPE_CHECKING, Any

import numpy as np

from service.core.shapes.configuration import Configuration, Feature
from service.core.shapes.similarity import prepare, shape_distance, shape_distances
from service.core.shapes.stacked import stacked_vertices

if TYPE_CHECKING:
    from service.core.tracking.localizer import ShapeConfig

#: A shape distance S*: ``(p (k, 2), q (l, 2)) -> metres >= 0``.
ShapeCost = Callable[[Any, Any], float]


def shape_cost_for(config: ShapeConfig) -> ShapeCost:
    """S* with the partial-matching weights of ``config`` (``shape_end_weight``,
    ``shape_skip_weight``; see :func:`service.core.shapes.similarity.shape_distance`)."""
    ew, sw = config.shape_end_weight, config.shape_skip_weight

    def cost(p: Any, q: Any) -> float:
        return shape_distance(p, q, end_weight=ew, skip_weight=sw)

    return cost


def gated_shape_cost(config: ShapeConfig, gate: float) -> ShapeCost:
    """:func:`shape_cost_for` for a caller that drops pairs with S* above ``gate``: the
    search is pruned at the gate (``upper_bound``), values <= ``gate`` are exact and larger
    ones come back as ``inf``."""
    ew, sw = config.shape_end_weight, config.shape_skip_weight
    bound = math.nextafter(gate, math.inf)

    def cost(p: Any, q: Any) -> float:
        return shape_distance(p, q, end_weight=ew, skip_weight=sw, upper_bound=bound)

    return cost


def batched_shape_cost(
    P: Configuration,
    Q: Configuration,
    p_rows: np.ndarray,
    q_rows: np.ndarray,
    config: ShapeConfig,
    gate: float,
) -> list[float]:
    """:func:`gated_shape_cost` of many pairs in one compiled call: pair ``r`` joins the
    features ``p_rows[r]`` of ``P`` and ``q_rows[r]`` of ``Q`` (``-1`` = none); values above
    ``gate`` come back as ``inf``."""
    pv, pvo = stacked_vertices(P)
    qv, qvo = stacked_vertices(Q)
    return shape_distances(
        pv,
        pvo,
        p_rows,
        qv,
        qvo,
        q_rows,
        end_weight=config.shape_end_weight,
        skip_weight=config.shape_skip_weight,
        upper_bound=math.nextafter(gate, math.inf),
    ).tolist()


def shape_arcs(
    f: Feature | tuple, verts: np.ndarray | Callable[[], np.ndarray], cache: dict
) -> Any:
    """S*-prepared polyline, cached under ``f`` (a feature or a key); ``verts`` may be a
    callable building the vertices only on a cache miss."""
    key = id(f) if isinstance(f, Feature) else f
    arcs = cache.get(key)
    if arcs is None:
        arcs = prepare(verts() if callable(verts) else verts)
        cache[key] = arcs
    return arcs
