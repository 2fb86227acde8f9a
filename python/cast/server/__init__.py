"""The gRPC server: servicers that translate between cast.v1 and the core."""
