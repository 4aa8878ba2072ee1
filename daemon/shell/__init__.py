"""The daemon's I/O shells around the cores: the asyncio service, serial links, ZeroMQ sockets, worker processes, files and its commands."""
