"""Wire code both sides share: what the client library and the server (and the tools) read and write alike.

Below the client and the server, above the core: ``values`` (type URLs, ``Any``, timestamps),
``describe`` (a system's description), ``metrics`` (the server's counts) and ``shared_memory``
(the frames of a shared-memory session). Protobuf only; no gRPC here.
"""
