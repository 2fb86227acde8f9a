"""A testing kit for components: a real CAST system for each test, in pytest or unittest.

::

    from cast.testing import start_system

    def test_counter_counts() -> None:
        with start_system(subarchitectures=["vision"]) as system:
            running = system.run(Counter, "counter", "vision", args={"to": 3})
            system.wait_for_entry("vision", "count", Int64Value, Int64Value(value=3))
            assert running.stop() == 0

With pytest the ``cast_system`` fixture gives the same system, closed after
the test also when it fails, whose output is added to a failed test's report
(the plugin ``cast.testing.pytest_plugin``, registered with pytest by the
package). The C++ (``cast/testing.h``) and Java (``cast-testing``) kits have
the same names in their own casing; docs/python.md, "Testing your components".
"""

from cast.testing.actors import Actor, RunningComponent
from cast.testing.changes import ChangeCollector
from cast.testing.describe import describe_change, describe_entry, describe_value
from cast.testing.launched import RunningSystem, run_system
from cast.testing.system import DEFAULT_SUBARCHITECTURES, LocalSystem, start_system
from cast.testing.waiting import DEFAULT_TIMEOUT_S, wait_for

__all__ = [
    "DEFAULT_SUBARCHITECTURES",
    "DEFAULT_TIMEOUT_S",
    "Actor",
    "ChangeCollector",
    "LocalSystem",
    "RunningComponent",
    "RunningSystem",
    "describe_change",
    "describe_entry",
    "describe_value",
    "run_system",
    "start_system",
    "wait_for",
]
