"""``loopnet serve``: uvicorn with the service's limits on connections, time-outs and proxies.

uvicorn alone trusts ``X-Forwarded-For`` from loopback (a local client then picks its own
address, past the failed-authentication limit and into the logs), holds connections without
limit, and has no time-out on a request's headers: 50 connections sending a byte now and then
stayed open for good. Here:

- ``X-Forwarded-For`` / ``-Proto`` are read only from ``LOOPNET_TRUSTED_PROXIES``;
- at most ``LOOPNET_MAX_CONNECTIONS`` connections and requests at once (503 beyond);
- a request's headers must be complete ``LOOPNET_HEADER_TIMEOUT_SECONDS`` after its first
  byte (after connecting, for the first request), else the connection is closed
  (:func:`with_header_deadline`); an idle keep-alive connection closes after
  ``LOOPNET_KEEP_ALIVE_SECONDS``; a body that stops arriving for
  ``LOOPNET_BODY_TIMEOUT_SECONDS`` is answered 408 (:mod:`service.api.guard`).

A reverse proxy in front (TLS, the public name) should set its own, tighter limits; see the
operations documentation.
"""

from __future__ import annotations

import asyncio
from typing import Any

import uvicorn
from uvicorn.protocols.http.auto import AutoHTTPProtocol

from service.config import Settings


def with_header_deadline(base: type[asyncio.Protocol], seconds: float) -> type[asyncio.Protocol]:
    """uvicorn's HTTP protocol ``base`` (h11 or httptools), closing a connection whose
    request headers are not complete ``seconds`` after the request's first byte (or, for the
    first request, after connecting). Both implementations set ``cycle`` once a request's
    headers are parsed, and mark it ``response_complete`` when its answer is sent."""

    class HeaderDeadline(base):  # type: ignore[valid-type,misc]
        _deadline: asyncio.TimerHandle | None = None
        _seen: Any = None

        def connection_made(self, transport: asyncio.BaseTransport) -> None:
            super().connection_made(transport)
            self._arm()

        def data_received(self, data: bytes) -> None:
            cycle = getattr(self, "cycle", None)
            if self._deadline is None and (cycle is None or cycle.response_complete):
                self._arm()  # the first bytes of the next request on this connection
            super().data_received(data)
            cycle = getattr(self, "cycle", None)
            if cycle is not None and cycle is not self._seen:  # its headers are in
                self._seen = cycle
                self._disarm()

        def connection_lost(self, exc: Exception | None) -> None:
            self._disarm()
            super().connection_lost(exc)

        def _arm(self) -> None:
            self._disarm()
            loop = asyncio.get_running_loop()
            self._deadline = loop.call_later(seconds, self._expired)

        def _disarm(self) -> None:
            if self._deadline is not None:
                self._deadline.cancel()
                self._deadline = None

        def _expired(self) -> None:
            self._deadline = None
            transport = getattr(self, "transport", None)
            if transport is not None and not transport.is_closing():
                transport.close()

    HeaderDeadline.__name__ = f"HeaderDeadline{base.__name__}"
    return HeaderDeadline


def uvicorn_config(app: Any, settings: Settings, host: str, port: int) -> uvicorn.Config:
    """The server's configuration: the settings' limits, time-outs and trusted proxies."""
    proxies = settings.proxies
    return uvicorn.Config(
        app,
        host=host,
        port=port,
        http=with_header_deadline(AutoHTTPProtocol, settings.header_timeout_seconds),
        proxy_headers=bool(proxies),
        forwarded_allow_ips=proxies or None,
        limit_concurrency=settings.max_connections,
        timeout_keep_alive=settings.keep_alive_seconds,
        server_header=False,
        log_level="info",
        access_log=False,  # service.api.request_log writes one line per request instead
    )


def serve(app: Any, settings: Settings, host: str, port: int) -> None:
    """Run ``app`` until stopped."""
    uvicorn.Server(uvicorn_config(app, settings, host, port)).run()
