"""Shared fixtures of the service tests: ``harness``, a :class:`~tests.service.node.harness.Harness`
(a node on a fake Zenoh session, ``--workers 0``) in a fresh directory, stopped at teardown."""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path

import pytest

from tests.service.node.harness import Harness


@pytest.fixture
def harness(tmp_path: Path) -> Iterator[Harness]:
    h = Harness(tmp_path)
    yield h
    h.node.stop()
