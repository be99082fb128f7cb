"""Which host names the page's server answers to (:class:`LocalHostsOnly`): by default the
loopback's only, so that a page elsewhere that rebinds its DNS name to the loopback (DNS
rebinding) does not reach the API."""

from __future__ import annotations

from typing import Any

from starlette.datastructures import Headers

from snds.app.messages import json_response, shown_text

__all__ = ["LOCAL_HOSTS", "LocalHostsOnly"]

#: Host names a server bound to the loopback answers to (others are refused, which stops a
#: web page elsewhere from reaching it through DNS rebinding).
LOCAL_HOSTS = ("127.0.0.1", "localhost", "::1", "[::1]")


def _host_name(header: str) -> str:
    """The host name of a ``Host`` header, without its port (``[::1]:8765`` -> ``[::1]``)."""
    if header.startswith("["):
        return header[: header.find("]") + 1]
    return header.split(":")[0]


class LocalHostsOnly:
    """ASGI middleware that answers a request for another host name with the JSON 400 of
    every refusal (``{"error": ...}``): a page elsewhere that rebinds its DNS name to the
    loopback (DNS rebinding) does not reach the API.

    Arguments:
        app: The application.
        allowed: Host names answered (``"*"``: any).
    """

    def __init__(self, app: Any, allowed: tuple[str, ...] | list[str]) -> None:
        self.app = app
        self.allowed = set(allowed)

    async def __call__(self, scope: dict, receive: Any, send: Any) -> None:
        if scope["type"] in ("http", "websocket") and "*" not in self.allowed:
            host = _host_name(Headers(scope=scope).get("host", ""))
            if host not in self.allowed:
                reason = (
                    f"host {shown_text(host)!r} is not served here (only "
                    f"{', '.join(sorted(self.allowed))}); open the page at its address"
                )
                await json_response({"error": reason}, 400)(scope, receive, send)
                return
        await self.app(scope, receive, send)
