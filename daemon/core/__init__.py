"""The daemon's sans-I/O cores: bytes, readings and a time in, frozen messages out (no event loop, socket, clock or logger)."""
