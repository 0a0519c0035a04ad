"""The composition roots: each builds a page (or a process's whole composition) from the parts
below it, and closes what it built.

``run`` (`run`'s: a checked plan in, the running live service out, through one ExitStack),
``live`` (the operator's service: the loop, its page, its recorder), ``replay`` (a recording
played back on a page of its own), ``fleet_page`` (a fleet's one page: the bus side; its widgets
are app.dashboard.fleet_view's), ``arena`` (a fleet's shared world), ``recording`` (a live
service's recorder started as asked), ``bus`` (joining a fleet's bus), ``ros2_node`` (the
service as a ROS 2 node, an emulated base) and ``foxglove_attach`` (a session served to
Foxglove). The command line only checks arguments into their plans and calls them; nothing
below imports from here."""
