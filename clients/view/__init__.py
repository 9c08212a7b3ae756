"""The live view: ``shapeloc view`` (or ``python -m clients.view``) serves a page on localhost
that draws, live, the maps, every robot's pose, path, status, scan and search candidates, from
what the service publishes over Zenoh (see docs/view.md).

:func:`clients.view.server.main` runs it (a Zenoh config in, until a stop event);
:class:`~clients.view.server.ViewServer` is the server, :class:`~clients.view.state.ViewState`
the state it keeps, :mod:`clients.view.palette` the colours and :mod:`clients.view.headless` a
headless Chromium driver that looks at the page. This package module imports none of them, so
the CLI can show the defaults below without loading the web server.
"""

from typing import Final

#: Where the page is served by default: this machine only.
DEFAULT_HOST: Final = "127.0.0.1"
DEFAULT_PORT: Final = 8765
#: Frames pushed to each page per second.
DEFAULT_RATE_HZ: Final = 10.0
#: Niceness ``shapeloc view`` adds to itself: a best-effort client, it yields the CPU to the
#: localiser on a shared machine (``--nice 0`` keeps the priority it was started with).
DEFAULT_NICE: Final = 10
