"""``cast export --validate VERSION``: the manifests checked against a Kubernetes version's schemas, offline.

``kubernetes-validate`` bundles the JSON schemas of each Kubernetes release
(1.25 on), so a person can check an export against the version their cluster
runs without a cluster; strict, so that a misspelt key is an error. It is an
optional dependency (the ``export`` extra: ``pip install cast-grpc[export]``);
``make setup`` installs it, and ``tests/export`` validates every export against
two versions with it.
"""

from __future__ import annotations

import re
from collections.abc import Iterable
from typing import Any

from cast.errors import InvalidArgumentError, NotFoundError

__all__ = ["validate_objects"]


def validate_objects(objects: Iterable[dict[str, Any]], version: str) -> list[str]:
    """What is wrong with each object for Kubernetes ``version`` (empty: every one is valid)."""
    try:
        from kubernetes_validate import utils  # type: ignore[import-untyped]  # the export extra; untyped
    except ImportError:
        raise NotFoundError("--validate needs the kubernetes-validate package: pip install 'cast-grpc[export]' "
                            "(make setup installs it)") from None
    known = sorted({".".join(v.split(".")[:2]) for v in utils.all_versions()}, key=_number)
    wanted = re.fullmatch(r"v?(\d+\.\d+)(\.\d+)?", version)
    if wanted is None or wanted[1] not in known:
        raise InvalidArgumentError(f"--validate {version}: give a Kubernetes version kubernetes-validate has the "
                                   f"schemas of: {', '.join(known)}")
    problems: list[str] = []
    for obj in objects:
        try:
            utils.validate(obj, wanted[1], strict=True)
        except utils.ValidationError as exc:
            where = ".".join(str(p) for p in exc.absolute_path) or "the top"
            hint = ""
            if "initContainers" in where and "restartPolicy" in exc.message:
                hint = " (the token-renewing sidecar of auth.token_ttl is a native sidecar: Kubernetes 1.29 or newer)"
            problems.append(f"{obj['kind']} {obj['metadata']['name']}: at {where}: {exc.message}{hint}")
    return problems


def _number(version: str) -> tuple[int, ...]:
    return tuple(int(part) for part in version.split("."))
