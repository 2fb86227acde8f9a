"""Entry schemas (validation, JSON rendering) and tokens."""

from __future__ import annotations

import pytest
from cast_testing_pb2 import Counter, Pose

from cast.auth import TokenSigner, peek
from cast.core.host import MemoryHost
from cast.core.records import Identity
from cast.core.schemas import SchemaRegistry, files_of
from cast.errors import InvalidArgumentError, NotFoundError, UnauthenticatedError


def test_registered_types_are_validated_and_rendered() -> None:
    reg = SchemaRegistry()
    types = reg.register(files_of(Pose.DESCRIPTOR))
    assert {"cast.testing.Pose", "cast.testing.Counter"} <= set(types)
    data = Pose(x=1.5, label="cup", tags=["red"]).SerializeToString()
    reg.validate("cast.testing.Pose", data)
    assert reg.to_json("cast.testing.Pose", data) == {"x": 1.5, "label": "cup", "tags": ["red"]}
    with pytest.raises(InvalidArgumentError, match="does not parse as cast.testing.Pose"):
        reg.validate("cast.testing.Pose", b"\xff\xff\xff")
    reg.validate("unknown.Type", b"\xff\xff\xff")  # no schema: passes through
    with pytest.raises(NotFoundError):
        reg.to_json("unknown.Type", b"")


def test_host_refuses_bytes_that_do_not_parse_as_their_registered_type() -> None:
    reg = SchemaRegistry()
    reg.register(files_of(Counter.DESCRIPTOR))
    host = MemoryHost(["vision"], validator=reg.validate)
    who = Identity("a", "vision")
    host.add(who, "vision", "ok", "cast.testing.Counter", Counter(value=1).SerializeToString())
    with pytest.raises(InvalidArgumentError, match="does not parse"):
        host.add(who, "vision", "bad", "cast.testing.Counter", b"\x08")  # truncated varint
    with pytest.raises(InvalidArgumentError):
        host.overwrite(who, "vision", "ok", "cast.testing.Counter", b"\x0a\x05ab")  # length past the end
    assert host.get(who, "vision", "ok").version == 0 and not host.exists(who, "vision", "bad")


def test_tokens_verify_and_forgeries_fail() -> None:
    signer = TokenSigner(b"s" * 32)
    token = signer.issue(Identity("comp", "vision", True))
    assert signer.verify(token) == Identity("comp", "vision", True)
    assert peek(token) == Identity("comp", "vision", True)
    other = TokenSigner(b"t" * 32)
    with pytest.raises(UnauthenticatedError, match="signature does not match"):
        other.verify(token)
    header, _, sig = token.split(".")
    # Claims of another identity under the real signature: refused.
    forged = TokenSigner(b"t" * 32).issue(Identity("boss", "vision", True)).split(".")[1]
    with pytest.raises(UnauthenticatedError, match="signature does not match"):
        signer.verify(f"{header}.{forged}.{sig}")
    with pytest.raises(UnauthenticatedError, match="malformed"):
        signer.verify("garbage")
    expired = signer.issue(Identity("comp", "vision"), ttl_seconds=-10)
    with pytest.raises(UnauthenticatedError, match="expired"):
        signer.verify(expired)


def test_tokens_are_standard_jwts_and_the_old_format_is_refused_with_advice() -> None:
    import jwt

    secret = b"s" * 32
    token = TokenSigner(secret).issue(Identity("comp", "vision", True), ttl_seconds=60)
    # Any JWT library reads it with the system's secret.
    claims = jwt.decode(token, secret, algorithms=["HS256"])
    assert (claims["c"], claims["s"], claims["p"]) == ("comp", "vision", True) and claims["exp"] > claims["iat"]
    assert "exp" not in jwt.decode(TokenSigner(secret).issue(Identity("comp", "vision")), secret, ["HS256"])
    # A token made by a JWT library with the same claims is accepted.
    made = jwt.encode({"c": "other", "s": "language", "p": False, "iat": 0}, secret, algorithm="HS256")
    assert TokenSigner(secret).verify(made) == Identity("other", "language", False)
    # "alg": "none" (unsigned) is refused.
    unsigned = jwt.encode({"c": "x", "s": "vision", "p": True, "iat": 0}, None, algorithm="none")
    with pytest.raises(UnauthenticatedError):
        TokenSigner(secret).verify(unsigned)
    # A token of the old '<payload>.<signature>' format: told to re-issue it.
    with pytest.raises(UnauthenticatedError, match="re-issue it with `cast token`"):
        TokenSigner(secret).verify("eyJjIjoiYyJ9.c2lnbmF0dXJl")
