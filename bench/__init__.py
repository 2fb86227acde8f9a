"""Benchmarks: `make bench` (full) and `make bench-quick` measure floors, the peer (Redis) and CAST side by side."""
