"""The trailing-slash redirect, without the client's ``Host`` header in it.

Starlette answers ``/v1/atlases/`` with a 307 to ``http://<Host header>/v1/atlases``: whatever
host the client named comes back in ``Location`` (a cache or a proxy in between may then send
others there). This router fallback gives the same 307 with a relative ``Location`` (the path
and query only, RFC 9110 allows it), so nothing the client sent is echoed as a host.
"""

from __future__ import annotations

from starlette.responses import RedirectResponse
from starlette.routing import Match, Router
from starlette.types import Receive, Scope, Send


class SlashRedirect:
    """``Router.default``: a 307 to the path with its trailing slash toggled when that path
    matches a route, else the router's own 404."""

    def __init__(self, router: Router) -> None:
        self.router = router

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        path: str = scope["path"]
        if scope["type"] == "http" and path != "/":
            toggled = path.rstrip("/") if path.endswith("/") else path + "/"
            relative = toggled.startswith("/") and not toggled.startswith("//")  # not "//host"
            if relative and self._matches({**scope, "path": toggled}):
                await RedirectResponse(_location(scope, toggled), 307)(scope, receive, send)
                return
        await self.router.not_found(scope, receive, send)

    def _matches(self, scope: Scope) -> bool:
        return any(route.matches(scope)[0] is not Match.NONE for route in self.router.routes)


def _location(scope: Scope, path: str) -> str:
    """The path (already with any root path) and query; '?' and '#' inside the decoded path are
    escaped as Starlette does (RedirectResponse percent-encodes the rest)."""
    escaped = path.replace("?", "%3F").replace("#", "%23").replace("\\", "%5C")
    query = scope.get("query_string", b"").decode("latin-1")
    return escaped + (f"?{query}" if query else "")


def install(router: Router) -> None:
    """Replace the router's own trailing-slash redirect by :class:`SlashRedirect`."""
    router.redirect_slashes = False
    router.default = SlashRedirect(router)
