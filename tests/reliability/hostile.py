"""Hypothesis strategies for the hostile values found by hand that schema fuzzing missed: deeply
nested JSON, integers beyond 64 bits, NUL characters, feature arrays of the wrong shape, numbers
past Python's 4,300-digit conversion limit in JSON form fields, ``.npy`` headers declaring
absurd shapes, and zip members with the encryption bit, an unreadable compression method or
corrupt deflate data."""

from __future__ import annotations

import io
import json
import struct
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
                *long_number_fields(),
                json.dumps({"rotation": [[1, 0], [0, 1]], "translation": [0, 0, 0]}),
            ]
        ),
        hostile_text(),
    )


def long_number_fields() -> list[str]:
    """Pose and intrinsics whose numbers pass Python's integer-conversion limit (4,300 digits:
    ``json.loads`` raises a plain ``ValueError``)."""
    return [
        json.dumps({"fx": 1, "fy": 1, "cx": 1, "cy": 1}).replace('"fx": 1', '"fx": ' + "7" * 4301),
        json.dumps({"rotation": [1, 0, 0, 0], "translation": [0, 0, 0]}).replace(
            "[0, 0, 0]", "[" + "9" * 5000 + ", 0, 0]"
        ),
        json.dumps({"fx": 1, "fy": 1, "cx": 1, "cy": 1}).replace('"cy": 1', '"cy": ' + "3" * 4302),
        '{"fx": -' + "1" * 100_000 + ', "fy": 1, "cx": 1, "cy": 1}',
    ]


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


def npy_declaring(shape: tuple[int, ...], dtype: str = "<f4", data: bytes = b"") -> bytes:
    """A ``.npy`` file whose header declares ``shape`` (10^12 values...), followed by ``data``."""
    buffer = io.BytesIO()
    header = {"descr": dtype, "fortran_order": False, "shape": shape}
    np.lib.format.write_array_header_1_0(buffer, header)
    return buffer.getvalue() + data


def replaced_member(
    payload: bytes, name: str, content: bytes, method: int = zipfile.ZIP_STORED
) -> bytes:
    """The zip ``payload`` with member ``name``'s content replaced (written with ``method``)."""
    buffer = io.BytesIO()
    with (
        zipfile.ZipFile(buffer, "w") as archive,
        zipfile.ZipFile(io.BytesIO(payload)) as original,
    ):
        for info in original.infolist():
            data = content if info.filename == name else original.read(info)
            archive.writestr(info.filename, data, compress_type=method)
    return buffer.getvalue()


def patched_member_header(
    payload: bytes, name: str, *, flags: int | None = None, method: int | None = None
) -> bytes:
    """The zip ``payload`` with member ``name``'s general-purpose flags (bit 0: encrypted) or
    compression method (6: implode) rewritten in its local and central headers."""
    data = bytearray(payload)
    local = zipfile.ZipFile(io.BytesIO(payload)).getinfo(name).header_offset
    central = struct.unpack_from("<I", data, data.rindex(b"PK\x05\x06") + 16)[0]
    while True:  # the central directory entry of ``name``
        length, extra, comment = struct.unpack_from("<HHH", data, central + 28)
        if data[central + 46 : central + 46 + length] == name.encode():
            break
        central += 46 + length + extra + comment
    for offset_flags, offset_method in ((local + 6, local + 8), (central + 8, central + 10)):
        if flags is not None:
            struct.pack_into("<H", data, offset_flags, flags)
        if method is not None:
            struct.pack_into("<H", data, offset_method, method)
    return bytes(data)


def corrupt_deflate(payload: bytes, name: str) -> bytes:
    """The zip ``payload`` with member ``name`` deflated and its compressed data overwritten
    past the first bytes (zlib then fails, or the CRC check does)."""
    deflated = replaced_member(
        payload, name, zipfile.ZipFile(io.BytesIO(payload)).read(name), zipfile.ZIP_DEFLATED
    )
    info = zipfile.ZipFile(io.BytesIO(deflated)).getinfo(name)
    data = bytearray(deflated)
    start = info.header_offset + 30 + len(info.filename.encode()) + len(info.extra)
    for i in range(start + 8, start + max(9, info.compress_size - 4)):
        data[i] = 0xFF
    return bytes(data)


def zip_tampering(valid: bytes, name: str) -> dict[str, bytes]:
    """The hostile variants of a valid ``.npz`` ``valid``, each on its array ``name``."""
    member = f"{name}.npy"
    return {
        "declares 10^12 values": replaced_member(valid, member, npy_declaring((10**12,))),
        "declares 10^12 rows, deflated": replaced_member(
            valid, member, npy_declaring((10**12, 128), data=b"\0" * 4096), zipfile.ZIP_DEFLATED
        ),
        "encrypted member": patched_member_header(valid, member, flags=0x1),
        "compression method 6": patched_member_header(valid, member, method=6),
        "corrupt deflate": corrupt_deflate(valid, member),
    }


@st.composite
def feature_payloads(draw: st.DrawFn, valid: bytes) -> bytes:
    """A valid precomputed-features payload, or one array reshaped, retyped, renamed, declaring
    an absurd shape, or in a member an ``.npz`` reader must refuse (zip flags and methods)."""
    arrays = dict(np.load(io.BytesIO(valid), allow_pickle=False))
    how = draw(
        st.sampled_from(
            ["valid", "reshape", "extra column", "empty", "rename", "dtype", "zip tampering"]
        )
    )
    if how == "valid":
        return valid
    if how == "zip tampering":
        variants = zip_tampering(valid, draw(st.sampled_from(sorted(arrays))))
        return variants[draw(st.sampled_from(sorted(variants)))]
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
