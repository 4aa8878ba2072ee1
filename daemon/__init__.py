"""The host daemon: reads the gateways' serial lines and publishes the skin on ZeroMQ.

Sans-I/O core (:mod:`cellbridge.daemon.pipeline`: bytes and a time in, messages out),
thin asyncio shells around it (links, publisher, control, service). It imports the
protocol and tactile layers only through :mod:`cellbridge.daemon.wire` and
:mod:`cellbridge.daemon.physics`, and never the emulator: a robot runs the daemon alone.
"""
