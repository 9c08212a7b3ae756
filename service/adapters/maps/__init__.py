"""Map formats and map tools (adapters beside the core; no zenoh).

World files (GeoJSON / WKT obstacle polygons), wire map files, ROS ``map_server`` occupancy
grids, maps built from logs, schematisation, map fidelity, and the files that keep each map's
view index of global localisation between runs (``index_files``). Everything here takes and
returns core types (:class:`service.core.types.MapData`, numpy arrays).
"""
