"""Where the web view listens: the address forms ``--listen`` / ``--web`` take, and the line saying who can reach it.

Light on purpose (no web framework imported): ``cast run`` reads the default
address when it builds its options.
"""

from __future__ import annotations

from cast.listen import ListenAddress, parse_listen

__all__ = ["DEFAULT_LISTEN", "listening_line", "parse_web_listen"]

DEFAULT_LISTEN = "127.0.0.1:8766"
"""Loopback, one port above Foxglove's 8765 (``cast foxglove``), so both views can run side by side."""


def parse_web_listen(text: str, option: str = "--listen") -> ListenAddress:
    """Where the web view listens (:func:`cast.listen.parse_listen`, with its default as the example)."""
    return parse_listen(text, option, DEFAULT_LISTEN)


def listening_line(address: ListenAddress, url: str) -> str:
    """Where the view listens and who can reach it: the first line ``cast web`` and ``cast run --web`` print."""
    if address.loopback:
        return f"listening on {url} (loopback only: open it in a browser on this machine, with the login link below)"
    return (f"listening on {url} (NOT loopback-only: anyone who reaches this address may try it; the page still needs "
            "the login link or a token, but its traffic is plain HTTP: prefer an SSH tunnel to a loopback view)")
