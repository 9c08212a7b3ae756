"""Per-scan reference files and their attachment to the scans of the excerpts."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from service.adapters.logs import attach_reference, load_reference, read_log
from service.errors import LogFormatError

DATA = Path(__file__).resolve().parents[3] / "data" / "real"
LOGS = [
    ("intel.300.bag", "intel", 12),
    ("fr079.300.bag", "fr079", 292),
    ("mit-csail.300.clf.gz", "mit-csail", 49),
]


@pytest.mark.parametrize(("log", "name", "flag1"), LOGS)
def test_every_scan_gets_its_row_by_exact_stamp(log: str, name: str, flag1: int) -> None:
    track = load_reference(DATA / f"{name}.300.gfs_reference_per_scan.txt")
    assert len(track) == 300 and int(track.ok.sum()) == flag1
    info, it = read_log(DATA / log)
    scans = list(attach_reference(it, track, align="stamp", scan_count=info.scan_count))
    stamps = np.array([s.stamp for s in scans])
    # tolerance 0: the reference stamps are the raw scans' stamps exactly, row i = scan i
    assert np.array_equal(track.find(stamps, tolerance=0.0), np.arange(300))
    assert all(s.reference is not None for s in scans)
    assert np.array_equal(np.array([s.reference for s in scans]), track.poses)
    assert [s.reference_ok for s in scans] == track.ok.tolist()
    # odometry and scans are untouched
    assert all(s.odom is not None for s in scans)


def test_auto_alignment_and_missing_stamps(tmp_path: Path) -> None:
    track = load_reference(DATA / "fr079.300.gfs_reference_per_scan.txt")
    _, it = read_log(DATA / "fr079.300.bag", limit=5)
    scans = list(it)
    auto = list(attach_reference(scans, track))
    assert np.array_equal(np.array([s.reference for s in auto]), track.poses[:5])
    # a track whose stamps are shifted by 1 ms: by stamp nothing matches
    shifted = tmp_path / "shifted.txt"
    shifted.write_text(
        "".join(
            f"{t + 1e-3:.6f} {x} {y} {th} 1\n"
            for t, (x, y, th) in zip(track.stamps, track.poses, strict=True)
        )
    )
    moved = load_reference(shifted)
    by_stamp = list(attach_reference(scans, moved, align="stamp"))
    assert all(s.reference is None and not s.reference_ok for s in by_stamp)
    # auto falls back to order when the counts agree, refuses when they differ
    by_order = list(attach_reference(scans, moved, scan_count=300))
    assert by_order[3].reference == pytest.approx(track.poses[3])
    with pytest.raises(LogFormatError, match="cannot align"):
        list(attach_reference(scans, moved, scan_count=299))
    # an offset composes the reference with a laser-in-frame pose
    off = list(attach_reference(scans[:1], track, frame_offset=(1.0, 0.0, 0.0)))
    th = track.poses[0, 2]
    assert off[0].reference[:2] == pytest.approx(track.poses[0, :2] + [np.cos(th), np.sin(th)])


@pytest.mark.parametrize(
    ("text", "problem"),
    [
        ("1.0 0 0 0\n", "expected 'stamp x y theta flag'"),
        ("1.0 0 zero 0 1\n", "not a number"),
        ("1.0 0 0 0 2\n", "flag not 0/1"),
        ("1.0 0 inf 0 1\n", "non-finite"),
    ],
)
def test_malformed_reference_names_file_and_line(tmp_path: Path, text: str, problem: str) -> None:
    path = tmp_path / "ref.txt"
    path.write_text("# stamp x y theta flag\n0.5 0 0 0 1\n" + text)
    with pytest.raises(LogFormatError, match=rf"ref\.txt:3: .*{problem}"):
        load_reference(path)
    with pytest.raises(LogFormatError, match="cannot read"):
        load_reference(tmp_path / "absent.txt")
