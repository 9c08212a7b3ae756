"""Wire contract of shapeloc (``wire-v1``).

Kept import-light on purpose: ``schemas.errors`` is used by the pure localisation core, which
must not pull in msgpack or zenoh. Import the models from ``schemas.messages`` and the
encode/decode helpers from ``schemas.codec``.
"""
