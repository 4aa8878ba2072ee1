"""The host daemon: reads the gateways' serial lines and publishes the skin on ZeroMQ.

Sans-I/O core (:mod:`cellbridge.daemon.core.pipeline`: bytes and a time in, messages out),
thin asyncio shells around it (links, publisher, control, service). It uses the
protocol layer through :mod:`cellbridge.daemon.core.wire`, the tactile physics through
:mod:`cellbridge.daemon.core.frontend`, :mod:`~cellbridge.daemon.core.elements` and
:mod:`~cellbridge.daemon.core.contacts`, and never the emulator: a robot runs the daemon alone.
"""
