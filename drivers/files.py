"""Opening an input file: a regular file of bounded size, else the caller's error, at once;
and creating an output file with exact permission bits.

Every file hilbo reads (a cart export or recording, a session log, a prior table, the config)
goes through :func:`open_regular_file` or :func:`read_regular_file`. Without the check,
``/dev/zero`` given as a file is read until memory runs out and a FIFO blocks the open until a
writer appears (forever, at the lab PC); a file far larger than any real one of its kind is a
wrong path, not data. The file is opened non-blocking (a FIFO's open returns at once), checked
with ``fstat`` on the open descriptor (no race with a rename between check and open), and read
at most ``max_bytes + 1`` bytes (a file that grows past its bound while being read is refused
too). ``OSError`` (no such file, permission denied) propagates unchanged: callers name the file
in their own words.

Files that hold health data (VO2, heart rate, body mass) are created with
:func:`create_private_file`: permission bits set on the open descriptor, so neither the umask
nor an older file of the same name leaves them readable by others (shared/DESIGN.md: session
files are the wearer's health data).
"""

from __future__ import annotations

import os
import stat
from collections.abc import Callable
from os import PathLike, fspath
from typing import BinaryIO

from drivers.errors import DriverConfigError

__all__ = [
    "MAX_CART_FILE_BYTES",
    "PRIVATE_FILE_MODE",
    "create_private_file",
    "describe_size",
    "open_regular_file",
    "read_regular_file",
]

MAX_CART_FILE_BYTES = 64 << 20
"""Largest cart export or recording read (64 MiB). A one-hour breath-by-breath export is well
under 1 MB (about 1,500 rows of a few hundred bytes), so this leaves a factor of 60 or more."""

PRIVATE_FILE_MODE = 0o600
"""Owner read/write only: the default mode of every file that holds health data."""

ErrorFactory = Callable[[str], Exception]

_KINDS = (
    (stat.S_ISDIR, "a directory"),
    (stat.S_ISFIFO, "a FIFO (named pipe)"),
    (stat.S_ISCHR, "a character device"),
    (stat.S_ISBLK, "a block device"),
    (stat.S_ISSOCK, "a socket"),
)


def describe_size(n_bytes: int) -> str:
    """``n_bytes`` for a message: ``"812 bytes"``, ``"3.2 MiB"``."""
    if n_bytes < 1 << 20:
        return f"{n_bytes:,} bytes"
    if n_bytes < 1 << 30:
        return f"{n_bytes / (1 << 20):.1f} MiB"
    return f"{n_bytes / (1 << 30):.1f} GiB"


def open_regular_file(
    path: str | PathLike[str], *, max_bytes: int, what: str, error: ErrorFactory = DriverConfigError
) -> BinaryIO:
    """Open ``path`` for binary reading if it is a regular file of at most ``max_bytes``.

    Args:
        path: The file.
        max_bytes: Largest size accepted.
        what: What the file should be, for the message (``"a cart export"``).
        error: Builds the exception raised for a file that is not regular or too large (the
            caller's package error, e.g. its config or format error).

    Returns:
        The open file (binary, unbuffered reads go through a ``BufferedReader``); the caller
        closes it.

    Raises:
        OSError: The file cannot be opened (no such file, permission denied...).
        Exception: ``error(message)`` for a directory, FIFO, device or socket, or a file larger
            than ``max_bytes``; the message names the path, what it is and what was expected.
    """
    p = fspath(path)
    # O_NONBLOCK: the open of a FIFO without a writer returns at once instead of waiting for one.
    fd = os.open(p, os.O_RDONLY | os.O_NONBLOCK | getattr(os, "O_CLOEXEC", 0))
    try:
        st = os.fstat(fd)
        if not stat.S_ISREG(st.st_mode):
            kind = next((name for test, name in _KINDS if test(st.st_mode)), "not a regular file")
            raise error(f"{p} is {kind}, not a regular file; expected {what}")
        if st.st_size > max_bytes:
            raise error(f"{p}: {describe_size(st.st_size)}, more than the {describe_size(max_bytes)} "
                        f"{what} may have; is it the right file?")
        os.set_blocking(fd, True)
        return os.fdopen(fd, "rb")
    except BaseException:
        os.close(fd)
        raise


_CHUNK_BYTES = 1 << 20


def read_regular_file(
    path: str | PathLike[str], *, max_bytes: int, what: str, error: ErrorFactory = DriverConfigError
) -> bytes:
    """The bytes of ``path``, checked as :func:`open_regular_file` checks it.

    Raises:
        OSError: The file cannot be opened or read.
        Exception: ``error(message)``: not a regular file, or more than ``max_bytes`` (also
            when it grows past them while being read).
    """
    # In chunks: read(n) allocates n bytes up front, and a bound of gigabytes is more memory
    # than a small machine (or the test's user-mode Linux) may have, whatever the file's size.
    chunks: list[bytes] = []
    total = 0
    with open_regular_file(path, max_bytes=max_bytes, what=what, error=error) as fh:
        while total <= max_bytes:
            chunk = fh.read(min(_CHUNK_BYTES, max_bytes + 1 - total))
            if not chunk:
                break
            chunks.append(chunk)
            total += len(chunk)
    data = b"".join(chunks)
    if len(data) > max_bytes:
        raise error(f"{fspath(path)}: grew past {describe_size(max_bytes)} while being read; "
                    f"expected {what}")
    return data


def create_private_file(path: str | PathLike[str], mode: int = PRIVATE_FILE_MODE) -> BinaryIO:
    """Create (or truncate) ``path`` for binary writing with exactly the permission bits ``mode``.

    Args:
        path: The file to write.
        mode: Permission bits, 0o000-0o777 (default owner read/write only).

    Returns:
        The open file; the caller closes it.

    Raises:
        OSError: The file cannot be created or its mode set.
    """
    fd = os.open(fspath(path), os.O_WRONLY | os.O_CREAT | os.O_TRUNC | getattr(os, "O_CLOEXEC", 0), mode)
    try:
        os.fchmod(fd, mode)  # the umask may have removed bits; a truncated old file keeps its mode
        return os.fdopen(fd, "wb")
    except BaseException:
        os.close(fd)
        raise
