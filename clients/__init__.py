"""shapeloc clients: the Python client library (:mod:`clients.client`) and the ``shapeloc`` CLI.

Never imports the simulator (:mod:`sim_publisher` sits above and uses this library).
"""
