"""The Python client library: transports, component model, runner."""
