"""Who may reach the API through a browser: the ``Host`` it was asked for, and the origin of
state-changing requests that carry no key.

Two attacks go through a visitor's browser rather than the network: a page of another site
POSTs a form to the service (a "simple" cross-origin request needs no CORS permission; on an
open service, before the first key exists, it created frames and restored snapshots), and a
DNS-rebinding page makes its own name resolve to the service's address, so that the browser
treats the service as the page's own origin and lets it read every answer. This pure ASGI
middleware refuses both before any route runs:

1. the ``Host`` header must name the service: the loopback names, ``LOOPNET_HOST`` and the
   names in ``LOOPNET_ALLOWED_HOSTS`` (a rebinding page's requests carry its own name): 400
   otherwise. The probes and the metrics (``GET /v1/health``, ``/v1/ready``, ``/metrics``)
   answer any host: orchestrators and Prometheus reach them by address, and they give callers
   without a key only counts;
2. a request that may change state (any method but GET, HEAD and OPTIONS) and shows no key
   (neither ``Authorization`` nor ``X-API-Key``: a browser sends neither cross-origin without a
   CORS permission this service never gives) must not come from another origin: refused (403)
   when ``Sec-Fetch-Site`` says ``cross-site`` or ``same-site``, or its ``Origin`` is not the
   host it was sent to. Clients that are not browsers send neither header and pass.
"""

from __future__ import annotations

from urllib.parse import urlsplit

from starlette.types import ASGIApp, Receive, Scope, Send

from service.api.errors import error_response
from service.config import Settings
from service.errors import Forbidden, UnknownHost

SAFE_METHODS = frozenset({"GET", "HEAD", "OPTIONS"})
ANY_HOST_PATHS = frozenset({"/v1/health", "/v1/ready", "/metrics"})
FOREIGN_FETCH_SITES = frozenset({"cross-site", "same-site"})


def host_name(authority: str) -> str:
    """The host of a ``Host`` value or URL authority, without port, lower case
    (``[::1]:8000`` -> ``::1``)."""
    authority = authority.strip().lower()
    if authority.startswith("["):
        return authority[1 : authority.find("]")] if "]" in authority else authority
    return authority.rsplit(":", 1)[0] if authority.count(":") == 1 else authority


def host_allowed(host: str, allowed: tuple[str, ...]) -> bool:
    """Whether ``host`` (already without port) is one of ``allowed``: exact names, ``*`` for
    any, ``*.example.org`` for the subdomains of example.org."""
    for name in allowed:
        if name == "*" or name == host:
            return True
        if name.startswith("*.") and host.endswith(name[1:]):
            return True
    return False


class HostOriginGuard:
    """ASGI middleware: 400 for a Host the service does not answer to, 403 for a keyless
    state change from another origin."""

    def __init__(self, app: ASGIApp, settings: Settings) -> None:
        self.app = app
        self.allowed = settings.host_names

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] == "http":
            refusal = self.refusal(scope)
            if refusal is not None:
                await error_response(refusal)(scope, receive, send)
                return
        await self.app(scope, receive, send)

    def refusal(self, scope: Scope) -> UnknownHost | Forbidden | None:
        headers = {k.decode("latin-1").lower(): v.decode("latin-1") for k, v in scope["headers"]}
        method: str = scope["method"]
        host = headers.get("host", "")
        open_probe = method in ("GET", "HEAD") and scope["path"] in ANY_HOST_PATHS
        if not open_probe and not host_allowed(host_name(host), self.allowed):
            return UnknownHost(
                f"this service does not answer to the host {host[:100]!r}; add the name clients "
                "use to LOOPNET_ALLOWED_HOSTS"
            )
        if method in SAFE_METHODS or "authorization" in headers or "x-api-key" in headers:
            return None
        origin = headers.get("origin")
        foreign = headers.get("sec-fetch-site") in FOREIGN_FETCH_SITES or (
            origin is not None and _origin_host(origin) != host.strip().lower()
        )
        if foreign:
            return Forbidden(
                "a request from another web origin may not change anything without an API key"
            )
        return None


def _origin_host(origin: str) -> str | None:
    """``host[:port]`` of an ``Origin`` header; None for ``null`` or anything unparsable."""
    try:
        parts = urlsplit(origin.strip().lower())
    except ValueError:
        return None
    return parts.netloc or None
