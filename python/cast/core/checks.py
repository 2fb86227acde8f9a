"""Argument checks of the WM core and the wording of its refusals.

Every refusal names the thing, the limit and what to do; the host calls these
before it takes its mutex where it can, so bad input costs no contention.
"""

from __future__ import annotations

import re

from cast.core.memory import LockState
from cast.core.records import Limits
from cast.errors import InvalidArgumentError

__all__ = ["TypeChecker", "check_id", "check_sa_name", "locked_message", "missing_message"]

_TYPE_NAME = re.compile(r"[A-Za-z_][A-Za-z0-9_]*(\.[A-Za-z_][A-Za-z0-9_]*)*\Z")
_CONTROL = re.compile(r"[\x00-\x1f\x7f]")


def check_id(entry_id: str, limits: Limits) -> None:
    """INVALID_ARGUMENT unless ``entry_id`` is 1 to ``max_id_bytes`` bytes of printable text."""
    # Most ids are short printable ASCII: one C-level test settles those (bytes == characters,
    # no control characters) before the full check, which every write would otherwise pay.
    if entry_id.isascii() and entry_id.isprintable() and 0 < len(entry_id) <= limits.max_id_bytes:
        return
    if not entry_id:
        raise InvalidArgumentError("entry id is empty: give an id of 1 to 256 bytes (new_id() makes one)")
    size = len(entry_id.encode("utf-8", "surrogatepass"))
    if size > limits.max_id_bytes:
        raise InvalidArgumentError(
            f"entry id '{entry_id[:40]}...' is {size} bytes, over the limit of {limits.max_id_bytes} "
            "bytes: use a shorter id"
        )
    if _CONTROL.search(entry_id):
        raise InvalidArgumentError(f"entry id {entry_id!r} contains control characters: use printable text")


class TypeChecker:
    """Checks entry type names, remembering (up to a bound) the ones that passed."""

    def __init__(self, limits: Limits) -> None:
        self._limits = limits
        self._good: set[str] = set()

    def check(self, type_name: str) -> None:
        """INVALID_ARGUMENT unless ``type_name`` is a full protobuf message name."""
        if type_name in self._good:
            return
        if not type_name:
            raise InvalidArgumentError(
                "entry type is empty: the value must be a google.protobuf.Any whose type_url names a message"
            )
        if len(type_name) > self._limits.max_type_bytes or not _TYPE_NAME.match(type_name):
            raise InvalidArgumentError(
                f"entry type {type_name[:80]!r} is not a full protobuf message name such as 'pkg.Message' "
                f"(letters, digits, '_' and '.', at most {self._limits.max_type_bytes} characters)"
            )
        if len(self._good) < 10_000:
            self._good.add(type_name)


def check_sa_name(name: str) -> None:
    """INVALID_ARGUMENT unless ``name`` is a valid subarchitecture name."""
    if not name or not re.fullmatch(r"[A-Za-z0-9_.\-]{1,128}", name):
        raise InvalidArgumentError(
            f"subarchitecture name {name!r} is invalid: use 1 to 128 letters, digits, '_', '-' or '.'"
        )


def missing_message(sa: str, entry_id: str) -> str:
    """``no entry 'x' in subarchitecture 'y'``."""
    return f"no entry '{entry_id}' in subarchitecture '{sa}'"


def locked_message(sa: str, entry_id: str, lock: LockState, action: str) -> str:
    """Why ``action`` is refused under ``lock``, naming its holder and mode."""
    return (
        f"cannot {action} entry '{entry_id}' in subarchitecture '{sa}': it is locked ({lock.mode.name}) by "
        f"component '{lock.holder}'; wait for the unlock (lock() blocks until then) or try again later"
    )
