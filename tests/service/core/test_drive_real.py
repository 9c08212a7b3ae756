"""The budgeted search over a drive on a real log, against the log's schematised map
(``tests/data/real/README.md``): fr079 scans 1174-1329, the robot starting unknown in a small
room at the west end and driving out along the corridor; scans 4361-4510 at the east end;
intel scans 8329-8648, one in four, along a corridor."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from service.adapters.maps.files import load_map_file
from service.core.factory import create_localizer
from service.core.global_localization import GlobalShapeLocalizer
from service.core.laser_odometry import LaserOdometryLocalizer
from service.core.pose import compose, invert
from service.core.probation import Probation
from service.core.types import Estimate, wrap_angle

DATA = Path(__file__).resolve().parents[2] / "data" / "real"

#: The drive without its later mechanisms: keyframes with the flat short credit, no search
#: during a probation, no polish on the window, the evidence rule on the window's mean only.
#: The mechanisms below were found on that drive and are checked on it; with the defaults
#: (``GlobalConfig.evidence_short_scale``, ``probation_searches``, ``window_polish``,
#: ``drive_recent_frames``) several of these starts are fixed at the true place without
#: reaching them, which each test checks too. The refinement and the held twins
#: (``verdict_refine``, ``twin_hold_kept``), the shortlist ranked by violations
#: (``shortlist_violation_beams``) and the contested window winners
#: (``probation_contest_all``) are off in it too.
BARE_DRIVE = {
    "evidence_short_scale": 0.0,
    "probation_searches": 0,
    "window_polish": False,
    "drive_recent_frames": 0,
    "verdict_refine": False,
    "twin_hold_kept": False,
    "shortlist_violation_beams": 0,
    "probation_contest_all": False,
}


def test_start_1174_is_fixed_at_the_true_place_and_its_twin_is_judged_by_the_drive(
    tmp_path: Path,
) -> None:
    """fr079 scans 1174-1329 (floor plan): the true place wins the drive's evidence by ~0.2
    from 7.6 m on, but its self-similarity check keeps finding an alias 31 m away that fits
    single scans better. Before commit 614352d the check found that twin on every try
    and the start was never fixed within 20 m.

    At the default 50 ms the search's work now finishes before the twin can hold the fix
    back, and the robot is fixed at the true place within the excerpt. At 20 ms (about the
    CPU the work model of 2026-11-23 bought at 50 on a floor plan) the twin joins the
    hypotheses, loses the drive by the margin and the check is answered (``twin_judged``);
    no pose is published away from the true place meanwhile (on the bare drive,
    ``BARE_DRIVE``)."""
    md = load_map_file(DATA / "fr079.schematic.geojson", kind="schematic")
    z = np.load(DATA / "fr079.1174-1329.npz")
    for budget in (50.0, 20.0):
        loc = create_localizer(
            "shape", md, None, cache_dir=tmp_path / str(budget), search_budget_ms=budget
        )
        assert isinstance(loc, LaserOdometryLocalizer)  # the factory default
        assert isinstance(loc.inner, GlobalShapeLocalizer)
        if budget == 20.0:
            loc.gconfig = loc.gconfig.model_copy(update=BARE_DRIVE)
        judged, fix = False, None
        for i in range(len(z["ranges"])):
            est = loc.update(z["ranges"][i], z["angles"][i], z["odom"][i])
            judged |= "twin_judged" in est.extras
            if est.status == "tracking" and z["flag"][i]:
                ref = z["reference"][i]
                assert np.hypot(*(est.pose[:2] - ref[:2])) < 0.5, (budget, i, est.pose, ref)
                assert abs(wrap_angle(float(est.pose[2] - ref[2]))) < np.deg2rad(10.0)
                fix = i if fix is None else fix
        if budget == 50.0:
            assert fix is not None, "not fixed within the excerpt"
        else:
            assert judged, "the drive never answered the twin check"


def test_a_probation_that_slides_off_the_odometry_into_walls_is_put_back(tmp_path: Path) -> None:
    """fr079 scans 4361-4510, east end of the floor plan: on a probation the tracker once slid
    along furniture, 0.34 m from the odometry's reckoning and into walls (24 % of beams
    through them, 8 % from the reckoned pose), and was published 0.52 m off. The check
    (``GlobalConfig.probation_slide``) on the excerpt's referenced scans, with a probation
    confirmed at the reference pose: a tracked pose 0.4 m off that lets more beams through
    walls is put back on the reckoned pose (and the tracker with it); one within
    ``probation_slide`` of it is left alone."""
    md = load_map_file(DATA / "fr079.schematic.geojson", kind="schematic")
    z = np.load(DATA / "fr079.4361-4510.npz")
    loc = create_localizer("shape", md, None, cache_dir=tmp_path, search_budget_ms=50.0)
    assert isinstance(loc, LaserOdometryLocalizer)  # the factory default
    assert isinstance(loc.inner, GlobalShapeLocalizer)
    g = loc.gconfig
    put_back, checked = 0, 0
    for i in np.flatnonzero(z["flag"])[::10]:
        r, a, odom, ref = z["ranges"][i], z["angles"][i], z["odom"][i], z["reference"][i]
        # the probation confirmed at the reference pose two scans earlier
        j = max(int(i) - 2, 0)
        start = compose(ref, compose(invert(odom), z["odom"][j]))
        loc._probation = Probation(
            track=None,
            left=1.0,
            ambiguity=0.0,
            start=start,  # type: ignore[arg-type]
            start_odom=z["odom"][j].copy(),
        )
        loc._last_odom = odom.copy()
        loc.tracker.reset(ref, odom)
        # the tracked pose slid 0.4 m to whichever side lets the most beams through walls
        sides = [
            ref + np.array([0.4 * np.cos(t), 0.4 * np.sin(t), 0.0])
            for t in np.arange(8) * np.pi / 4
        ]
        v = loc.tracker.violations(r, a, [ref, *sides])
        slid = sides[int(np.argmax(v[1:]))]
        if max(v[1:]) <= v[0] + g.probation_slide_violation:
            continue
        checked += 1
        est = Estimate(pose=slid.copy(), status="initializing", score=0.5, extras={})
        loc._slide_check(r, a, est)
        assert "slide_reset" in est.extras, i
        assert np.allclose(est.pose, ref, atol=1e-6)
        put_back += 1
        near = Estimate(
            pose=ref + np.array([0.1, 0.0, 0.0]), status="initializing", score=0.5, extras={}
        )
        loc._slide_check(r, a, near)
        assert "slide_reset" not in near.extras and "slide_violation" not in near.extras
    assert checked >= 3 and put_back == checked


def test_a_winner_of_the_drive_is_held_through_rejected_scans_it_does_not_contradict(
    tmp_path: Path,
) -> None:
    """fr079 scans 4401-4510, the east hall, which the floor plan draws as an outline: the
    true place wins the evidence rule and goes on probation at scan 4482, then the tracker
    rejects most scans (the plan explains a quarter of the returns). Those rejections no
    longer fail the probation while the drive's evidence still names the place and the scans
    do not run through walls (``GlobalConfig.probation_hold_violation``); before, the
    probation failed on its third rejection (4486) and the next one too (4492). With holding
    switched off (0) it fails again."""
    md = load_map_file(DATA / "fr079.schematic.geojson", kind="schematic")
    z = np.load(DATA / "fr079.4361-4510.npz")
    first = 4401 - 4361
    for hold in (None, 0.0):
        loc = create_localizer("shape", md, None, cache_dir=tmp_path, search_budget_ms=50.0)
        assert isinstance(loc, LaserOdometryLocalizer)  # the factory default
        assert isinstance(loc.inner, GlobalShapeLocalizer)
        if hold is not None:
            loc.gconfig = loc.gconfig.model_copy(update={"probation_hold_violation": hold})
        held = failed = on_probation = 0
        for i in range(first, len(z["ranges"])):
            est = loc.update(z["ranges"][i], z["angles"][i], z["odom"][i])
            assert est.status != "tracking", i  # the probation's 2 m end after the excerpt
            held += "probation_held" in est.extras
            failed += "probation_failed" in est.extras
            if "probation" in est.extras and z["flag"][i]:
                on_probation += 1
                assert np.hypot(*(est.pose[:2] - z["reference"][i][:2])) < 0.3, i
        if hold is None:
            assert failed == 0 and held >= 10 and on_probation >= 20, (failed, held)
        else:
            assert failed >= 1 and held == 0, (failed, held)


def test_a_probation_whose_winner_the_drive_explains_worse_fails_at_its_end(
    tmp_path: Path,
) -> None:
    """fr079 scans 2871-2985 (floor plan) at a 45 ms search budget: a single scan's rules fix a
    place 18 m off (it leads the drive's keyframes by less than ``drive_margin``), and its
    2 m probation, tracked without a rejected scan, would publish it at scan 2946. The
    probation keeps up the drive's evidence, on which the true place explains the keyframes
    better by its end, so it fails there (``GlobalConfig.probation_verdict``) and the true
    place is fixed by the evidence rule 3 m later. With the verdict off the wrong place is
    published. Both on the bare drive (``BARE_DRIVE``); with the defaults the place 18 m off
    never wins and the true place is fixed, no pose published elsewhere."""
    md = load_map_file(DATA / "fr079.schematic.geojson", kind="schematic")
    z = np.load(DATA / "fr079.2871-2985.npz")
    for verdict in (True, False, None):
        loc = create_localizer("shape", md, None, cache_dir=tmp_path, search_budget_ms=45.0)
        assert isinstance(loc, LaserOdometryLocalizer)  # the factory default
        assert isinstance(loc.inner, GlobalShapeLocalizer)
        assert loc.gconfig.probation_verdict
        if verdict is not None:
            update = {**BARE_DRIVE, "probation_verdict": verdict}
            loc.gconfig = loc.gconfig.model_copy(update=update)
        beaten, wrong, fix = 0, 0, None
        for i in range(len(z["ranges"])):
            est = loc.update(z["ranges"][i], z["angles"][i], z["odom"][i])
            beaten += "probation_beaten" in est.extras
            if est.status == "tracking" and z["flag"][i]:
                ref = z["reference"][i]
                ok = np.hypot(*(est.pose[:2] - ref[:2])) < 0.5 and abs(
                    wrap_angle(float(est.pose[2] - ref[2]))
                ) < np.deg2rad(10.0)
                wrong += not ok
                fix = i if fix is None and ok else fix
        if verdict is None:
            assert wrong == 0 and fix is not None, (beaten, wrong, fix)
        elif verdict:
            assert beaten == 1 and wrong == 0 and fix is not None, (beaten, wrong, fix)
        else:
            assert beaten == 0 and wrong > 0, (beaten, wrong)


def test_a_winner_of_the_drive_is_confirmed_under_the_prior_the_drive_gives(
    tmp_path: Path,
) -> None:
    """fr079 scans 4371-4510 (the east hall, floor plan): the evidence rule names the true
    place 7.7 m into the drive. Confirmed with the weak prior that lets the scan decide alone,
    the tracker swung the pose 0.2-0.5 m and up to 34 degrees, or rejected the scan, on every
    try (a third of the scan lies on the plan) and the start was never fixed in 20 m. Under
    the prior the drive gives (``GlobalConfig.confirm_drive_prior``) it is confirmed, and its
    probation tracks the true place. Both on the bare drive (``BARE_DRIVE``); with the defaults
    (the winner polished on the window, ``window_polish``) it is confirmed and tracked too."""
    md = load_map_file(DATA / "fr079.schematic.geojson", kind="schematic")
    z = np.load(DATA / "fr079.4361-4510.npz")
    first = 4371 - 4361
    for prior in (True, False, None):
        loc = create_localizer("shape", md, None, cache_dir=tmp_path, search_budget_ms=50.0)
        assert isinstance(loc, LaserOdometryLocalizer)  # the factory default
        assert isinstance(loc.inner, GlobalShapeLocalizer)
        assert loc.gconfig.confirm_drive_prior
        if prior is not None:
            update = {**BARE_DRIVE, "confirm_drive_prior": prior}
            loc.gconfig = loc.gconfig.model_copy(update=update)
        refused = on_probation = 0
        for i in range(first, len(z["ranges"])):
            est = loc.update(z["ranges"][i], z["angles"][i], z["odom"][i])
            refused += "confirm_rejected" in est.extras
            if "probation" in est.extras:
                on_probation += 1
                if z["flag"][i]:
                    assert np.hypot(*(est.pose[:2] - z["reference"][i][:2])) < 0.3, i
                    ref = z["reference"][i]
                    assert abs(wrap_angle(float(est.pose[2] - ref[2]))) < np.deg2rad(5.0), i
        if prior is None or prior:
            assert on_probation >= 15, (refused, on_probation)
        else:
            assert on_probation == 0 and refused >= 3, (refused, on_probation)


def _reckoned(z: np.lib.npyio.NpzFile, i: int) -> np.ndarray:
    """The reference pose of window row ``i``: its own, else the nearest earlier referenced
    row's moved by the odometry between the two."""
    j = max(k for k in range(i + 1) if z["flag"][k])
    return compose(z["reference"][j], compose(invert(z["odom"][j]), z["odom"][i]))


def test_a_scan_that_explains_itself_better_elsewhere_is_not_confirmed_under_the_prior(
    tmp_path: Path,
) -> None:
    """intel scans 8329-8648 fed one in four (floor plan, tuning split): the evidence rule's
    winner lies 1.37 m along a corridor from the true place. Its confirming scan, fitted
    alone, lands 0.63 m from it (support 0.91), fails the confirmation bars, and under the
    winner's prior the scan fits at the winner with support 0.69. Confirmed there, the
    probation followed the wrong place and the robot was published 0.86 m off; the bar on the
    unexplained shares (``GlobalConfig.confirm_unexplained``: 0.09 against 0.31) lets the
    place the scan pointed to join the hypotheses instead, the drive judges it, and the robot
    is fixed at the true place (13.2 m into the drive on the bench, against the wrong fix's
    10.4 m). With the bar at (nearly) 0 the wrong fix returns. Both on the bare drive
    (``BARE_DRIVE``); with the defaults the winner is polished on the window first
    (``window_polish``), is confirmed alone and the first fix lies at the true place."""
    md = load_map_file(DATA / "intel.schematic.geojson", kind="schematic")
    z = np.load(DATA / "intel.8329-8648.every4.npz")
    for bar in (0.5, 1e-6, None):
        loc = create_localizer("shape", md, None, cache_dir=tmp_path, search_budget_ms=50.0)
        assert isinstance(loc, LaserOdometryLocalizer)  # the factory default
        assert isinstance(loc.inner, GlobalShapeLocalizer)
        assert loc.gconfig.confirm_unexplained == 0.5
        if bar is not None:
            update = {**BARE_DRIVE, "confirm_unexplained": bar}
            loc.gconfig = loc.gconfig.model_copy(update=update)
        elsewhere, first = 0, None
        for i in range(len(z["ranges"])):
            est = loc.update(z["ranges"][i], z["angles"][i], z["odom"][i])
            elsewhere += "confirm_elsewhere" in est.extras
            if est.status == "tracking" and first is None:
                first = np.hypot(*(est.pose[:2] - _reckoned(z, i)[:2]))
        assert first is not None, bar
        if bar is None:
            assert first < 0.3, (elsewhere, first)
        elif bar == 0.5:
            assert elsewhere == 1 and first < 0.3, (elsewhere, first)
        else:
            assert elsewhere == 0 and first > 0.7, (elsewhere, first)


def test_a_winner_is_held_against_the_rivals_it_won_against(tmp_path: Path) -> None:
    """fr079 scans 4327-4539 fed one in three (floor plan, tuning split; the drive bench's
    ``--real-stride 3`` start 4327 in the east hall): the window names the true place at
    10.5 m and it goes on probation; the tracker rejects three scans and the drive's evidence
    holds it. With ``probation_contest_all`` the probation's search adds places to the
    hypotheses meanwhile, scored on a few keyframes yet; weighed against those as well the
    hold failed and the robot was not fixed within the excerpt (measured, forgetting the
    rivals below). Weighed against the places it won against (``Probation.rivals``) it is
    held and fixed at the true place (scan 4519, 0.06 m); the new places were the verdict's
    to judge at the end."""
    md = load_map_file(DATA / "fr079.schematic.geojson", kind="schematic")
    z = np.load(DATA / "fr079.4327-4539.every3.npz")

    def first_fix(forget: bool) -> tuple[int, float, bool, bool]:
        """(scan of the first fix or -1, its error m, held through rejections, places
        joined during a probation)."""
        loc = create_localizer("shape", md, None, cache_dir=tmp_path, search_budget_ms=50.0)
        assert isinstance(loc, LaserOdometryLocalizer)  # the factory default
        assert isinstance(loc.inner, GlobalShapeLocalizer)
        assert loc.gconfig.probation_contest_all
        grew = False
        for i in range(len(z["ranges"])):
            est = loc.update(z["ranges"][i], z["angles"][i], z["odom"][i])
            p = loc._probation
            if p is not None:
                grew |= any(all(t is not r for r in p.rivals) for t in loc._tracks)
                if forget:
                    p.rivals = ()
            if est.status == "tracking":
                err = float(np.hypot(*(est.pose[:2] - z["reference"][i][:2])))
                return int(z["scan"][i]), err, "probation_held" in est.extras, grew
        return -1, float("inf"), False, grew

    scan, err, held, grew = first_fix(False)
    assert scan > 0 and err < 0.5 and held and grew, (scan, err, held, grew)
    scan, _err, _held, _grew = first_fix(True)
    assert scan == -1, scan
