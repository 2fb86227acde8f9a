"""Where the Foxglove live view listens: the forms of ``--listen`` / ``--foxglove``, and who can connect.

Light on purpose (foxglove-sdk is not imported): ``cast run`` reads the default
address when it builds its options, and most runs show no live view.
"""

from __future__ import annotations

from cast.listen import ListenAddress, parse_listen

__all__ = ["DEFAULT_LISTEN", "listening_line", "parse_foxglove_listen"]

DEFAULT_LISTEN = "127.0.0.1:8765"
"""Foxglove's own default port, on loopback: the app's "Foxglove WebSocket" connection offers this address."""

def parse_foxglove_listen(text: str, option: str = "--listen") -> ListenAddress:
    """Where the live view listens (:func:`cast.listen.parse_listen`, with Foxglove's default as the example)."""
    return parse_listen(text, option, DEFAULT_LISTEN)


def listening_line(address: ListenAddress, url: str) -> str:
    """Where the view listens, and who can connect: the first line ``cast foxglove`` and ``cast run`` print."""
    if address.loopback:
        return (f"listening on {url} (loopback only: on this machine, Foxglove's Open connection -> Foxglove "
                f"WebSocket -> {url})")
    return (f"listening on {url} (NOT loopback-only: anyone who reaches this address sees every working memory "
            "shown, with no authentication)")
