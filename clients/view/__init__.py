"""The live view: ``python -m clients.view`` serves a page on localhost that draws, live, the
maps, every robot's pose, path, status, scan and search candidates, from what the service
publishes over Zenoh (see docs/view.md).

:func:`main` runs it (a Zenoh config in, until a stop event); :class:`ViewServer` is the
server, :class:`ViewState` the state it keeps, :mod:`clients.view.palette` the colours and
:mod:`clients.view.headless` a headless Chromium driver that looks at the page.
"""

from clients.view.server import DEFAULT_PORT, ViewServer, main
from clients.view.state import ViewState

__all__ = ["DEFAULT_PORT", "ViewServer", "ViewState", "main"]
