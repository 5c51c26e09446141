"""Files written safely: atomic writes (a temporary name renamed into place), output
checks, plain-text reads, CSV and JSON tables.
"""

from __future__ import annotations

import contextlib
import csv
import glob
import json
import math
import os
import re
import tempfile
from collections.abc import Iterator, Mapping, Sequence
from pathlib import Path

from fgat._core.resources import DISK_FULL_ERRNOS, check_disk_space, disk_full_error
from fgat.io.zarr_series import is_zarr


def _temporary_pattern(path: Path) -> re.Pattern:
    """Names of :func:`atomic_path`'s temporaries for ``path``: ``.<name>.<pid>.<random>.part``."""
    return re.compile(rf"\.{re.escape(path.name)}\.(\d+)\.[A-Za-z0-9_]+\.part")


def process_alive(pid: int) -> bool:
    """Whether a process ``pid`` exists (one of another user counts as alive). On Windows, where
    signal 0 would terminate the process, every PID counts as alive."""
    if os.name == "nt":
        return True
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        pass
    return True


def remove_stale_temporaries(path: str | Path) -> list[Path]:
    """Delete the temporaries that killed writers of ``path`` left behind (see :func:`atomic_path`);
    those of a live process, and every other file, are kept. Returns the removed paths."""
    path = Path(path)
    pattern = _temporary_pattern(path)
    removed = []
    for candidate in path.parent.glob(f".{glob.escape(path.name)}.*.part"):
        match = pattern.fullmatch(candidate.name)
        if match and int(match[1]) != os.getpid() and not process_alive(int(match[1])):
            candidate.unlink(missing_ok=True)
            removed.append(candidate)
    return removed


@contextlib.contextmanager
def atomic_path(path: str | Path, nbytes: int | None = None) -> Iterator[Path]:
    """Yield a temporary path beside ``path``; rename it onto ``path`` only if the block succeeds.

    The temporary is ``.<name>.<pid>.<random>.part`` in the target's folder, removed when the block
    fails; one that a killed process left (its PID no longer running) is removed by the next
    writer of the same target. With ``nbytes`` (the size about to be written) a disk without
    that much room is refused before writing (:func:`fgat._core.resources.check_disk_space`); a
    write that still runs out of room (``ENOSPC``, ``EDQUOT``) ends in one
    :class:`~fgat._core.resources.DiskFullError` naming ``path`` and the bytes needed, the temporary
    removed.
    """
    path = Path(path)
    if not path.parent.is_dir():
        raise FileNotFoundError(f"cannot write {path}: folder {path.parent} does not exist")
    if path.is_dir():
        raise ValueError(f"cannot write {path}: it is a folder")
    remove_stale_temporaries(path)
    if nbytes is not None:
        check_disk_space(path, nbytes, what=f"cannot write {path}")
    try:
        handle, temporary = tempfile.mkstemp(
            prefix=f".{path.name}.{os.getpid()}.", suffix=".part", dir=path.parent
        )
    except OSError as error:
        if error.errno in DISK_FULL_ERRNOS:
            raise disk_full_error(path, error, nbytes) from None
        raise ValueError(
            f"cannot write {path}: folder {path.parent} is not writable ({error.strerror})"
        ) from None
    os.close(handle)
    temporary = Path(temporary)
    umask = os.umask(0)
    os.umask(umask)
    try:
        yield temporary
        temporary.chmod(0o666 & ~umask)  # mkstemp creates 0600; give the file the usual mode
        os.replace(temporary, path)
    except OSError as error:
        if error.errno in DISK_FULL_ERRNOS:
            raise disk_full_error(path, error, nbytes) from None
        raise
    finally:
        temporary.unlink(missing_ok=True)


def check_output_file(
    path: str | Path, *, overwrite: bool = False, option: str | None = None
) -> Path:
    """Check, before any computation, that ``path`` can be written; return it as a Path.

    Refused with one line naming ``option`` (e.g. ``"--out"``) and the path: a missing folder
    (``FileNotFoundError``), a path that is a folder, an existing file unless ``overwrite``, a
    folder where no file can be created (probed by creating and removing a temporary file, so
    that read-only file systems and permissions count even for root) (``ValueError``).
    """
    path = Path(path)
    name = f"{option} {path}" if option else str(path)
    folder = path.resolve().parent
    if not folder.is_dir():
        raise FileNotFoundError(f"{name}: folder {folder} does not exist")
    store = is_zarr(path)
    if path.is_dir() and not store:
        raise ValueError(f"{name}: is a folder; expected a file name (or a *.zarr store)")
    if path.exists() and path.suffix == ".zarr" and not store:
        raise ValueError(f"{name}: exists and is not a Zarr store; it is not replaced")
    if path.exists() and not overwrite:
        raise ValueError(
            f"{name}: the {'store' if store else 'file'} exists; choose another name or pass "
            "--overwrite to replace it"
        )
    check_writable_folder(folder, name)
    return path


def check_writable_folder(folder: str | Path, name: str | None = None) -> None:
    """Raise ``ValueError`` naming ``name`` (default: the folder) unless a file can be created in
    the existing ``folder`` (a real probe: create and remove a temporary file)."""
    try:
        handle, probe = tempfile.mkstemp(prefix=".fgat-probe-", dir=folder)
        os.close(handle)
        os.unlink(probe)
    except OSError as error:
        raise ValueError(
            f"{name or folder}: cannot write in folder {folder} ({error.strerror})"
        ) from None


def require_file(path: str | Path) -> Path:
    path = Path(path)
    if not path.exists():
        raise FileNotFoundError(f"{path}: no such file")
    if not path.is_file():
        raise ValueError(f"{path}: not a file")
    return path


def write_csv(path: str | Path, columns: Sequence[str], rows) -> Path:
    """Write a table as CSV, atomically: a header of ``columns``, then one line per row (a
    mapping, read at ``columns``, or a sequence in that order)."""
    path = Path(path)
    with atomic_path(path) as temporary, temporary.open("w", newline="") as handle:
        writer = csv.writer(handle)
        writer.writerow(columns)
        writer.writerows(
            [row[c] for c in columns] if isinstance(row, Mapping) else row for row in rows
        )
    return path


def write_json(path: str | Path, data: Mapping[str, object]) -> Path:
    """Write ``data`` as indented JSON, atomically; NaN and infinite floats (at any depth of
    its lists) as ``null``, which strict JSON readers accept."""

    def plain(value):
        if isinstance(value, float) and not math.isfinite(value):
            return None
        if isinstance(value, (list, tuple)):
            return [plain(item) for item in value]
        return value

    path = Path(path)
    text = json.dumps({k: plain(v) for k, v in data.items()}, indent=2) + "\n"
    with atomic_path(path, len(text.encode())) as temporary:
        temporary.write_text(text)
    return path


def read_text(path: str | Path, source: str | None = None) -> str:
    """The UTF-8 text of the file ``path``; a file that is not UTF-8 text (binary, or another
    encoding) is one ``ValueError`` naming ``source`` (default the path) and the first bad
    byte."""
    path = Path(path)
    data = path.read_bytes()
    try:
        return data.decode("utf-8-sig")
    except UnicodeDecodeError as error:
        raise ValueError(
            f"{source or path}: not a UTF-8 text file (byte 0x{data[error.start]:02x} at offset "
            f"{error.start}); expected YAML text"
        ) from None
