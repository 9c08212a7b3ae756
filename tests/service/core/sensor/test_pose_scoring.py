"""Scoring a pose against the map (service/core/sensor/pose_scoring.py): the beam verification."""

from __future__ import annotations

import numpy as np

from service.core.reloc.global_config import GlobalConfig
from service.core.reloc.global_localization import load_or_build_index
from service.core.sensor import pose_scoring as gs
from service.core.sensor.raycast import RayCaster
from service.core.shapes.configuration import scan_configuration
from service.core.tracking.localizer import ShapeConfig
from service.core.types import MapData

ROOM = np.array([[0.0, 0.0], [10.0, 0.0], [10.0, 6.0], [0.0, 6.0], [0.0, 0.0]])
# a cabinet drawn in the map, 1.5 m in front of the robot's left wall, gone when the scan runs
CABINET = np.array([[2.0, 1.5], [2.0, 4.5]])


def _scan(pose: np.ndarray, beams: int = 360) -> tuple[np.ndarray, np.ndarray]:
    angles = np.linspace(-np.pi, np.pi, beams, endpoint=False)
    ranges = RayCaster(MapData.from_lists("now", "metric", [ROOM]).segments()).cast(
        pose, angles, 15.0
    )
    return ranges, angles


def test_a_beam_past_a_gone_object_onto_a_mapped_wall_is_no_violation() -> None:
    """The map holds a cabinet the laser now sees past: without ``see_through`` the true pose
    pays for ~1/6 of its beams as violations (cost above a bad fit's); with it those beams
    are neither hits nor violations. A pose 1.5 m off, whose beams leave the room through
    its walls into unmapped space, keeps its violations either way."""
    md = MapData.from_lists("room", "metric", [ROOM, CABINET])
    cfg = ShapeConfig.for_kind("metric")
    truth = np.array([5.0, 3.0, np.pi])
    ranges, angles = _scan(truth)
    P = scan_configuration(ranges, angles, cfg.extraction())
    off = np.array([6.5, 3.0, np.pi])
    out = {}
    for see in (False, True):
        g = GlobalConfig.for_kind("metric").model_copy(update={"see_through": see})
        idx = load_or_build_index(md, cfg, g)
        out[see] = (
            gs.verify(idx, truth, ranges, angles, P, cfg, g),
            gs.verify(idx, off, ranges, angles, P, cfg, g),
        )
    true_plain, off_plain = out[False]
    true_see, off_see = out[True]
    assert true_plain.violation > 0.1
    assert true_see.violation == 0.0
    assert true_see.hit == true_plain.hit
    assert true_see.cost < true_plain.cost - 0.2
    # the wrong pose: beams through the right-hand wall end in unmapped space
    assert off_see.violation > 0.05
    assert off_see.violation <= off_plain.violation
    assert off_see.cost > true_see.cost + 0.2


def test_field_violations_agree_with_the_ray_casters() -> None:
    """The search's cheap violation share (beams marched on the distance field) is the exact
    ray cast's within a beam or two, at the true pose (none: the beams end at the walls they
    came from) and at poses across the partition of two rooms (beams through it)."""
    partition = np.array([[5.0, 0.0], [5.0, 6.0]])
    md = MapData.from_lists("two", "schematic", [ROOM, partition])
    cfg = ShapeConfig.for_kind("schematic")
    g = GlobalConfig.for_kind("schematic")
    idx = load_or_build_index(md, cfg, g)
    truth = np.array([2.0, 3.0, 0.3])
    angles = np.linspace(-np.pi, np.pi, 40, endpoint=False)
    ranges = idx.caster.cast(truth, angles, 15.0)
    margin = max(cfg.support_tolerance, g.violation_margin)
    rng = np.random.default_rng(3)
    poses = np.vstack(
        [
            truth,
            np.column_stack(
                [rng.uniform(0.5, 9.5, 30), rng.uniform(0.5, 5.5, 30), rng.uniform(-3, 3, 30)]
            ),
        ]
    )
    field = gs._field_violations(idx, poses, ranges, angles, margin)
    tol = cfg.support_tolerance
    exact = np.array(
        [gs._beam_fractions(ranges, idx.caster.cast(p, angles, 15.0), tol, g)[1] for p in poses]
    )
    assert field[0] == 0.0 and exact[0] == 0.0
    assert exact.max() > 0.3  # poses whose beams cross the partition or the outer walls
    assert np.max(np.abs(field - exact)) <= 2 / 40
