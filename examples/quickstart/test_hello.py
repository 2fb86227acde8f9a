"""The quick start's component under test: pytest, with the fixture of cast.testing (docs/python.md)."""

from pathlib import Path

import pytest
from google.protobuf.wrappers_pb2 import StringValue
from hello import Hello

import cast
from cast.testing import LocalSystem, wait_for

# Each test gets a real system of the quick start's configuration, stopped after it.
pytestmark = pytest.mark.cast_system(Path(__file__).with_name("system.yaml"))


def test_hello_adds_three_greetings_and_stops_once_it_saw_them(cast_system: LocalSystem) -> None:
    greetings = cast_system.collect_changes(cast.global_type_filter(StringValue, include_entry=True))
    hello = cast_system.run(Hello, "hello", "greetings")
    assert hello.join() == 0  # it stops by itself after seeing its three greetings
    texts = [change.entry(StringValue).value.value for change in greetings.wait_for_count(3)]
    assert texts == ["hello 0", "hello 1", "hello 2"]


def test_hello_counts_greetings_of_others_too(cast_system: LocalSystem) -> None:
    hello = cast_system.bind(Hello, "hello", "greetings")  # stepped: the test calls its hooks
    hello.start()
    visitor = cast_system.act_as("visitor", "greetings")
    for i in range(3):
        visitor.add(f"visit-{i}", StringValue(value=f"hi {i}"))
    wait_for(lambda: not hello.running, what="hello to ask to stop after three greetings")
    cast_system.assert_entry("greetings", "visit-2", StringValue, StringValue(value="hi 2"))
