"""Who may see the page: nobody without the one-time login link or a token the system accepts."""

from __future__ import annotations

import json
from urllib.parse import urlencode

from playwright.sync_api import Browser

from cast.auth import TokenSigner
from cast.core.records import Identity
from tests.web.conftest import WebRun, http

PROTECTED = ("/", "/api/state", "/api/entries?sa=vision", "/api/entry?sa=vision&id=x", "/api/events")


def signer(web_run: WebRun) -> TokenSigner:
    return TokenSigner((web_run.run.runtime_dir / "secret").read_bytes().strip())


def test_without_credentials_every_page_and_call_is_refused(web_run: WebRun) -> None:
    for path in PROTECTED:
        status, headers, body = http(web_run.base + path)
        assert status == 401, (path, status, body)
        if path.startswith("/api/"):
            assert "not signed in" in json.loads(body)["error"]
        else:
            assert "login link" in body and headers["content-security-policy"].startswith("default-src 'self'")
    # A cookie the view never handed out is no session.
    assert http(web_run.base + "/api/state", {"Cookie": "cast_web_session=made-up"})[0] == 401


def test_a_login_link_works_once_and_the_next_one_is_printed(web_run: WebRun) -> None:
    link = web_run.take_link()
    status, headers, _ = http(link)
    assert status == 303 and headers["location"] == "/"
    assert "HttpOnly" in headers["set-cookie"] and "SameSite=strict" in headers["set-cookie"]
    cookie = headers["set-cookie"].split(";")[0]
    status, _, body = http(web_run.base + "/api/state", {"Cookie": cookie})
    assert status == 200 and json.loads(body)["system"] == "webtest"
    assert http(link)[0] == 403  # spent
    fresh = web_run.take_link()  # printed when the first was spent
    assert fresh != link and http(fresh)[0] == 303 and http(fresh)[0] == 403
    assert http(f"{web_run.base}/login?key=guessed")[0] == 403


def test_a_token_the_system_accepts_opens_the_api_and_others_are_refused(web_run: WebRun) -> None:
    good = signer(web_run).issue(Identity("viewer", "", False), 600)
    status, _, body = http(web_run.base + "/api/entries?sa=motor", {"Authorization": f"Bearer {good}"})
    assert status == 200 and json.loads(body)["subarchitecture"] == "motor"
    foreign = TokenSigner(b"another-system-secret-0123456789abcdef").issue(Identity("viewer", "", False))
    expired = signer(web_run).issue(Identity("viewer", "", False), -10)
    for bad in (foreign, expired, "not-a-token"):
        status, _, body = http(web_run.base + "/api/state", {"Authorization": f"Bearer {bad}"})
        assert status == 403, (bad, status, body)
        assert "does not accept this token" in json.loads(body)["error"]
    # The sign-in form turns a token into a browser session.
    status, headers, _ = http(web_run.base + "/login", data=urlencode({"token": good}).encode())
    assert status == 303 and http(web_run.base + "/", {"Cookie": headers["set-cookie"].split(";")[0]})[0] == 200
    assert http(web_run.base + "/login", data=urlencode({"token": foreign}).encode())[0] == 403


def test_a_browser_without_a_session_gets_the_sign_in_page(browser: Browser, web_run: WebRun) -> None:
    context = browser.new_context()
    try:
        stranger = context.new_page()
        response = stranger.goto(web_run.base + "/#memories")
        assert response is not None and response.status == 401
        assert stranger.locator("form input[name=token]").count() == 1
        assert stranger.locator("#entries").count() == 0  # not the page
    finally:
        context.close()
