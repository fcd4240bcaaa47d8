"""Domain errors, raised by the core and the storage layer and mapped to HTTP in one place."""

from __future__ import annotations


class LoopNetError(Exception):
    """Base class of every error LoopNet reports to its callers."""


class InvalidInput(LoopNetError):
    """The caller sent something we cannot use (bad parameter, bad pose, ...)."""


class InvalidImage(InvalidInput):
    """The upload is not a decodable image (not an image, empty, truncated, unsupported)."""


class ImageTooLarge(InvalidInput):
    """The upload exceeds the configured byte or pixel limits."""


class NotFound(LoopNetError):
    """A named atlas, submap, frame or model version does not exist."""


class Conflict(LoopNetError):
    """The request contradicts the current state (duplicate name, incompatible features)."""


class WeightsUnavailable(LoopNetError):
    """A pretrained weights file is missing and could not be downloaded."""


class NotReady(LoopNetError):
    """The service is still starting (models or indexes not loaded yet)."""


class AtlasUnavailable(NotReady):
    """One atlas's model or index cannot be loaded (503 with the reason); the others serve."""


class Overloaded(LoopNetError):
    """Inference is saturated (every slot busy, the wait queue full): retry after a while."""

    def __init__(self, message: str, *, retry_after_s: int = 1) -> None:
        super().__init__(message)
        self.retry_after_s = retry_after_s


class Unauthorized(LoopNetError):
    """No API key, or an unknown or revoked one."""


class Forbidden(LoopNetError):
    """The key's role or atlases do not cover the request."""


class TooManyFailures(LoopNetError):
    """Too many failed authentications from one client address: retry after a while."""

    def __init__(self, message: str, *, retry_after_s: int = 1) -> None:
        super().__init__(message)
        self.retry_after_s = retry_after_s


class RequestTooLarge(LoopNetError):
    """The request body is over the route's byte limit."""


class UnknownHost(LoopNetError):
    """The request's Host header names a host this service does not answer to."""


class RequestTimeout(LoopNetError):
    """The request body stopped arriving (LOOPNET_BODY_TIMEOUT_SECONDS)."""
