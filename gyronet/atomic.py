"""Write an output file whole or not at all: a temporary file in the same folder, renamed into place.

A full disk, a quota or a crash halfway leaves the previous file (or none) instead of a file
whose last line is cut in half, and a full disk becomes one :class:`OutputError` line for the
user instead of a traceback. Use it for every file a command writes::

    with atomic_output(path) as tmp:
        frame.to_csv(tmp)          # anything that writes a file at ``tmp``
"""
from __future__ import annotations

import contextlib
import errno
import gzip
import json
import logging
import math
import numbers
import os
import shutil
import tempfile
from pathlib import Path
from typing import Any, Iterator, Mapping

from gyronet.errors import GyronetError

log = logging.getLogger(__name__)

_USER_ERRNOS = {errno.ENOSPC: "no space left on the device", errno.EDQUOT: "disk quota exceeded",
                errno.EROFS: "read-only file system", errno.EACCES: "permission denied",
                errno.EPERM: "operation not permitted", errno.EFBIG: "file too large for the file system",
                errno.EISDIR: "it is a folder", errno.ENOTDIR: "a part of the path is a file, not a folder",
                errno.ENAMETOOLONG: "name too long"}


class OutputError(GyronetError, OSError):
    """An output file that could not be written (full disk, no permission); nothing was left behind."""


@contextlib.contextmanager
def atomic_output(path: str | os.PathLike) -> Iterator[Path]:
    """Yield a temporary path beside ``path``; when the block ends without error, rename it to ``path``.

    A ``path`` ending in ``.gz`` gets the block's file gzip-compressed, as its name promises. On any
    error the temporary file is removed and ``path`` is left as it was. An OSError that a user can act
    on (no space, quota, read-only, permission) becomes one :class:`OutputError` line naming ``path``;
    other exceptions pass through unchanged.
    """
    path = Path(path)
    if path.name in ("", ".", ".."):  # output= or output=.: the rename onto a folder failed as "Device or resource
        # busy", naming the temporary file
        raise _user_error(path, OSError(errno.EISDIR, "it is a folder"))
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        fd, name = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".part", dir=path.parent)
        os.close(fd)
    except FileExistsError as err:  # mkdir: a part of the folder path is a file
        raise _user_error(path, OSError(errno.ENOTDIR, err.strerror)) from None
    except OSError as err:
        raise _user_error(path, err) from None
    tmp = Path(name)
    try:
        yield tmp
        if path.name.lower().endswith(".gz"):
            _gzip_in_place(tmp)
        os.chmod(tmp, 0o666 & ~_UMASK)  # mkstemp's 0600 is for the temporary file only
        os.replace(tmp, path)
    except OSError as err:
        tmp.unlink(missing_ok=True)
        raise _user_error(path, err) from None
    except BaseException:
        tmp.unlink(missing_ok=True)
        raise
    log.debug("wrote %s", path)


def _gzip_in_place(path: Path) -> None:
    """Replace ``path``'s bytes with their gzip stream (level 6: a tenth of the CPU of 9, a few % larger)."""
    packed = path.with_name(path.name + ".gz")
    try:
        with open(path, "rb") as source, gzip.open(packed, "wb", compresslevel=6) as target:
            shutil.copyfileobj(source, target, 1 << 20)
        os.replace(packed, path)
    finally:
        packed.unlink(missing_ok=True)


def refuse_overwriting(input_path: str | os.PathLike, output_path: str | os.PathLike) -> None:
    """Refuse, in one line, an output that is the command's own input: a recording cannot be made again."""
    source, target = Path(input_path), Path(output_path)
    with contextlib.suppress(OSError):
        if source.resolve() == target.resolve() or (target.exists() and os.path.samefile(source, target)):
            raise GyronetError(f"{target}: the output is the input file itself, which writing would replace; "
                               "choose another output")


def write_text(path: str | os.PathLike, text: str) -> None:
    """``path`` holding ``text``, written whole or not at all (``atomic_output``)."""
    with atomic_output(path) as tmp:
        tmp.write_text(text)


def write_json(path: str | os.PathLike, value: Any, indent: int = 2) -> None:
    """``value`` as :func:`json_text`, written whole or not at all."""
    write_text(path, json_text(value, indent))


def json_text(value: Any, indent: int = 2) -> str:
    """``value`` as strict JSON (:func:`jsonable`), ending in a newline: any reader takes it, jq and JavaScript
    too, where a bare ``NaN`` is an error."""
    return json.dumps(jsonable(value), indent=indent, allow_nan=False) + "\n"


def jsonable(value: Any) -> Any:
    """``value`` with only JSON's types: numpy arrays and numbers as Python's, tuples as lists, keys as text,
    NaN and infinities as None (null: a figure with no value)."""
    if isinstance(value, Mapping):
        return {str(k): jsonable(v) for k, v in value.items()}
    if hasattr(value, "tolist") and not isinstance(value, (str, bytes)):  # a numpy array or number
        value = value.tolist()
    if isinstance(value, (list, tuple)):
        return [jsonable(v) for v in value]
    if isinstance(value, bool) or value is None:
        return value
    if isinstance(value, numbers.Integral):
        return int(value)
    if isinstance(value, numbers.Real):
        return float(value) if math.isfinite(value) else None
    return value


_FULL = {errno.ENOSPC, errno.EDQUOT, errno.EFBIG}


def _user_error(path: Path, err: OSError) -> OSError:
    reason = _USER_ERRNOS.get(err.errno)
    if reason is None or isinstance(err, OutputError):
        return err
    advice = "free space or choose another output folder" if err.errno in _FULL else "choose another output path"
    error = OutputError(f"{path}: cannot write ({reason}); nothing was written: {advice} and run again")
    error.errno = err.errno
    return error


def _umask() -> int:
    mask = os.umask(0)
    os.umask(mask)
    return mask


_UMASK = _umask()  # read once, at import: os.umask is process-wide and not thread-safe
