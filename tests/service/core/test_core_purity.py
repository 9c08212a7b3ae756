"""The localisation core is pure: importing and running it pulls in neither zenoh nor msgpack."""

from __future__ import annotations

import subprocess
import sys

CHECK = """
import sys
import numpy as np
from service.core.factory import create_localizer
from service.core.reloc.global_localization import GlobalShapeLocalizer  # noqa: F401
from service.core.baselines.icp import ICPLocalizer  # noqa: F401
from service.core.baselines.lines import LineLocalizer  # noqa: F401
from service.core.types import MapData

room = [[0, 0], [4, 0], [4, 3], [0, 3], [0, 0]]
md = MapData.from_lists("room", "metric", [room])
loc = create_localizer("shape", md, np.array([2.0, 1.5, 0.0]))
angles = np.linspace(-np.pi / 2, np.pi / 2, 181)
loc.update(np.full(181, 1.2), angles)
bad = sorted(m for m in sys.modules if m.split(".")[0] in ("zenoh", "msgpack"))
print(",".join(bad))
"""


def test_core_imports_neither_zenoh_nor_msgpack() -> None:
    out = subprocess.run(
        [sys.executable, "-c", CHECK], capture_output=True, text=True, timeout=120, check=True
    )
    assert out.stdout.strip() == "", f"core pulled in: {out.stdout.strip()}"
