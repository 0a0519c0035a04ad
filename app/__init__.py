"""omniformation app: everything that touches time, threads, files, ports and the browser.

    cli/        one module per subcommand family (`omniformation COMMAND`); bench/ one per benchmark family
    services/   the composition roots: the live service, a replay's page, the fleet page, a session's recording
    fleet/      the fleet on Eclipse Zenoh: a leader's bridge, the arena, orphan adoption
    dashboard/  the viser page: 3D scene, plots, controls, camera, recordings, calibration and tuning panels
    recording/  recordings: schema, writer, reader, rerun, report, the fleet's recorder
    live/       the loop, the tuning bench's step tests and sweeps, the service's config
    backends/   what the loop talks to: simulated team, real robots, an arena's team, feedback (truth or
                vision), cameras, serial link, radio, emulator
    contracts   the Protocols the loop is typed against, and the Rig value
    params      the operator's parameters and their store, read by the loop once per tick
    tick        one tick's state (what the dashboard, the recorder and a replay read), the session's clock
                and the publisher that hands a slow reader the newest state
    figures     static figures in the paper's style (matplotlib): the report's, the tuning and calibration panels'
    keys        the names on a fleet's bus
    files       where the project's files are, and reading the ones people give
    memory      glibc's malloc set for hours of frames, and the heap's accounts
    realtime    real-time scheduling for the threads on a frame's way to the robots
    processes   stopping child processes as a person stops them
"""
