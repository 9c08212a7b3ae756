"""The Zenoh node of the localizer service (layer 4): the session's subscribers and queryables,
the scan intake, the workers that run the core, the state store, settings and the cluster of
instances. Only this layer (and the clients) know Zenoh; the core below takes arrays."""
