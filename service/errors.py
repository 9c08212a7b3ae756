"""The one error hierarchy of shapeloc.

Dependency-free on purpose: the wire (:mod:`schemas`), the core (:mod:`service.core`) and every
edge import it, so neither the wire nor the core has to import the other.

Every error the project raises on purpose derives from :class:`ShapelocError`. The transport
layer (the Zenoh node) turns these into ``reply_err`` payloads and notices on
``<prefix>/errors``; anything else escaping a handler is a bug and is reported as such.
"""

from __future__ import annotations


class ShapelocError(Exception):
    """Base class of all shapeloc errors."""


class InvalidMessage(ShapelocError, ValueError):
    """A wire message (or a file holding one) failed validation; the text says precisely why."""


class InvalidWorld(ShapelocError, ValueError):
    """A world file is malformed; the text names the feature and the problem."""


class UnknownRobot(ShapelocError, LookupError):
    """A request names a robot that has no configuration."""


class UnknownMap(ShapelocError, LookupError):
    """A request names a map id that is not stored."""


class StateError(ShapelocError):
    """Persisted state is missing, unreadable or corrupt (never reset silently)."""


class LocalizationError(ShapelocError, ValueError):
    """The localisation core was given input it cannot use (e.g. mismatched array lengths)."""


class Unreachable(ShapelocError, ConnectionError):
    """No Zenoh peer/router could be reached at the configured endpoints."""


class ServiceTimeout(ShapelocError, TimeoutError):
    """A request got no reply within its timeout (service down, or not serving that key)."""


class RemoteError(ShapelocError):
    """The service answered a request with ``reply_err``; the text is the service's reason."""


class LogFormatError(ShapelocError, ValueError):
    """A recorded log (ROS bag, CARMEN log, reference or relations file) is malformed or cannot be
    used; the text names the file, the line or message, and the problem."""
