"""The WM core: plain Python, no gRPC."""
