"""The pytest plugin of cast.testing: the ``cast_system`` fixture and its marker.

Registered with pytest by the package (the ``pytest11`` entry point ``cast``),
so a test only names the fixture::

    @pytest.mark.cast_system(subarchitectures=["vision"])
    def test_counter_counts(cast_system: LocalSystem) -> None:
        cast_system.run(Counter, "counter", "vision", args={"to": 3})
        cast_system.wait_for_entry("vision", "count", Int64Value, Int64Value(value=3))

The marker takes :func:`cast.testing.start_system`'s arguments (on a test, a
class or a module's ``pytestmark``). The system is closed after the test, also
when it fails, and a failed test's report gets a section with what the server
printed or logged. This module imports the kit only when a test asks for it.
"""

from __future__ import annotations

from collections.abc import Generator, Iterator
from typing import TYPE_CHECKING, Any

import pytest

if TYPE_CHECKING:
    from cast.testing.system import LocalSystem

__all__ = ["cast_system", "pytest_configure", "pytest_runtest_makereport"]

_SYSTEMS = pytest.StashKey[list["LocalSystem"]]()


def pytest_configure(config: pytest.Config) -> None:
    """Declare the marker."""
    config.addinivalue_line(
        "markers",
        "cast_system(config=None, *, subarchitectures=None, process=False, sets=None): how the cast_system "
        "fixture starts its system (the arguments of cast.testing.start_system)",
    )


@pytest.fixture
def cast_system(request: pytest.FixtureRequest) -> Iterator[LocalSystem]:
    """A real CAST system for this test (:func:`cast.testing.start_system`), closed after it."""
    from cast.testing.system import start_system

    marker = request.node.get_closest_marker("cast_system")
    args: tuple[Any, ...] = marker.args if marker else ()
    kwargs: dict[str, Any] = dict(marker.kwargs) if marker else {}
    system = start_system(*args, **kwargs)
    request.node.stash.setdefault(_SYSTEMS, []).append(system)
    try:
        yield system
    finally:
        system.close()


@pytest.hookimpl(wrapper=True)
def pytest_runtest_makereport(item: pytest.Item, call: pytest.CallInfo[None]) -> Generator[None, Any, Any]:
    """A failed test's report shows what its systems printed or logged."""
    report = yield
    if report.failed:
        for system in item.stash.get(_SYSTEMS, []):
            report.sections.append((f"cast system '{system.name}' at {system.endpoint}", system.output() or
                                    "(nothing printed or logged)"))
    return report
