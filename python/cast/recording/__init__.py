"""Recordings of working memories: ``cast record``, ``cast replay`` and ``cast info`` (docs/recording.md).

A client-side tool: it reaches a running system through the client library
(watch streams that resume after a reconnect, the gRPC transport) and never
imports the server, the orchestrator or the command line. The mapping from
changes to channels (:mod:`cast.recording.channels`) is shared by every sink:
the MCAP file here, a live viewer elsewhere.
"""
