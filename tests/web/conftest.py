"""The web view's tests: one `cast run --web=127.0.0.1:0` system and one headless Chromium for the whole package.

The system: `vision` (goals are posted there by the tests' script) and `motor`, whose managed planner proposes a task
per goal, reads the goal across SAs and writes its plan into its own WM. The browser is Debian's chromium
(`make web-deps`), driven by Playwright without any browser download; a missing browser fails the tests, it never
skips them. Screenshots of the three views go to build/web-screenshots/.
"""

from __future__ import annotations

import re
import signal
import urllib.error
import urllib.request
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import pytest
from playwright.sync_api import Browser, Page, expect, sync_playwright

from tests.conftest import ROOT, wait_for
from tests.orchestrator.conftest import CastRun, start_cast_run

CHROMIUM = Path("/usr/bin/chromium")
SCREENSHOTS = ROOT / "build" / "web-screenshots"
COMPONENTS = Path(__file__).resolve().parent / "components"
LINK = re.compile(r"open (http://127\.0\.0\.1:\d+/login\?key=[\w-]+)")
NEXT_LINK = re.compile(r"the next one, for another browser: (http://\S+/login\?key=[\w-]+)")
TIMEOUT_MS = 30_000  # a guard against a hang, not a measurement
expect.set_options(timeout=TIMEOUT_MS)  # every expect(...) of these tests waits up to this for the page to show it

CONFIG = f"""
system: webtest
python_path: [{COMPONENTS}]
subarchitectures:
  vision: {{}}
  motor:
    task_manager: {{policy: fifo, max_concurrent: 1}}
    components:
      planner: {{language: python, kind: managed, class: web_components:Planner}}
"""


@dataclass
class WebRun:
    """The running system and its web view: where it listens and the login links it printed."""

    run: CastRun
    base: str
    first_link: str
    taken: set[str] = field(default_factory=set)

    def links(self) -> list[str]:
        """Every login link printed so far, the first one first."""
        return [self.first_link, *NEXT_LINK.findall(self.run.output())]

    def take_link(self) -> str:
        """The newest login link no test took yet (each works once; a new one is printed when one is used)."""
        link = wait_for(lambda: next((x for x in reversed(self.links()) if x not in self.taken), None), 30,
                        "a login link not used yet")
        self.taken.add(link)
        return str(link)


@pytest.fixture(scope="package")
def web_run(tmp_path_factory: pytest.TempPathFactory) -> Iterator[WebRun]:
    """`cast run CONFIG --web=127.0.0.1:0`, until the package's last test."""
    tmp = tmp_path_factory.mktemp("web")
    config = tmp / "system.yaml"
    config.write_text(CONFIG)
    run = start_cast_run(tmp, config, "--web=127.0.0.1:0")
    try:
        found = wait_for(lambda: LINK.search(run.output()), 30, "the login link")
        link = found.group(1)
        yield WebRun(run, link.split("/login")[0], link)
    finally:
        run.stop(signal.SIGTERM)


@pytest.fixture(scope="package")
def browser() -> Iterator[Browser]:
    """Debian's headless chromium under Playwright (no browser download)."""
    if not CHROMIUM.exists():
        pytest.fail(f"{CHROMIUM} is missing: `make web-deps` installs Debian's chromium, which these tests drive")
    with sync_playwright() as playwright:
        chromium = playwright.chromium.launch(executable_path=str(CHROMIUM))
        yield chromium
        chromium.close()


@pytest.fixture(scope="package")
def page(browser: Browser, web_run: WebRun) -> Iterator[Page]:
    """A page signed in with the first login link `cast run --web` printed."""
    context = browser.new_context(viewport={"width": 1400, "height": 900})
    context.set_default_timeout(TIMEOUT_MS)
    signed_in = context.new_page()
    errors: list[str] = []
    signed_in.on("pageerror", lambda exc: errors.append(str(exc)))
    response = signed_in.goto(web_run.take_link())
    assert response is not None and response.ok and signed_in.url == f"{web_run.base}/"
    yield signed_in
    context.close()
    assert not errors, f"the page's script failed: {errors}"


def screenshot(page: Page, name: str) -> None:
    """Save the whole page as build/web-screenshots/NAME.png."""
    SCREENSHOTS.mkdir(parents=True, exist_ok=True)
    page.screenshot(path=str(SCREENSHOTS / f"{name}.png"), full_page=True)


def http(url: str, headers: dict[str, str] | None = None, data: bytes | None = None) -> tuple[int, dict[str, str], str]:
    """A plain HTTP request (no cookies kept, redirects not followed): status, headers (names in lower case), body."""

    class NoRedirect(urllib.request.HTTPRedirectHandler):
        def redirect_request(self, *args: Any, **kwargs: Any) -> None:
            return None

    opener = urllib.request.build_opener(NoRedirect)
    request = urllib.request.Request(url, data=data, headers=headers or {})
    try:
        with opener.open(request, timeout=30) as response:
            return response.status, {k.lower(): v for k, v in response.headers.items()}, response.read().decode()
    except urllib.error.HTTPError as exc:
        return exc.code, {k.lower(): v for k, v in exc.headers.items()}, exc.read().decode()
