"""Hypothesis strategies for the hostile values found by hand that schema fuzzing missed: deeply
nested JSON, integers beyond 64 bits, NUL characters, and feature arrays of the wrong shape."""

from __future__ import annotations

import io
import json
import zipfile

import numpy as np
from hypothesis import strategies as st

# 2**31: past the 32-bit INTEGER ids of PostgreSQL (a lookup of one once overflowed there, 500)
HUGE_INTEGERS = (2**31, 6469693229, 2**63, 2**64, -(2**63) - 1, 10**30, 1409, 4096)


def deep_json(depth: int = 50_000) -> str:
    return "[" * depth + "]" * depth


def hostile_text() -> st.SearchStrategy[str]:
    """Names and descriptions: NUL characters, control characters, very long or deep text."""
    return st.one_of(
        st.sampled_from(["a\x00b", "\x00", "campus\x00", "s0\x00x", "r1\x00"]),
        st.text(alphabet=st.sampled_from("ab\x00\x01\x7f\n"), min_size=1, max_size=12),
        st.just(deep_json(2_000)),
    )


def hostile_json_field() -> st.SearchStrategy[str]:
    """Values of JSON form fields (pose, intrinsics)."""
    return st.one_of(
        st.sampled_from(
            [
                deep_json(),
                '{"a":' * 20_000 + "1" + "}" * 20_000,
                json.dumps({"rotation": [2**70, 0, 0, 0], "translation": [0, 0, 0]}),
                json.dumps({"fx": 10**400, "fy": 1, "cx": 1, "cy": 1}).replace("1e400", "9" * 500),
                '{"fx": "\\u0000", "fy": 1, "cx": 1, "cy": 1}',
                json.dumps({"rotation": [[1, 0], [0, 1]], "translation": [0, 0, 0]}),
            ]
        ),
        hostile_text(),
    )


def hostile_integers() -> st.SearchStrategy[int]:
    return st.one_of(st.sampled_from(HUGE_INTEGERS), st.integers(min_value=2**63))


def _savez(arrays: dict[str, np.ndarray]) -> bytes:
    buffer = io.BytesIO()
    np.savez(buffer, **arrays)  # type: ignore[arg-type]
    return buffer.getvalue()


def renamed_member(payload: bytes, old: str, new: str) -> bytes:
    """The ``.npz`` payload with one zip member renamed."""
    buffer = io.BytesIO()
    with (
        zipfile.ZipFile(buffer, "w") as archive,
        zipfile.ZipFile(io.BytesIO(payload)) as original,
    ):
        for info in original.infolist():
            archive.writestr(new if info.filename == old else info.filename, original.read(info))
    return buffer.getvalue()


@st.composite
def feature_payloads(draw: st.DrawFn, valid: bytes) -> bytes:
    """A valid precomputed-features payload, or one array reshaped, retyped or renamed."""
    arrays = dict(np.load(io.BytesIO(valid), allow_pickle=False))
    how = draw(st.sampled_from(["valid", "reshape", "extra column", "empty", "rename", "dtype"]))
    if how == "valid":
        return valid
    name = draw(st.sampled_from(sorted(arrays)))
    if how == "rename":
        return renamed_member(
            valid, f"{name}.npy", draw(st.sampled_from([name, name.upper(), "x.npy"]))
        )
    array = arrays[name]
    if array.ndim == 0:  # the signature: make it 1-d or a number
        arrays[name] = array.reshape(1) if how != "dtype" else np.array(0)
    elif how == "reshape":
        arrays[name] = array.reshape(-1) if array.ndim > 1 else array[:, None]
    elif how == "extra column" and array.ndim == 2:
        arrays[name] = np.concatenate([array, array[:, :1]], axis=1)
    elif how == "empty":
        arrays[name] = array[:0]
    elif how == "dtype":
        arrays[name] = array.astype(draw(st.sampled_from([np.int64, np.complex64, np.bool_])))
    return _savez(arrays)
