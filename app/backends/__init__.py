"""Concrete ports: the simulated team today; camera, video and serial link later."""
