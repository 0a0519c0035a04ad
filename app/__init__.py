"""omniformation app: everything that touches time, threads, files, ports and the browser.

    cli/        one module per subcommand family (`omniformation COMMAND`); bench/ one per benchmark family;
                each parses and checks its arguments, prints, and calls services
    services/   the composition roots: `run`'s (run: a checked plan in, the running service out), the live
                service, a replay's page, the fleet page's bus side, a session's recording, joining the
                fleet's bus, the ROS 2 node, Foxglove attached to a session
    fleet/      the fleet on Eclipse Zenoh: a leader's bridge, the arena, orphan adoption
    ros2/       the service as a ROS 2 node: its bridge, an emulated base, the session
    dashboard/  the viser page: 3D scene, plots, controls, camera, recordings, calibration and tuning panels,
                the fleet page's widgets (fleet_view)
    recording/  recordings: schema, writer, reader, rerun, report, the fleet's recorder
    live/       the loop, the tuning bench's step tests and sweeps, the service's config
    backends/   what the loop talks to: simulated team, real robots, an arena's team, feedback (truth or
                vision), cameras, serial link, radio, emulator
    contracts   the Protocols the loop is typed against, and the Rig value
    params      the operator's parameters and their store, read by the loop once per tick
    tick        one tick's state (what the dashboard, the recorder and a replay read), the session's clock
                and the publisher that hands a slow reader the newest state
    figures     static figures in the paper's style (matplotlib): the report's, the tuning and calibration panels'
    keys        the names on a fleet's bus, and a robot's one name on every page (R3; R3 (F1) on its leader's)
    files       where the project's files are, and reading the ones people give
    memory      glibc's malloc set for hours of frames, and the heap's accounts
    realtime    real-time scheduling for the threads on a frame's way to the robots
    processes   stopping child processes as a person stops them
"""
