"""The live service: the one loop (loop), what each tick produced (tick), the operator's
parameters (params), where poses come from (feedback), the service around the loop with its
viser server (service) and its configuration file (config).

Nothing is re-exported here: importing ``app.tick`` must not import the loop."""
