"""The one rule for names of atlases, submaps, robots and API keys."""

from __future__ import annotations

import re

from service.errors import InvalidInput

NAME_PATTERN = re.compile(r"^[A-Za-z0-9][A-Za-z0-9._-]{0,63}$")


def validate_name(kind: str, name: str) -> str:
    if not NAME_PATTERN.match(name):
        raise InvalidInput(
            f"{kind} name {name!r} is invalid: use 1-64 letters, digits, '.', '_' or '-', "
            "starting with a letter or digit"
        )
    return name
