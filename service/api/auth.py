"""Role dependencies for routes: ``RobotAccess``, ``OperatorAccess``, ``AdminAccess`` and
``UnscopedAdminAccess``.

Add one as a parameter of a route (``_: OperatorAccess``): it answers 403 when the key's role is
too low, the route's ``{atlas}`` path parameter is not one of its atlases, or (unscoped) the key
is limited to some atlases. The key itself (``Authorization: Bearer <key>`` or ``X-API-Key``)
was already checked by :class:`~service.api.guard.RequestGuard` before the body was read (401);
dependencies run before FastAPI validates the body, so a 422 means the caller got past auth.
The parameter's value is the caller (:class:`~service.fleet.keys.Principal`).
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Annotated, overload

from fastapi import Depends, Request
from fastapi.security import APIKeyHeader, HTTPAuthorizationCredentials, HTTPBearer

from service.errors import Forbidden, NotReady
from service.fleet.keys import Authenticator, Principal, Role

bearer = HTTPBearer(auto_error=False, description="An API key from `loopnet keys create`.")
api_key_header = APIKeyHeader(name="X-API-Key", auto_error=False)


def get_authenticator(request: Request) -> Authenticator:
    authenticator: Authenticator | None = getattr(request.app.state, "authenticator", None)
    if authenticator is None:
        raise NotReady("the service is starting")
    return authenticator


PRINCIPAL_KEY = "loopnet.principal"  # where the guard leaves the caller in the ASGI scope


def presented_token(authorization: str | None, api_key: str | None) -> str | None:
    """The key of ``Authorization: Bearer <key>``, else of ``X-API-Key``."""
    if authorization:
        scheme, _, credentials = authorization.partition(" ")
        if scheme.lower() == "bearer" and credentials.strip():
            return credentials.strip()
    return api_key or None


def client_address(request: Request) -> str | None:
    return request.client.host if request.client else None


def key_holder(request: Request) -> Principal | None:
    """The caller of an open route (probes, public metrics) if it shows a valid key (or the API
    is open): who may read atlas names and errors there; None for anyone else."""
    authenticator: Authenticator | None = getattr(request.app.state, "authenticator", None)
    if authenticator is None:
        return None
    token = presented_token(request.headers.get("authorization"), request.headers.get("x-api-key"))
    return authenticator.identify(token, client_address(request))


def require(role: Role, *, unscoped: bool = False) -> Callable[..., Principal]:
    """A dependency admitting keys of ``role`` or above (on the route's atlas, if it has one;
    with ``unscoped``, only keys for every atlas)."""

    def dependency(
        request: Request,
        authenticator: Annotated[Authenticator, Depends(get_authenticator)],
        credentials: Annotated[HTTPAuthorizationCredentials | None, Depends(bearer)],
        api_key: Annotated[str | None, Depends(api_key_header)],
    ) -> Principal:
        principal: Principal | None = request.scope.get(PRINCIPAL_KEY)
        if principal is None:  # an app without the guard
            token = credentials.credentials if credentials is not None else api_key
            principal = authenticator.authenticate(token, client_address(request))
        caller = authenticator.authorize(
            principal, role, request.path_params.get("atlas"), unscoped=unscoped
        )
        request.state.caller = caller  # the request log names the robot
        return caller

    dependency.__name__ = f"require_{'unscoped_' if unscoped else ''}{role.name}"
    return dependency


RobotAccess = Annotated[Principal, Depends(require(Role.robot))]
OperatorAccess = Annotated[Principal, Depends(require(Role.operator))]
AdminAccess = Annotated[Principal, Depends(require(Role.admin))]
UnscopedAdminAccess = Annotated[Principal, Depends(require(Role.admin, unscoped=True))]


@overload
def acting_robot(caller: Principal, robot_id: str) -> str: ...
@overload
def acting_robot(caller: Principal, robot_id: str | None) -> str | None: ...
def acting_robot(caller: Principal, robot_id: str | None) -> str | None:
    """The robot a request acts as: a robot key is its robot (the key's name).

    A robot key may only send its own name as ``robot_id`` (403 otherwise), and a request
    that names none acts as that robot; operators, admins and the open service send any.
    """
    if caller.role is not Role.robot or caller.key_id is None:
        return robot_id
    if robot_id and robot_id != caller.name:
        raise Forbidden(f"this key acts as robot '{caller.name}', not '{robot_id}'")
    return caller.name
