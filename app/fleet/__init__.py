"""Several leaders on one bus (Eclipse Zenoh): each leader's bridge (bridge.py)."""
