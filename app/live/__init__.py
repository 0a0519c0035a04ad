"""The loop and what runs beside it: the one loop (loop: observe, control step, link, publish),
its warm-up of numba's kernels before its clock starts (warmup), the tuning bench's step tests
(tuning) and gain sweeps in a worker process (sweep), and the service's configuration file
(config).

The loop types against app.contracts alone and imports nothing from app.backends: the services
hand it its world. What each tick produced is app.tick's, the operator's parameters app.params',
the service around the loop app.services.live's.

Nothing is re-exported here: importing ``app.tick`` must not import the loop."""
