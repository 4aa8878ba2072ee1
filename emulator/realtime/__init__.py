"""The real-time shells: one process per bridge, the medium, the world, their sockets, ptys and clocks, and the commands that start them."""
