"""Reading ``.npz`` archives (NumPy's zip of ``.npy`` arrays) sent by others, within bounds.

``numpy.load`` trusts what it reads: an array is allocated at the shape its ``.npy`` header
declares (a shape of 10^12 is a memory error), and zip features it cannot read (an encrypted
member, a compression method other than stored or deflate, corrupt deflate data) surface as
``RuntimeError``, ``NotImplementedError`` or ``zlib.error``. :class:`NpzReader` checks each
member's zip flags and method when the archive is opened, reads an array's header before any
of its data, refuses a declared size over the caller's bound before inflating a byte, never
unpickles, checks the zip's CRC, and turns every failure into :class:`InvalidInput` (HTTP 422)
naming the archive and the array. The precomputed-features payload and the snapshot's
``features.npz`` both read through it; large arrays can go to a ``.npy`` file on disk (streamed
in bounded chunks) and come back memory-mapped.
"""

from __future__ import annotations

import io
import math
import zipfile
import zlib
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path
from typing import IO

import numpy as np

from service.errors import InvalidInput

READABLE_METHODS = {zipfile.ZIP_STORED: "stored", zipfile.ZIP_DEFLATED: "deflate"}
ENCRYPTED_FLAG = 0x1
MAX_HEADER_BYTES = 10_000  # numpy's own bound on a .npy header
COPY_CHUNK = 1024 * 1024  # bytes inflated at a time when an array goes to disk
# what reading a zip member can raise on hostile input (besides InvalidInput)
UNREADABLE = (
    ValueError,
    OSError,
    EOFError,
    zipfile.BadZipFile,
    zlib.error,
    RuntimeError,
    NotImplementedError,
)


@dataclass(frozen=True)
class ArrayHeader:
    """What a ``.npy`` header declares, and where the data starts."""

    shape: tuple[int, ...]
    dtype: np.dtype
    fortran_order: bool

    @property
    def nbytes(self) -> int:
        """Bytes of the declared array (Python integers: no overflow for absurd shapes)."""
        return math.prod(self.shape) * self.dtype.itemsize


class NpzReader:
    """An ``.npz`` archive from bytes or a file, its members checked on opening.

    ``what`` names the archive in messages (``"the features payload"``).
    """

    def __init__(self, source: bytes | Path, what: str) -> None:
        self.what = what
        try:
            self._zip = zipfile.ZipFile(io.BytesIO(source) if isinstance(source, bytes) else source)
            infos = self._zip.infolist()
        except (*UNREADABLE, zipfile.LargeZipFile) as exc:
            raise InvalidInput(f"{what} is not an .npz archive: {exc}") from exc
        self.members: dict[str, zipfile.ZipInfo] = {}
        for info in infos:
            if info.filename in self.members:
                raise InvalidInput(f"{what} holds {info.filename!r} twice")
            if info.flag_bits & ENCRYPTED_FLAG:
                raise InvalidInput(f"{what}'s {info.filename!r} is encrypted")
            if info.compress_type not in READABLE_METHODS:
                raise InvalidInput(
                    f"{what}'s {info.filename!r} uses zip compression method "
                    f"{info.compress_type}; only stored (0) and deflate (8) are read"
                )
            self.members[info.filename] = info
        # members whose header was read, left open just past it: each is inflated once
        self._opened: dict[str, tuple[IO[bytes], ArrayHeader]] = {}

    def close(self) -> None:
        for member, _ in self._opened.values():
            member.close()
        self._opened.clear()
        self._zip.close()

    def __enter__(self) -> NpzReader:
        return self

    def __exit__(self, *_: object) -> None:
        self.close()

    @property
    def arrays(self) -> set[str]:
        """The members' names without ``.npy`` (other members keep their full name)."""
        return {name.removesuffix(".npy") for name in self.members}

    def header(self, name: str) -> ArrayHeader:
        """Array ``name``'s declared shape and type, read without touching its data (the
        member stays open there, so reading the array later inflates nothing twice)."""
        if name not in self._opened:
            member = self._open(name)
            try:
                self._opened[name] = (member, self._header(name, member))
            except BaseException:
                member.close()
                raise
        return self._opened[name][1]

    def read(self, name: str, max_bytes: int) -> np.ndarray:
        """Array ``name`` in memory, refused unread when it declares more than ``max_bytes``."""
        with self._data(name, max_bytes) as (member, header):
            buffer = bytearray(header.nbytes)
            self._fill(name, member, memoryview(buffer))
        return _as_array(buffer, header)

    def extract(self, name: str, target: Path, max_bytes: int) -> np.ndarray:
        """Array ``name`` written to the ``.npy`` file ``target`` in bounded chunks, returned
        memory-mapped (read-only); refused unread when it declares more than ``max_bytes``."""
        with self._data(name, max_bytes) as (member, header):
            with target.open("wb") as out:
                np.lib.format.write_array_header_1_0(
                    out,
                    {
                        "descr": np.lib.format.dtype_to_descr(header.dtype),
                        "fortran_order": header.fortran_order,
                        "shape": header.shape,
                    },
                )
                left = header.nbytes
                while left:
                    chunk = self._chunk(name, member, min(left, COPY_CHUNK))
                    out.write(chunk)
                    left -= len(chunk)
            self._at_end(name, member)
        if header.nbytes == 0:  # an empty file cannot be mapped
            return np.zeros(header.shape, header.dtype)
        return np.load(target, mmap_mode="r", allow_pickle=False)

    # ----- helpers -------------------------------------------------------------------------

    @contextmanager
    def _data(self, name: str, max_bytes: int) -> Iterator[tuple[IO[bytes], ArrayHeader]]:
        """The member positioned at its data, its header within ``max_bytes``; closed after."""
        header = self.header(name)
        member = self._opened.pop(name)[0]
        try:
            if header.nbytes > max_bytes:
                raise InvalidInput(
                    f"{self.what}'s array '{name}' declares shape {header.shape} of "
                    f"{header.dtype} ({header.nbytes} bytes); at most {max_bytes} bytes fit here"
                )
            yield member, header
        finally:
            member.close()

    def _open(self, name: str) -> IO[bytes]:
        info = self.members.get(f"{name}.npy")
        if info is None:
            raise InvalidInput(f"{self.what} has no array '{name}'")
        try:
            return self._zip.open(info)
        except UNREADABLE as exc:
            raise InvalidInput(f"{self.what}'s array '{name}' is unreadable: {exc}") from exc

    def _header(self, name: str, member: IO[bytes]) -> ArrayHeader:
        try:
            version = np.lib.format.read_magic(member)
            if version == (1, 0):
                shape, fortran, dtype = np.lib.format.read_array_header_1_0(
                    member, max_header_size=MAX_HEADER_BYTES
                )
            elif version == (2, 0):
                shape, fortran, dtype = np.lib.format.read_array_header_2_0(
                    member, max_header_size=MAX_HEADER_BYTES
                )
            else:
                raise InvalidInput(
                    f"{self.what}'s array '{name}' is .npy version {version}; 1.0 and 2.0 are read"
                )
        except InvalidInput:
            raise
        except (*UNREADABLE, TypeError, SyntaxError) as exc:
            raise InvalidInput(f"{self.what}'s array '{name}' has no valid header: {exc}") from exc
        if any(n < 0 for n in shape):
            raise InvalidInput(f"{self.what}'s array '{name}' declares a negative shape {shape}")
        if dtype.hasobject or dtype.fields is not None or dtype.subdtype is not None:
            raise InvalidInput(
                f"{self.what}'s array '{name}' has type {dtype}: only plain numbers and text"
            )
        return ArrayHeader(tuple(int(n) for n in shape), dtype, bool(fortran))

    def _chunk(self, name: str, member: IO[bytes], size: int) -> bytes:
        try:
            chunk = member.read(size)
        except UNREADABLE as exc:
            raise InvalidInput(f"{self.what}'s array '{name}' is unreadable: {exc}") from exc
        if not chunk:
            raise InvalidInput(f"{self.what}'s array '{name}' is shorter than its header says")
        return chunk

    def _fill(self, name: str, member: IO[bytes], view: memoryview) -> None:
        position = 0
        while position < len(view):
            chunk = self._chunk(name, member, min(len(view) - position, COPY_CHUNK))
            view[position : position + len(chunk)] = chunk
            position += len(chunk)
        self._at_end(name, member)

    def _at_end(self, name: str, member: IO[bytes]) -> None:
        """The member ends with the array (reading to its end also checks the zip's CRC)."""
        try:
            extra = member.read(1)
        except UNREADABLE as exc:
            raise InvalidInput(f"{self.what}'s array '{name}' is unreadable: {exc}") from exc
        if extra:
            raise InvalidInput(f"{self.what}'s array '{name}' has bytes after its data")


def _as_array(buffer: bytearray, header: ArrayHeader) -> np.ndarray:
    flat = np.frombuffer(buffer, dtype=header.dtype)
    return flat.reshape(header.shape, order="F" if header.fortran_order else "C")
