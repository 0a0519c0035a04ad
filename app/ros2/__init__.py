"""The service as a ROS 2 node on rmw_zenoh's wire format (docs/ros2.md): what the loop
publishes, out on ROS topics; with ``--ros2-control``, STOP and goals in; and an emulated
ROS 2 base for tests and demos."""
