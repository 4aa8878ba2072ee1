"""The service's operations: systemd notifications, CURVE security and peer bounds on the ZeroMQ sockets."""
