"""Wire contract of shapeloc (``wire-v1``): message models, codec, key helpers.

The wire does not know the localisation core: nothing here imports :mod:`service.core`.
Errors come from the project's one hierarchy, :mod:`service.errors`. Converting wire messages
to core types is the edge's job (:mod:`service.adapters.convert`). Import the models from
``schemas.messages`` and the encode/decode helpers from ``schemas.codec``.
"""
