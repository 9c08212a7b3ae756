"""shapeloc clients: the Python client (:mod:`clients.client`), the ``shapeloc`` CLI and tools."""
