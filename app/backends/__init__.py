"""What the loop talks to, behind app.contracts: the simulated team (sim), real robots
(hardware), cameras, videos and image folders (camera), the serial follower link
(serial_link) and the emulated followers it can talk to (emulator)."""
