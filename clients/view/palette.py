"""The colours of the live view and the recordings: one table, used by the page and the recorder.

A robot is drawn in the colour of its pose's ``status``. The wire's statuses today are
``tracking``, ``initializing`` (a global search runs: drawn as *searching*) and ``lost``;
``dead_reckoning`` is here for a service that reports it. A status this table does not know
is drawn in :data:`UNKNOWN_COLOUR`, so a newer service never breaks the view. The page gets
the table from the server (its ``hello`` message) and has no colours of its own.
"""

from __future__ import annotations

from typing import Final

#: Status -> (colour, label shown in the legend). Colours are ``#rrggbb``.
STATUS_COLOURS: Final[dict[str, tuple[str, str]]] = {
    "tracking": ("#1a9850", "tracking"),
    "dead_reckoning": ("#e6a100", "dead reckoning"),
    "initializing": ("#2c6fdb", "searching"),
    "lost": ("#d7301f", "lost"),
}
#: Any status not in :data:`STATUS_COLOURS` (and robots with no pose yet).
UNKNOWN_COLOUR: Final[str] = "#8c8c8c"
#: Scan points drawn at the published pose: a colour no status uses.
SCAN_COLOUR: Final[str] = "#c51b8a"
#: Candidate places of a global search (outlined arrows).
CANDIDATE_COLOUR: Final[str] = "#2c6fdb"
#: The selected map's lines, and a second map drawn under it for comparison.
MAP_COLOURS: Final[dict[str, str]] = {"metric": "#303030", "schematic": "#4a4a8c"}
OVERLAY_COLOUR: Final[str] = "#c8c8c8"


def status_colour(status: str | None) -> str:
    """The colour of ``status`` (:data:`UNKNOWN_COLOUR` for ``None`` or an unknown one)."""
    entry = STATUS_COLOURS.get(status or "")
    return entry[0] if entry is not None else UNKNOWN_COLOUR


def rgba(colour: str, alpha: float = 1.0) -> dict[str, float]:
    """``#rrggbb`` as ``{"r", "g", "b", "a"}`` floats in [0, 1] (Foxglove's ``Color``)."""
    if len(colour) != 7 or colour[0] != "#":
        raise ValueError(f"colour must be #rrggbb, got {colour!r}")
    r, g, b = (int(colour[i : i + 2], 16) / 255.0 for i in (1, 3, 5))
    return {"r": r, "g": g, "b": b, "a": float(alpha)}


def palette_message() -> dict[str, object]:
    """The table as the page receives it."""
    return {
        "status": {k: {"colour": c, "label": lab} for k, (c, lab) in STATUS_COLOURS.items()},
        "unknown": UNKNOWN_COLOUR,
        "scan": SCAN_COLOUR,
        "candidate": CANDIDATE_COLOUR,
        "map": dict(MAP_COLOURS),
        "overlay": OVERLAY_COLOUR,
    }
