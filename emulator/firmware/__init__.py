"""One bridge's firmware as plain objects fed frames, events and a tick: sampling, link, routing, mesh time, readout, commands."""
