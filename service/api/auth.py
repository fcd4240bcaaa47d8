"""Role dependencies for routes: ``RobotAccess``, ``OperatorAccess``, ``AdminAccess``.

Add one as a parameter of a route (``_: OperatorAccess``): it reads the key from
``Authorization: Bearer <key>`` or ``X-API-Key``, answers 401 without a valid key and 403 when
the key's role is too low or the route's ``{atlas}`` path parameter is not one of its atlases.
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


def require(role: Role) -> Callable[..., Principal]:
    """A dependency admitting keys of ``role`` or above (on the route's atlas, if it has one)."""

    def dependency(
        request: Request,
        authenticator: Annotated[Authenticator, Depends(get_authenticator)],
        credentials: Annotated[HTTPAuthorizationCredentials | None, Depends(bearer)],
        api_key: Annotated[str | None, Depends(api_key_header)],
    ) -> Principal:
        token = credentials.credentials if credentials is not None else api_key
        return authenticator.authorize(token, role, request.path_params.get("atlas"))

    dependency.__name__ = f"require_{role.name}"
    return dependency


RobotAccess = Annotated[Principal, Depends(require(Role.robot))]
OperatorAccess = Annotated[Principal, Depends(require(Role.operator))]
AdminAccess = Annotated[Principal, Depends(require(Role.admin))]


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
