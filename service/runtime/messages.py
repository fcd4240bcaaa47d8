"""The job queue's wire format: JSON carrying one job id, never pickle.

Huey pickles its messages by default, so whoever can write to Redis or to ``queue.sqlite3``
runs code in the worker. :class:`JobIdSerializer` writes a message as a small JSON object and
reads back only that shape: the one LoopNet task, a single positive job id, no keyword
arguments, callbacks or chords. Anything else (a pickle, other JSON) raises
:class:`RejectedMessage` before a task exists; Huey's consumer logs it and drops the message.
The job id itself is then checked against the jobs table by the job runner.

Huey stores a few other values through the same serializer (revocations, locks, results): those
are JSON too (plain values; datetimes tagged), and nothing is ever unpickled.
"""

from __future__ import annotations

import datetime as dt
import json
import logging
from typing import Any

from huey.registry import Message
from huey.serializer import Serializer

from service.domain.limits import MAX_ROW_ID as MAX_JOB_ID

log = logging.getLogger(__name__)

MAX_MESSAGE_BYTES = 64 * 1024


class RejectedMessage(ValueError):
    """Queue data that is not a LoopNet job message (or plain JSON value)."""


class JobIdSerializer(Serializer):  # type: ignore[misc]
    """Huey serializer accepting only ``task_name(job_id)`` messages, in JSON."""

    def __init__(self, task_name: str) -> None:
        super().__init__()
        self.task_name = task_name

    def _serialize(self, data: Any) -> bytes:
        if isinstance(data, Message):
            return json.dumps({"message": self._message_fields(data)}).encode()
        return json.dumps({"value": _plain(data)}).encode()

    def _deserialize(self, data: bytes) -> Any:
        try:
            if len(data) > MAX_MESSAGE_BYTES:
                raise RejectedMessage(f"{len(data)} bytes")
            decoded = json.loads(data)
            if not isinstance(decoded, dict) or len(decoded) != 1:
                raise RejectedMessage("not a LoopNet queue record")
            if "message" in decoded:
                return self._message(decoded["message"])
            if "value" in decoded:
                return _unplain(decoded["value"])
            raise RejectedMessage("not a LoopNet queue record")
        except (ValueError, TypeError, KeyError) as exc:  # JSON errors are ValueErrors
            log.error("rejected a queue message that is not a LoopNet job (%s)", exc)
            raise RejectedMessage(f"rejected queue message: {exc}") from None

    def _message_fields(self, message: Message) -> dict[str, Any]:
        if message.name != self.task_name or message.kwargs or len(message.args) != 1:
            raise RejectedMessage(f"only {self.task_name}(job_id) is queued, not {message.name}")
        if message.on_complete or message.on_error or message.chord_config:
            raise RejectedMessage("job messages have no callbacks")
        return {
            "id": message.id,
            "name": message.name,
            "job_id": _job_id(message.args[0]),
            "eta": _plain(message.eta),
            "retries": message.retries,
            "retry_delay": message.retry_delay,
            "priority": message.priority,
            "expires": message.expires,
            "expires_resolved": _plain(message.expires_resolved),
            "timeout": message.timeout,
            "retry_backoff": message.retry_backoff,
        }

    def _message(self, fields: dict[str, Any]) -> Message:
        if fields["name"] != self.task_name:
            raise RejectedMessage(f"unknown task {fields['name']!r}")
        if not isinstance(fields["id"], str):
            raise RejectedMessage("a task id is a string")
        for name in ("retries", "retry_delay", "priority", "expires", "timeout"):
            if fields[name] is not None and not isinstance(fields[name], int | float):
                raise RejectedMessage(f"{name} is not a number")
        return Message(
            fields["id"],
            self.task_name,
            _unplain(fields["eta"]),
            fields["retries"],
            fields["retry_delay"],
            fields["priority"],
            (_job_id(fields["job_id"]),),
            {},
            None,
            None,
            fields["expires"],
            _unplain(fields["expires_resolved"]),
            fields["timeout"],
            None,
            fields["retry_backoff"],
        )


def _job_id(value: Any) -> int:
    if type(value) is not int or not 1 <= value <= MAX_JOB_ID:
        raise RejectedMessage(f"a job id is an integer in 1..{MAX_JOB_ID}, not {value!r}")
    return value


def _plain(value: Any) -> Any:
    """A JSON-ready copy of the plain values Huey stores (datetimes tagged)."""
    if isinstance(value, dt.datetime):
        return {"datetime": value.isoformat()}
    if isinstance(value, list | tuple):
        return [_plain(item) for item in value]
    if value is None or isinstance(value, bool | int | float | str):
        return value
    raise RejectedMessage(f"the queue stores plain values, not {type(value).__name__}")


def _unplain(value: Any) -> Any:
    if isinstance(value, dict):
        if set(value) != {"datetime"} or not isinstance(value["datetime"], str):
            raise RejectedMessage("unexpected object")
        return dt.datetime.fromisoformat(value["datetime"])
    if isinstance(value, list):
        return tuple(_unplain(item) for item in value)
    return value
