"""The bridge emulator: chip, firmware, cell medium, world, virtual-time mesh, process shells.

Every model is a sans-I/O object fed bytes, events and a time in chip cycles
(``docs/emulator.md`` lists their calls); :mod:`.mesh.virtual` runs them all on one event
queue, and the ``realtime.process_*`` modules run them as real processes that talk over
ZeroMQ and serve each gateway's serial line on a pseudo-terminal.
"""
