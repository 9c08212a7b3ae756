"""Odometry checked against the scans (service/core/tracking/scan_odometry.py)."""

from __future__ import annotations

import pickle
from pathlib import Path

import numpy as np
import pytest

from service.core import kernels
from service.core.pose import compose, invert
from service.core.reloc.global_localization import GlobalShapeLocalizer
from service.core.tracking import scan_odometry as so
from service.core.tracking.localizer import ShapeConfig
from service.core.tracking.motion import MotionConfig, ScanOdometryConfig
from service.core.types import MapData
from service.errors import LocalizationError

#: fr079 scans 846-865 (tests/data/real/README.md): from scan 854 on the robot backs up ~0.8 m
#: while the log's odometry reports ~0.7 m forwards.
WINDOW = Path(__file__).resolve().parents[3] / "data" / "real" / "fr079.846-865.npz"


#: intel scans 4870-4881 (tests/data/real/README.md): the odometry reports a 0.37 rad turn at
#: scan 4876 that the scans show at 4877, one scan late.
EARLY_TURN = Path(__file__).resolve().parents[3] / "data" / "real" / "intel.4870-4881.npz"


def _odometry(config: ScanOdometryConfig | None = None) -> so.ScanOdometry:
    m = MotionConfig()
    return so.ScanOdometry(config or m.scan_odometry, m)


def _corridor_scan(y: float, heading: float) -> tuple[np.ndarray, np.ndarray]:
    """A 180-degree, 361-beam scan in an endless corridor between the walls y = -1 and
    y = +1 (no return beyond 15 m), from ``(x, y, heading)`` (x does not matter)."""
    angles = np.linspace(-np.pi / 2, np.pi / 2, 361)
    world = angles + heading
    s = np.sin(world)
    with np.errstate(divide="ignore"):
        ranges = np.where(s > 0, (1.0 - y) / s, (-1.0 - y) / s)
    ranges = np.where((np.abs(s) > 1e-9) & (ranges > 0) & (ranges <= 15.0), ranges, np.nan)
    return ranges, angles


def test_a_backward_drive_that_the_odometry_reports_forwards_is_corrected() -> None:
    z = np.load(WINDOW)
    odo = _odometry()
    out = np.array([odo.correct(z["ranges"][i], z["angles"][i], z["odom"][i]) for i in range(20)])
    a, b = 853 - 846, 864 - 846
    assert z["flag"][a] and z["flag"][b]
    ref = compose(invert(z["reference"][a]), z["reference"][b])
    raw = compose(invert(z["odom"][a]), z["odom"][b])
    got = compose(invert(out[a]), out[b])
    assert ref[0] < -0.7 and raw[0] > 0.6  # the log: backwards, reported forwards
    assert np.hypot(*(raw[:2] - ref[:2])) > 1.4
    assert np.hypot(*(got[:2] - ref[:2])) < 0.15  # measured 0.094 m
    assert abs(got[2] - ref[2]) < 0.05


def test_fed_every_third_scan_the_backward_drive_is_corrected_by_the_fallback_fit() -> None:
    """``ScanOdometryConfig.fallback_sigma`` (opt-in, 0.5 m here): every 3rd scan of the same
    window the odometry's increment is ~0.6 m from the true one, beyond the association
    gate, and the fit seeded there explains too little of the scan; fitted again from no
    translation it finds the backward step. Without the fallback the window's drive stays
    > 0.5 m off."""
    z = np.load(WINDOW)
    idx = list(range(0, 20, 3))
    ref = compose(invert(z["reference"][0]), z["reference"][18])
    errors = {}
    for sigma in (0.5, 0.0):
        m = MotionConfig()
        config = m.scan_odometry.model_copy(update={"fallback_sigma": sigma})
        odo = so.ScanOdometry(config, m)
        out = {i: odo.correct(z["ranges"][i], z["angles"][i], z["odom"][i]) for i in idx}
        got = compose(invert(out[0]), out[18])
        errors[sigma] = float(np.hypot(*(got[:2] - ref[:2])))
    assert MotionConfig().scan_odometry.fallback_sigma == 0.0  # opt-in
    assert errors[0.0] > 0.5  # measured 0.72 m
    assert errors[0.5] < 0.15  # measured 0.08 m


def test_a_turn_the_odometry_stamps_a_scan_early_is_kept_not_lost() -> None:
    """The scans take the early turn out of scan 4876's increment; scan 4877's raw increment
    lacks it, and a fit started there fails. Started from the turn the last fit took out, it
    matches, and over the window the corrected readings turn as GMapping's reference does
    (measured 2 mrad off; with the turn dropped 0.43 rad, the raw odometry's 0.10 rad)."""
    z = np.load(EARLY_TURN)
    odo = _odometry()
    out, kept = [], []
    for i in range(len(z["scan"])):
        out.append(odo.correct(z["ranges"][i], z["angles"][i], z["odom"][i]))
        kept.append(odo.corrected)
    ref = compose(invert(z["reference"][0]), z["reference"][-1])
    got = compose(invert(out[0]), out[-1])
    early = list(z["scan"]).index(4876)
    step = compose(invert(z["odom"][early - 1]), z["odom"][early])
    assert step[2] > 0.3  # the log: the early turn
    assert all(kept[1:])  # every increment matched by the scans
    assert abs(got[2] - ref[2]) < 0.02
    assert np.hypot(*(got[:2] - ref[:2])) < 0.05  # measured 0.031 m


def test_a_state_pickled_without_the_owed_turn_loads_and_goes_on() -> None:
    z = np.load(EARLY_TURN)
    odo = _odometry()
    for i in range(3):
        odo.correct(z["ranges"][i], z["angles"][i], z["odom"][i])
    state = pickle.dumps(odo)
    old = pickle.loads(state)
    del old.__dict__["owed"]  # as an earlier version pickled it
    for i in range(3, len(z["scan"])):
        a = odo.correct(z["ranges"][i], z["angles"][i], z["odom"][i])
        np.testing.assert_array_equal(old.correct(z["ranges"][i], z["angles"][i], z["odom"][i]), a)


def test_along_a_featureless_corridor_the_odometry_holds_and_the_rest_is_corrected() -> None:
    """The scans observe the sideways offset and the heading, never the position along the
    corridor: a fit there would follow noise, so the odometry's value stays."""
    odo = _odometry()
    odo.correct(*_corridor_scan(0.0, 0.0), np.zeros(3))
    # truly: 0.1 m along the corridor, 0.05 m sideways, turned 0.04 rad; the odometry says
    # 0.3 m along, no sideways motion, no turn
    truth = np.array([0.1, 0.05, 0.04])
    out = odo.correct(*_corridor_scan(0.05, 0.04), np.array([0.3, 0.0, 0.0]))
    assert odo.corrected
    assert out[0] == pytest.approx(0.3, abs=0.01)  # along: the odometry
    assert out[1] == pytest.approx(truth[1], abs=0.01)  # across: the scans
    assert out[2] == pytest.approx(truth[2], abs=0.005)


def test_a_stale_reading_is_repeated_and_the_next_one_matched_from_the_last_fresh_scan() -> None:
    z = np.load(WINDOW)
    odo = _odometry()
    first = odo.correct(z["ranges"][0], z["angles"][0], z["odom"][0])
    np.testing.assert_array_equal(first, z["odom"][0])  # nothing to correct yet
    assert odo.matched_from is None
    second = odo.correct(z["ranges"][1], z["angles"][1], z["odom"][1])
    # the fit is kept: its increment was measured from the first (corrected) reading
    assert odo.corrected
    np.testing.assert_array_equal(odo.matched_from, first)
    # the odometry did not update: the same reading comes back bit for bit
    again = odo.correct(z["ranges"][2], z["angles"][2], z["odom"][1])
    np.testing.assert_array_equal(again, second)
    assert np.isnan(odo.explained) and not odo.corrected and odo.matched_from is None
    # the next fresh reading is matched against scan 1 (the scan of the last fresh reading)
    ref = _odometry()
    ref.correct(z["ranges"][0], z["angles"][0], z["odom"][0])
    ref.correct(z["ranges"][1], z["angles"][1], z["odom"][1])
    np.testing.assert_array_equal(
        odo.correct(z["ranges"][3], z["angles"][3], z["odom"][3]),
        ref.correct(z["ranges"][3], z["angles"][3], z["odom"][3]),
    )


def test_reset_reanchors_and_a_pickled_copy_goes_on_identically() -> None:
    z = np.load(WINDOW)
    odo = _odometry()
    for i in range(10):
        odo.correct(z["ranges"][i], z["angles"][i], z["odom"][i])
    copy = pickle.loads(pickle.dumps(odo))
    for i in range(10, 14):
        np.testing.assert_array_equal(
            copy.correct(z["ranges"][i], z["angles"][i], z["odom"][i]),
            odo.correct(z["ranges"][i], z["angles"][i], z["odom"][i]),
        )
    odo.reset(z["odom"][14])
    np.testing.assert_array_equal(
        odo.correct(z["ranges"][14], z["angles"][14], z["odom"][14]), z["odom"][14]
    )


def test_the_compiled_fit_and_the_numpy_reference_agree(monkeypatch: pytest.MonkeyPatch) -> None:
    if not kernels.HAVE_NUMBA:
        pytest.skip("numba is not installed")
    z = np.load(WINDOW)
    cfg = MotionConfig().scan_odometry
    for i in (5, 9, 13):
        prev, prev_n = so._surface_points(z["ranges"][i - 1], z["angles"][i - 1], cfg)
        pts, nrm = so._surface_points(z["ranges"][i], z["angles"][i], cfg)
        delta = compose(invert(z["odom"][i - 1]), z["odom"][i])
        info = so._prior_information(delta, MotionConfig())
        args = (prev, prev_n, pts[::3], nrm[::3], delta, info, cfg)
        fast = so.match_increment(*args)
        with monkeypatch.context() as mp:
            mp.setattr(kernels, "HAVE_NUMBA", False)
            slow = so.match_increment(*args)
        np.testing.assert_allclose(fast[0], slow[0], atol=1e-9)
        assert fast[1] == pytest.approx(slow[1])
        assert fast[1] > 0.5


def test_the_localiser_uses_the_checked_odometry_and_can_switch_it_off() -> None:
    z = np.load(WINDOW)
    square = np.array([[-8.0, -8.0], [8.0, -8.0], [8.0, 8.0], [-8.0, 8.0], [-8.0, -8.0]])
    md = MapData.from_lists("box", "metric", [square])
    on = GlobalShapeLocalizer(md, np.zeros(3))
    base = ShapeConfig.for_kind("metric")
    off_cfg = base.model_copy(
        update={
            "motion": base.motion.model_copy(
                update={"scan_odometry": ScanOdometryConfig(enabled=False)}
            )
        }
    )
    off = GlobalShapeLocalizer(md, np.zeros(3), off_cfg)
    ref = so.ScanOdometry(on.config.motion.scan_odometry, on.config.motion)  # its motion noise
    for i in range(8):
        want = ref.correct(z["ranges"][i], z["angles"][i], z["odom"][i])
        on.update(z["ranges"][i], z["angles"][i], z["odom"][i])
        off.update(z["ranges"][i], z["angles"][i], z["odom"][i])
        np.testing.assert_array_equal(on.odometry.last, want)
        np.testing.assert_array_equal(off.odometry.last, z["odom"][i])
    # a malformed scan is refused before the odometry check sees it
    before = pickle.dumps(on.odometry)
    with pytest.raises(LocalizationError):
        on.update(z["ranges"][8][:-1], z["angles"][8], z["odom"][8])
    assert pickle.dumps(on.odometry) == before


def test_surface_normals_follow_the_wall_not_the_range_noise(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """A wall 1 m away, returns 9 mm apart with 5 mm of range noise: the chord of two
    neighbours swings by tens of degrees, the fitted normal stays within a few; the compiled
    and numpy versions agree; a corner gets no normal."""
    rng = np.random.default_rng(3)
    angles = np.linspace(-0.5, 0.5, 111)
    ranges = 1.0 / np.cos(angles) + rng.normal(0.0, 0.005, angles.size)
    pts = np.column_stack([ranges * np.cos(angles), ranges * np.sin(angles)])
    cfg = MotionConfig().scan_odometry
    got = so.surface_normals(pts, cfg.normal_window, cfg.normal_radius, cfg.max_flatness)
    ok = np.all(np.isfinite(got), axis=1)
    assert ok.mean() > 0.8
    off = np.degrees(np.arccos(np.minimum(1.0, np.abs(got[ok, 0]))))  # the wall's normal is x
    assert np.percentile(off, 90) < 10.0
    chord = pts[2:] - pts[:-2]
    chord_off = np.degrees(np.arcsin(np.minimum(1.0, np.abs(chord[:, 0]) / np.hypot(*chord.T))))
    assert np.percentile(chord_off, 90) > 20.0
    with monkeypatch.context() as mp:
        mp.setattr(kernels, "HAVE_NUMBA", False)
        ref = so.surface_normals(pts, cfg.normal_window, cfg.normal_radius, cfg.max_flatness)
    np.testing.assert_allclose(got, ref, atol=1e-12)
    corner = np.array(
        [[1.0, y] for y in np.linspace(-0.1, 0.0, 6)]
        + [[x, 0.0] for x in np.linspace(0.98, 0.9, 5)]
    )
    cn = so.surface_normals(corner, 5, 0.2, 0.1)
    assert np.isnan(cn[5]).all()  # the corner point itself


def test_a_scan_matched_turn_keeps_the_floor_plan_tracker_off_the_furniture() -> None:
    """``MotionConfig.matched_turn_noise``: tuning building 16's floor plan (setup 2), tracked
    with its odometry from the true pose of scan 160. With the raw odometry's turn noise on
    the scan-matched increments the tracker can slide onto furniture (measured: 0.47-0.80 m
    within 10 scans, depending on the tour's last bits); with a matched increment's sigmas the
    published pose (tracked, or dead-reckoned where the plan explains too little) stays on
    the true pose, and never further off than with the raw noise."""
    from sim_publisher.generator import BuildingParams, generate_building
    from sim_publisher.scenario import building_setup

    su = building_setup(generate_building(16, BuildingParams(people=0)), 2, seed=0)
    base = ShapeConfig.for_kind("schematic")

    def worst(share: float) -> float:
        cfg = base.model_copy(
            update={"motion": base.motion.model_copy(update={"matched_turn_noise": share})}
        )
        loc = GlobalShapeLocalizer(su.map_data, su.truth[160].copy(), cfg)
        err = []
        for i in range(160, 180):
            est = loc.update(*su.scan(i), su.odom[i])
            # the plan explains a third of these scans: tracked or dead-reckoned, never lost
            # to a search
            assert est.state in ("tracking", "dead_reckoning"), (i, est.state)
            err.append(float(np.hypot(*(est.pose[:2] - su.truth[i][:2]))))
        return max(err)

    matched = worst(0.0)
    assert matched < 0.3
    assert matched <= worst(1.0)
