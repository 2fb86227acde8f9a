"""Task policy options are declared once, by each policy class, and checked from that declaration everywhere:
cast check (with lines and suggestions), make_policy, and the configuration's JSON Schema."""

from __future__ import annotations

import inspect
import math
import textwrap
from pathlib import Path
from typing import Any

import pytest
from hypothesis import given
from hypothesis import strategies as st

from cast.config import load_config
from cast.config.schema_check import validator_for
from cast.core.policies import BUILTIN_POLICIES, PolicyOption, make_policy
from cast.errors import InvalidArgumentError
from tests.orchestrator.conftest import COMPONENTS
from tests.orchestrator.test_config import one, problems

OPTIONS = [
    PolicyOption("slots", int, 1, "whole, at least 0", minimum=0),
    PolicyOption("count", int, 3, "any whole number"),
    PolicyOption("ratio", float, 0.5, "a number, at least 0", minimum=0),
    PolicyOption("strict", bool, False, "true or false"),
    PolicyOption("label", str, "x", "text"),
]
YAML_VALUES = st.one_of(
    st.none(), st.booleans(), st.integers(-5, 5), st.floats(allow_nan=False), st.text(max_size=3),
    st.lists(st.integers(), max_size=2), st.dictionaries(st.text(max_size=2), st.integers(), max_size=2),
)


@pytest.mark.parametrize("option", OPTIONS, ids=lambda o: o.name)
@given(value=YAML_VALUES)
def test_an_options_check_and_its_schema_accept_the_same_values(option: PolicyOption, value: Any) -> None:
    in_code = option.problem(value) is None
    in_schema = validator_for(option.json_schema()).is_valid(value)
    assert in_code == in_schema, (option, value, option.problem(value))


def test_what_an_option_says_of_a_wrong_value() -> None:
    slots, count, ratio, strict, label = OPTIONS
    assert slots.problem(-1) == "must be a whole number >= 0, not -1"
    assert slots.problem(2.0) == "must be a whole number >= 0, not 2.0"  # YAML's 2.0 is no whole number
    assert count.problem(True) == "must be a whole number, not True"
    assert ratio.problem("x") == "must be a number >= 0, not 'x'"
    assert strict.problem(1) == "must be true or false, not 1"
    assert label.problem(None) == "must be text, not None"
    assert slots.problem(0) is None and ratio.problem(math.inf) is None
    assert slots.json_schema() == {"description": "whole, at least 0", "type": "integer", "minimum": 0, "default": 1}
    with pytest.raises(TypeError):
        PolicyOption("when", list, [], "no lists")


@pytest.mark.parametrize("name", list(BUILTIN_POLICIES))
def test_each_builtin_policy_declares_what_its_constructor_takes(name: str) -> None:
    cls = BUILTIN_POLICIES[name]
    assert cls.options is not None, f"{name} must declare its options"
    parameters = {p.name: p.default for p in inspect.signature(cls.__init__).parameters.values()
                  if p.name != "self" and p.kind is inspect.Parameter.POSITIONAL_OR_KEYWORD}
    assert {o.name: o.default for o in cls.options} == parameters
    for option in cls.options:
        assert option.problem(option.default) is None and option.description


def test_make_policy_checks_the_declaration() -> None:
    with pytest.raises(InvalidArgumentError, match=r"max_concurent is not one of its options \(did you mean "
                                                   r"'max_concurrent'\?\)"):
        make_policy("fifo", {"max_concurent": 2})
    with pytest.raises(InvalidArgumentError, match="task manager policy 'priority': max_waiting must be a whole "
                                                   "number >= 0, not 'many'"):
        make_policy("priority", {"max_waiting": "many"})
    with pytest.raises(InvalidArgumentError, match="takes no options, got: max_concurrent"):
        make_policy("exclusive", {"max_concurrent": 1})
    assert make_policy("priority", {"max_concurrent": 3}).describe() == "priority(max_concurrent=3)"


# ------------------------------------------------------------------ users' policy classes

USER_POLICIES = '''\
from cast import Decision, TaskPolicy
from cast.core.policies import PolicyOption


class Threshold(TaskPolicy):
    """Adopts tasks whose priority reaches the threshold."""

    name = "threshold"
    options = (PolicyOption("threshold", float, 0.5, "lowest priority adopted", minimum=0),
               PolicyOption("verbose", bool, False, "say why"))

    def __init__(self, threshold: float = 0.5, verbose: bool = False) -> None:
        self.threshold, self.verbose = threshold, verbose

    def decide(self, waiting, adopted, wm):
        return Decision(adopt=[t for t in waiting if t.priority >= self.threshold])

    def describe(self) -> str:
        return f"threshold({self.threshold})"
'''


def test_a_users_policy_declaring_options_is_checked_on_its_lines(tmp_path: Path) -> None:
    (tmp_path / "user_policies.py").write_text(USER_POLICIES)
    found = problems(tmp_path, f"""\
        python_path: [{tmp_path}]
        subarchitectures:
          a:
            task_manager: {{policy: "user_policies:Threshold", threshhold: 2}}
          b:
            task_manager:
              policy: "user_policies:Threshold"
              threshold: -1
              verbose: yes please
        """)
    one(found, 4, "a.task_manager.threshhold", "unknown key 'threshhold' (did you mean 'threshold'?)")
    one(found, 8, "b.task_manager.threshold",
        "task manager policy 'user_policies:Threshold': threshold must be a number >= 0, not -1")
    one(found, 9, "b.task_manager.verbose", "verbose must be true or false, not 'yes please'")
    assert len(found) == 3, "\n".join(map(str, found))
    path = tmp_path / "good.yaml"
    path.write_text(textwrap.dedent(f"""\
        python_path: [{tmp_path}]
        subarchitectures:
          a: {{task_manager: {{policy: "user_policies:Threshold", threshold: 2}}}}
        """))
    sa = load_config(path, environ={}).subarchitectures["a"]
    assert sa.policy_options == {"threshold": 2}
    assert sa.make_policy().describe() == "threshold(2)"


def test_a_users_policy_declaring_nothing_gets_its_options_as_before(tmp_path: Path) -> None:
    path = tmp_path / "system.yaml"
    path.write_text(textwrap.dedent(f"""\
        python_path: [{COMPONENTS}]
        subarchitectures:
          a: {{task_manager: {{policy: "orch_policies:PrefixPolicy", prefix: go}}}}
        """))
    sa = load_config(path, environ={}).subarchitectures["a"]
    assert sa.policy_options == {"prefix": "go"} and sa.make_policy().describe() == "prefix(go)"
    found = problems(tmp_path, f"""\
        python_path: [{COMPONENTS}]
        subarchitectures:
          a: {{task_manager: {{policy: "orch_policies:PrefixPolicy", prefx: go}}}}
        """)
    one(found, 3, "a.task_manager.policy", "bad options {'prefx': 'go'}")  # its constructor refuses it
