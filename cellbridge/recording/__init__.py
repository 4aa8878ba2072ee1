"""Recordings of the daemon's topics in MCAP: record, replay, info."""
