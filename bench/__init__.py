"""Benchmarks that print tables: run each from the repository root as a module,
``python -m bench.<name>`` (e.g. ``python -m bench.bench_service --help``); ``make bench`` runs
every ``bench_*`` module except the long real-log ones. The other modules are their shared
parts; :mod:`bench.harness` (services and routers on loopback) is shared with the integration
tests. Not installed with the package: the benchmarks need the repository."""
