"""Fixtures of the live-view tests: the integration tests' real-process fixtures
(``spawn_service`` and its helpers in tests/integration/conftest.py), loaded from that file
rather than copied (a conftest cannot be imported under ``--import-mode=importlib``)."""

from __future__ import annotations

import importlib.util
import sys
from pathlib import Path

_PATH = Path(__file__).resolve().parents[2] / "integration" / "conftest.py"
_spec = importlib.util.spec_from_file_location("shapeloc_integration_fixtures", _PATH)
assert _spec is not None and _spec.loader is not None
integration = importlib.util.module_from_spec(_spec)
sys.modules[_spec.name] = integration  # dataclasses look their module up there
_spec.loader.exec_module(integration)

spawn_service = integration.spawn_service
