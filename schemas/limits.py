"""Hard limits of the wire contract.

Every limit here is enforced on input (decode and model construction) so that an untrusted
peer cannot make the service allocate or compute without bound. Encoders enforce the payload
limit too, so the project never publishes a message that its own receivers would reject.
"""

from __future__ import annotations

import math

#: Largest accepted payload, in bytes (msgpack or JSON), checked before parsing.
MAX_PAYLOAD_BYTES: int = 16 * 1024 * 1024

#: Deepest accepted nesting of lists/maps (a map's polylines need 4: map, list, polyline, point).
MAX_NESTING: int = 16

#: Most beams in one scan (list elements, or float32 values in the bytes form).
MAX_BEAMS: int = 8192

#: Most polylines in one map.
MAX_POLYLINES: int = 20000

#: Most points over all polylines of one map.
MAX_MAP_POINTS: int = 200000

#: Identifiers (robot_id, map_id, instance_id, method): length range and character set.
ID_MIN_LEN: int = 1
ID_MAX_LEN: int = 64
ID_CHARS: str = "A-Za-z0-9_.-"

#: Longest free-text field (Map.name, ErrorNotice.error), in characters.
MAX_TEXT_LEN: int = 8192

#: Longest key expression carried inside a message (ErrorNotice.key), in characters.
MAX_KEY_LEN: int = 1024

#: Total scan field of view, (n - 1) * angle_increment, may not exceed this (radians).
MAX_FOV: float = 2.0 * math.pi + 1e-6

#: Largest integer counter (seq, health counters): what msgpack can carry (uint64).
MAX_UINT: int = 2**64 - 1

#: Most pose candidates in one PoseMsg (the best few hypotheses of a global search).
MAX_CANDIDATES: int = 16
