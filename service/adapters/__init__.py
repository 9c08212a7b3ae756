"""Adapters beside the core, free of Zenoh (layer 3): map files and map tools (``maps``), log
readers (``logs``) and the conversion between wire messages and the core's types
(``convert``)."""
