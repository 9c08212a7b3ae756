"""Pure localisation core: numpy arrays in, poses out. No zenoh, no msgpack.

Entry point for users: :func:`service.core.factory.create_localizer`.
"""
