"""Recorded sessions: what a file holds (schema), writing it (writer, session), reading it back
(reader), and what is done with one (replay, rerun, report and its plots, simulated runs as
recordings, CSV logs).

Nothing is re-exported here, so a reader never imports the writer's threads or the replay's server."""
