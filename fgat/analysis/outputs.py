"""The output folder of an analysis: checked before the analysis, created only when its files are
written, and left as it was when a write fails (``python -m fgat analyze ...``).

Every file goes through one of :mod:`fgat.io`'s atomic writers (a temporary name, then a
rename), so a failed write never leaves a partial file; :func:`write_outputs` removes what the
failed run made (the folder it created, or the files it added to an existing one) and names the
file it could not write.
"""

from __future__ import annotations

import shutil
from collections.abc import Callable, Mapping, Sequence
from pathlib import Path

from fgat.io.files import check_output_file, check_writable_folder


def _existing_ancestor(folder: Path) -> Path:
    """The nearest of ``folder`` and its parents that exists."""
    existing = folder.resolve()
    while not existing.exists():
        existing = existing.parent
    return existing


def check_output_folder(
    folder: str | Path, names: Sequence[str], *, overwrite: bool = False, option: str = "--out"
) -> Path:
    """Check, before any computation and without creating anything, that ``names`` can be
    written into ``folder``.

    Refused with one line naming ``option`` and the folder: a file; a folder that cannot be
    created (a file on its path) or written in; an existing file of ``names`` unless
    ``overwrite``.
    """
    folder = Path(folder)
    if folder.exists() and not folder.is_dir():
        raise ValueError(f"{option} {folder}: a file; expected a folder")
    if folder.is_dir():
        for name in names:
            check_output_file(folder / name, overwrite=overwrite, option=option)
        return folder
    existing = _existing_ancestor(folder)
    if not existing.is_dir():
        raise ValueError(f"{option} {folder}: cannot create it, {existing} is a file")
    check_writable_folder(existing, f"{option} {folder}")
    return folder


def write_outputs(
    folder: str | Path,
    writers: Mapping[str, Callable[[Path], object]],
    *,
    option: str = "--out",
) -> list[Path]:
    """Create ``folder`` and write its files in order: ``writers[name](folder / name)``.

    Parameters
    ----------
    folder : str or Path
        The output folder (created with its missing parents).
    writers : mapping of str to callable
        File name -> a function writing that path through an atomic writer of :mod:`fgat.io`.
    option : str
        The option that named ``folder``, for errors.

    Returns
    -------
    list of Path
        The written files.

    Raises
    ------
    ValueError
        A file could not be written (an ``OSError``: disk full, permissions), naming it; a
        ``ValueError`` of a writer passes as it is. Either way the folders this call created
        are removed, or, in a folder that existed, the files it added.
    """
    folder = Path(folder)
    created = None if folder.is_dir() else _existing_ancestor(folder)
    folder.mkdir(parents=True, exist_ok=True)
    written, added = [], []
    try:
        for name, write in writers.items():
            path = folder / name
            existed = path.exists()
            try:
                write(path)
            except OSError as error:
                reason = error.strerror or str(error)
                raise ValueError(f"{option} {folder}: cannot write {path} ({reason})") from None
            written.append(path)
            if not existed:
                added.append(path)
    except BaseException:
        if created is not None:
            shutil.rmtree(_created_root(folder, created), ignore_errors=True)
        else:
            for path in added:
                path.unlink(missing_ok=True)
        raise
    return written


def _created_root(folder: Path, ancestor: Path) -> Path:
    """The outermost folder between ``ancestor`` (which existed) and ``folder`` (created)."""
    folder = folder.resolve()
    for parent in [folder, *folder.parents]:
        if parent.parent == ancestor:
            return parent
    return folder
