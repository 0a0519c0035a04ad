"""What the loop runs on, behind app.contracts: the world the services hand the loop (world),
the simulated team (sim), real robots (hardware), a fleet arena's team and its feedback (arena),
the truth and vision feedbacks (feedback), cameras, videos and image folders (camera), the serial
follower link (serial_link, with link_auth and link_stats), the shared radio (radio) and its keys
(radio_keys), the emulated followers (emulator), the ROS 2 node's wire (ros2), and the link
registry that maps a link spec's scheme to its parser and factory (links)."""
