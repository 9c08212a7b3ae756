"""shapeloc service: the pure localisation core (:mod:`service.core`) and its Zenoh node.

Importing :mod:`service` or :mod:`service.core` must not import zenoh or msgpack; only
:mod:`service.node.node` and :mod:`service.__main__` know about the transport.
"""

__version__ = "0.1.0"
