"""``cast export``: a configuration as a cluster engine's own files (docs/deploy.md).

- :mod:`cast.export.kubernetes` and :mod:`cast.export.pods`: plain manifests and a
  ``kustomization.yaml`` (servers as Deployments or StatefulSets with a Service,
  components as Deployments or Jobs, the Secrets);
- :mod:`cast.export.systemd`: ``cast-system@.service`` and a ``cast-agent.service`` per host;
- :mod:`cast.export.images`: what runs in which image, and how;
- :mod:`cast.export.secrets`: the system secret and the TLS files as Secrets;
- :mod:`cast.export.files`: the output directory (never over files the export did not write);
- :mod:`cast.export.health_probe`: the servers' health probe over TLS, run inside their containers.

What an engine cannot express is refused before anything is written, on its
line, by :mod:`cast.config.engines` (``cast check --to ENGINE`` says the same).
The package depends on :mod:`cast.config` and nothing above it; only the
health probe, which runs in the cluster, talks gRPC.
"""

from __future__ import annotations

__all__: list[str] = []
