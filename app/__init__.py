"""omniformation app: everything that touches time, threads, files, ports and the browser.

    cli/        one module per subcommand family (`omniformation COMMAND`)
    live/       the loop, its tick state, parameters, feedback, the service and its config
    backends/   what the loop talks to: simulated team, real robots, cameras, serial link, emulator
    recording/  recordings: schema, writer, reader, replay, rerun, report and plots
    dashboard/  the viser page: 3D scene, plots, controls, camera and recordings panels
    contracts   the Protocols the loop is typed against, and the Rig value
    files       where the project's files are, and reading the ones people give
"""
