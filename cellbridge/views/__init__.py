"""Views of a running daemon for people: ``watch`` (terminal), ``web`` (a page), ``foxglove``.

Each is a ZeroMQ subscriber of the daemon's documented API (``docs/zmq-api.md``), never
part of the daemon process. They share one sans-I/O view model
(:mod:`cellbridge.views.model`) and one ZeroMQ shell (:mod:`cellbridge.views.source`).
"""
