"""Reading PyTorch files a user hands to fgat: Lightning checkpoints and ``gaussians.pt``.

Unpickling an arbitrary object can run arbitrary code, so every file is read with
``torch.load(weights_only=True)``: tensors, numbers, strings and plain containers only, which is
all that fgat's checkpoints (static and dynamic, written by the CLI or from Python) and
``gaussians.pt`` hold, so no class is allow-listed. A file that holds anything else, or that is
not a PyTorch file at all, is refused with one line that names it.
"""

from __future__ import annotations

import pickle
import re
import warnings
from pathlib import Path

import torch

from fgat._core.resources import DiskFullError
from fgat.io.files import atomic_path


def load_torch_file(path: str | Path, source: str) -> dict:
    """The dict stored in a ``torch.save`` file, read without running any code from it.

    Parameters
    ----------
    path : str or Path
        The file (a Lightning ``.ckpt`` or a ``gaussians.pt``).
    source : str
        What the file was given as, for the error line (``"--ckpt_path"``, ``"model.static"``).

    Returns
    -------
    dict
        The file's content, tensors on the CPU.

    Raises
    ------
    FileNotFoundError
        ``path`` is not a file.
    ValueError
        The file holds objects other than tensors and plain values, is not a PyTorch file, is
        damaged, or does not hold a dict.
    """
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"{source}: {path} does not exist")
    try:
        with warnings.catch_warnings():  # e.g. "Detected pickle protocol 4": the error says more
            warnings.simplefilter("ignore", UserWarning)
            content = torch.load(path, map_location="cpu", weights_only=True)
    except Exception as error:  # noqa: BLE001 (torch.load raises anything on a file that is not its own)
        text = str(error).strip()
        found = re.search(r"Unsupported global: GLOBAL (\S+)", text)
        if isinstance(error, pickle.UnpicklingError) and found:
            raise ValueError(
                f"{source}: {path} contains {found.group(1)}, not only tensors and plain values; "
                "refused: fgat reads PyTorch files with weights_only=True, since unpickling other "
                "objects can run code"
            ) from None
        unpickler = re.search(r"WeightsUnpickler error:\s*(\S[^\n]*)", text)
        if unpickler:
            reason = f"weights-only unpickler: {unpickler.group(1)}"
        else:
            reason = (
                re.split(r"(?<=[.!?])\s", text.splitlines()[0])[0].rstrip(".")
                if text
                else type(error).__name__
            )
        raise ValueError(f"{source}: {path} is not a readable PyTorch file ({reason})") from None
    if not isinstance(content, dict):
        raise ValueError(
            f"{source}: {path} holds a {type(content).__name__}, expected a dict (a checkpoint or "
            "gaussians.pt)"
        )
    return content


def content_bytes(content) -> int:
    """Bytes of the tensors in ``content`` (nested dicts, lists and tuples), each storage once:
    about what ``torch.save`` writes."""
    seen: dict[int, int] = {}

    def visit(value) -> None:
        if isinstance(value, torch.Tensor):
            storage = value.untyped_storage()
            seen[storage.data_ptr() or id(storage)] = storage.nbytes()
        elif isinstance(value, dict):
            for item in value.values():
                visit(item)
        elif isinstance(value, (list, tuple)):
            for item in value:
                visit(item)

    visit(content)
    return sum(seen.values())


def save_torch_file(content: dict, path: str | Path, what: str = "checkpoint") -> Path:
    """``torch.save(content)`` to ``path`` under a temporary name renamed when whole
    (:func:`fgat.io.files.atomic_path`): a write that fails leaves no partial file.

    Raises
    ------
    fgat._core.resources.DiskFullError
        The disk (or quota) is full: one line naming the ``what`` at ``path``, about how many
        bytes it needs (:func:`content_bytes`) and how many its file system has free.
    """
    path = Path(path)
    try:
        with atomic_path(path, nbytes=content_bytes(content)) as temporary:
            torch.save(content, temporary)
    except DiskFullError as error:
        raise DiskFullError(f"{what}: {error}; then resume with --ckpt_path last") from None
    return path
