"""The page in a real browser (headless chromium): what it shows is the running system, live.

Each check compares the page with what the `cast` tools say about the same system at the same moment, and waits
(bounded) for live changes to arrive. Screenshots of the three views go to build/web-screenshots/.
"""

from __future__ import annotations

from google.protobuf.wrappers_pb2 import BytesValue, Int32Value, StringValue
from playwright.sync_api import Page, expect

import cast
from tests.conftest import wait_for
from tests.web.conftest import WebRun, screenshot


def post_goal(web_run: WebRun, goal_id: str, text: str) -> None:
    """A script writes a goal into `vision`; the planner in `motor` then plans it (a task, a read, a write)."""
    with cast.connect(runtime_dir=web_run.run.runtime_dir, subarchitecture="vision") as script:
        script.add(goal_id, StringValue(value=text))


def overwrite_goal(web_run: WebRun, goal_id: str, text: str) -> None:
    with cast.connect(runtime_dir=web_run.run.runtime_dir, subarchitecture="vision") as script:
        script.overwrite(goal_id, StringValue(value=text))


def attribute_list(page: Page, selector: str, name: str) -> list[str]:
    return list(page.locator(selector).evaluate_all(f"nodes => nodes.map(n => n.getAttribute('{name}'))"))


def test_the_architecture_shows_the_systems_subarchitectures_and_components(page: Page, web_run: WebRun) -> None:
    page.goto(f"{web_run.base}/#architecture")
    expect(page.locator(".sa")).to_have_count(2)
    assert attribute_list(page, ".sa", "data-sa") == ["vision", "motor"]  # the configuration's order

    def same() -> bool:
        rows = web_run.run.cli_json("components")
        for sa in ("vision", "motor"):
            expected = [r["id"] for r in rows if r["subarchitecture"] == sa]
            if attribute_list(page, f'.sa[data-sa="{sa}"] [data-component]', "data-component") != expected:
                return False
        return True

    wait_for(same, 30, "the components shown to be those `cast components` lists")
    planner = page.locator('[data-component="planner"]')
    expect(planner.locator(".lang")).to_have_text("Python")
    expect(planner.locator(".sub")).to_contain_text("running · managed")
    expect(page.locator('.sa[data-sa="motor"]')).to_contain_text("task manager: fifo")


def test_a_write_by_a_component_appears_and_the_entries_are_the_working_memorys(page: Page, web_run: WebRun) -> None:
    page.goto(f"{web_run.base}/#memories")
    page.click('#wm-sas button[data-wm="motor"]')
    post_goal(web_run, "goal-a", "fetch the cup")
    # The planner's own write in its SA, with its author, in the entries and in the last changes.
    row = page.locator('#entries tr[data-entry-id="plan-goal-a"]')
    expect(row).to_be_visible()
    expect(row.locator("td").nth(3)).to_have_text("planner")
    expect(page.locator('#changes tr[data-change^="motor/plan-goal-a@"]')).to_have_count(1)

    def same() -> set[str] | None:
        listed = {e["id"] for e in web_run.run.cli_json("ls", "motor")}
        shown = set(attribute_list(page, "#entries tbody tr", "data-entry-id"))
        return listed if listed == shown else None

    listed = wait_for(same, 30, "the entries shown to be those `cast ls motor` lists")
    expect(page.locator("#wm-count")).to_contain_text(f"{len(listed)} entries")
    row.click()
    expect(page.locator("#value")).to_contain_text('"planned: fetch the cup"')  # rendered through its schema
    expect(page.locator("#value-head")).to_contain_text("google.protobuf.StringValue")
    screenshot(page, "memories")


def test_a_clicked_value_follows_its_entry_live_and_the_type_filter_narrows(page: Page, web_run: WebRun) -> None:
    post_goal(web_run, "goal-live", "first wording")
    with cast.connect(runtime_dir=web_run.run.runtime_dir, subarchitecture="vision") as script:
        script.add("goal-count", Int32Value(value=3))  # a second type in vision, for the filter
        script.add("camera", BytesValue(value=bytes(1_100_000)))  # too big to render
    page.goto(f"{web_run.base}/#memories")
    page.click('#wm-sas button[data-wm="vision"]')
    page.locator('#entries tr[data-entry-id="goal-live"]').click()
    expect(page.locator("#value")).to_contain_text('"first wording"')
    overwrite_goal(web_run, "goal-live", "second wording")
    expect(page.locator("#value")).to_contain_text('"second wording"')
    expect(page.locator('#changes tr[data-change^="vision/goal-live@"]')).to_have_count(2)  # add, overwrite
    # Filtered by type: only the Int32Value is left, then only the goals.
    page.select_option("#wm-type", "google.protobuf.Int32Value")
    expect(page.locator("#wm-count")).to_contain_text("1 of type Int32Value")
    assert attribute_list(page, "#entries tbody tr", "data-entry-id") == ["goal-count"]
    page.select_option("#wm-type", "google.protobuf.StringValue")
    expect(page.locator('#entries tr[data-entry-id="goal-count"]')).to_have_count(0)
    expect(page.locator('#entries tr[data-entry-id="goal-live"]')).to_have_count(1)
    page.select_option("#wm-type", "google.protobuf.BytesValue")
    page.locator('#entries tr[data-entry-id="camera"]').click()
    expect(page.locator("#value")).to_contain_text("a value of 1,100,004 bytes: more than the 1,048,576 this page")
    expect(page.locator("#value")).to_contain_text("`cast get vision camera` prints it")


def test_a_task_decision_appears_in_the_task_view(page: Page, web_run: WebRun) -> None:
    page.goto(f"{web_run.base}/#tasks")
    post_goal(web_run, "goal-t", "open the door")
    decisions = page.locator("#decisions")
    expect(decisions.locator('tr[data-decision="motor/plan-goal-t/adopted"]')).to_have_count(1)
    completed = decisions.locator('tr[data-decision="motor/plan-goal-t/completed"]')
    expect(completed).to_contain_text("completed: succeeded")
    expect(completed).to_contain_text("planner")

    def same() -> bool:
        counted = next(c for c in web_run.run.cli_json("tasks")["subarchitectures"] if c["subarchitecture"] == "motor")
        card = page.locator('[data-tm="motor"]')
        shown = {name: int(card.locator(f'[data-count="{name}"] b').inner_text())
                 for name in ("proposed", "adopted", "completed")}
        return shown == {name: counted[name] for name in shown}

    wait_for(same, 30, "the motor task manager's counts to be those `cast tasks` gives")
    expect(page.locator('[data-tm="motor"]')).to_contain_text("fifo")
    screenshot(page, "tasks")


def test_arrows_follow_the_cross_sa_traffic_and_rates_are_drawn(page: Page, web_run: WebRun) -> None:
    page.goto(f"{web_run.base}/#architecture")
    post_goal(web_run, "goal-r", "look around")
    # The planner (motor) watches and reads vision: an arrow from motor to vision, with a live rate on it.
    arrow = page.locator('[data-arrow="motor->vision"]')
    expect(arrow).to_contain_text("motor → vision")
    expect(arrow).to_contain_text("r/s")
    expect(page.locator('[data-arrow="vision->motor"]')).to_have_count(0)  # nobody in vision uses motor
    for chart in ("events-vision", "events-motor", "latency"):
        expect(page.locator(f'[data-chart="{chart}"] path')).not_to_have_count(0)
    screenshot(page, "architecture")
