"""The orchestrator behind ``cast run``: servers, component processes, supervision, status."""
