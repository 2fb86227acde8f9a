"""A component process loads only what carrying its token and reaching its server need.

Every Python component `cast run` starts is ``python -m cast.run module:Class`` (cast.client.runner):
the modules it imports at start are CPU every component pays before its first call (docs/decisions.md,
"What a component process imports").
"""

from __future__ import annotations

import json
import subprocess
import sys

from cast.auth import TokenSigner
from cast.core.records import Identity
from cast.version import library_version

# PyJWT (with the cryptography package it loads) is for making and checking tokens, which the
# orchestrator and the server do; importlib.metadata (with the email parser) was only the version.
NOT_AT_START = {"jwt", "cryptography", "importlib.metadata", "email.parser"}


def test_a_component_process_imports_no_token_signing_or_package_metadata() -> None:
    code = "import json, sys\nimport cast.client.runner\nprint(json.dumps(sorted(sys.modules)))"
    done = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=60, check=True)
    loaded = set(json.loads(done.stdout))
    assert "cast.client.component" in loaded and "grpc" in loaded
    assert not NOT_AT_START & loaded, sorted(NOT_AT_START & loaded)


def test_tokens_are_still_made_and_checked_where_they_are_needed() -> None:
    signer = TokenSigner(b"k" * 32)
    token = signer.issue(Identity("c1", "sa", False), ttl_seconds=60)
    assert signer.verify(token) == Identity("c1", "sa", False)


def test_the_library_version_is_the_release_file() -> None:
    from tests.conftest import ROOT

    assert library_version() == (ROOT / "VERSION").read_text().strip()
