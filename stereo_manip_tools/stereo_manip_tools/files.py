"""
Opening files named by parameters or requests: regular files only (no rclpy needed).

A path parameter that names a FIFO, a device or a directory would block a node's callback on
``open`` (a FIFO waits for a writer) or read without end (``/dev/zero``). These helpers check
the file type on the open descriptor (``O_NONBLOCK``, then ``fstat``), so nothing blocks and
there is no window between the check and the open.
"""

from __future__ import annotations

import io
import os
from pathlib import Path
import stat
from typing import IO, Optional

__all__ = ['NotARegularFileError', 'check_regular_file', 'open_regular_file']


class NotARegularFileError(ValueError):
    """A path that exists but is not a regular file (FIFO, device, socket, directory)."""


def _kind(mode: int) -> str:
    for test, name in ((stat.S_ISDIR, 'a directory'), (stat.S_ISFIFO, 'a FIFO'),
                       (stat.S_ISCHR, 'a character device'), (stat.S_ISBLK, 'a block device'),
                       (stat.S_ISSOCK, 'a socket')):
        if test(mode):
            return name
    return 'not a regular file'


def check_regular_file(path: os.PathLike | str, what: str = 'file',
                       max_bytes: Optional[int] = None) -> Path:
    """
    ``path`` as a Path if it is a regular file (symlinks followed), of at most ``max_bytes``.

    For libraries that open the path themselves (e.g. Open3D's mesh readers).

    :raises FileNotFoundError: nothing at ``path``.
    :raises NotARegularFileError: a FIFO, device, socket or directory, or a file too large.
    """
    p = Path(path)
    try:
        st = os.stat(p)
    except FileNotFoundError:
        raise FileNotFoundError(f'{what} {p} does not exist') from None
    if not stat.S_ISREG(st.st_mode):
        raise NotARegularFileError(f'{what} {p} is {_kind(st.st_mode)}, not a regular file')
    if max_bytes is not None and st.st_size > max_bytes:
        raise NotARegularFileError(f'{what} {p} has {st.st_size} bytes; at most {max_bytes}')
    return p


def open_regular_file(path: os.PathLike | str, what: str = 'file', *, binary: bool = False,
                      encoding: str = 'utf-8', max_bytes: Optional[int] = None) -> IO:
    """
    Open ``path`` for reading only if it is a regular file; never blocks on a FIFO.

    :raises FileNotFoundError: nothing at ``path``.
    :raises NotARegularFileError: a FIFO, device, socket or directory, or a file too large.
    """
    p = Path(path)
    try:
        fd = os.open(p, os.O_RDONLY | os.O_NONBLOCK)
    except FileNotFoundError:
        raise FileNotFoundError(f'{what} {p} does not exist') from None
    except IsADirectoryError:
        raise NotARegularFileError(f'{what} {p} is a directory, not a regular file') from None
    try:
        st = os.fstat(fd)
        if not stat.S_ISREG(st.st_mode):
            raise NotARegularFileError(f'{what} {p} is {_kind(st.st_mode)}, not a regular file')
        if max_bytes is not None and st.st_size > max_bytes:
            raise NotARegularFileError(f'{what} {p} has {st.st_size} bytes; at most '
                                       f'{max_bytes}')
        os.set_blocking(fd, True)
        raw = os.fdopen(fd, 'rb')
    except BaseException:
        os.close(fd)
        raise
    return raw if binary else io.TextIOWrapper(raw, encoding=encoding)
