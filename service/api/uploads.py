"""Reading multipart fields: the image within the byte limit, JSON-valued form fields."""

from __future__ import annotations

import json
import sys
from typing import TypeVar

from fastapi import UploadFile
from pydantic import BaseModel, ValidationError

from service.errors import ImageTooLarge, InvalidInput

Model = TypeVar("Model", bound=BaseModel)


def read_image_upload(upload: UploadFile, max_bytes: int) -> bytes:
    """The uploaded bytes, refusing more than ``max_bytes`` without reading the rest."""
    data = upload.file.read(max_bytes + 1)
    if len(data) > max_bytes:
        raise ImageTooLarge(f"the upload exceeds the limit of {max_bytes} bytes")
    return data


def parse_json_field(name: str, raw: str | None, model: type[Model]) -> Model | None:
    """Parse a form field holding JSON into ``model``; a clear 422 when it does not fit."""
    if raw is None or raw.strip() == "":
        return None
    try:
        return model.model_validate(json.loads(raw))
    except json.JSONDecodeError as exc:
        raise InvalidInput(f"field '{name}' is not valid JSON: {exc.msg}") from exc
    except RecursionError as exc:  # the decoder recurses once per nesting level
        raise InvalidInput(f"field '{name}' is nested too deeply") from exc
    except ValidationError as exc:
        problems = "; ".join(
            f"{'.'.join(str(p) for p in e['loc']) or name}: {e['msg']}" for e in exc.errors()
        )
        raise InvalidInput(f"field '{name}' is invalid: {problems}") from exc
    except ValueError as exc:  # an integer beyond Python's integer-conversion limit
        raise InvalidInput(
            f"field '{name}' holds a number of more than {sys.get_int_max_str_digits()} digits"
        ) from exc
