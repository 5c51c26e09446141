"""What produced a result: a fingerprint of a resolved configuration and of its input files.

A stage or trial counts as finished only for the same fingerprint: the resolved configuration
(every field after config files, defaults and command-line overrides, less the fields that do
not change the result: names, logging, progress bars, output folders) with every field that
names an existing file or folder replaced by the digest of its contents. Changing a seed, an
override or the bytes of an input file changes the fingerprint; moving or renaming a file, a
different MLflow experiment or output folder does not.

The record of a run folder (``fingerprint.json``) holds the fingerprint, the canonical
configuration it was computed from (so a mismatch can name the fields that differ) and the
run's status.
"""

from __future__ import annotations

import hashlib
import json
import os
import socket
from dataclasses import dataclass, field
from pathlib import Path

RECORD = "fingerprint.json"

# Fields that never change what a run computes (dotted paths into the resolved config).
IGNORED = frozenset(
    {
        "config",
        "ckpt_path",
        "weights_only",
        "mlflow",
        "checkpoint_every",
        "times",
        "out",
        "overwrite",
        "trainer.default_root_dir",
        "trainer.enable_progress_bar",
        "trainer.enable_model_summary",
        "trainer.logger",
        "trainer.log_every_n_steps",
        "trainer.enable_checkpointing",
        "trainer.profiler",
    }
)
# Fields a resumed run may change: how long it trains.
TRAINING_LENGTH = frozenset(
    {
        "trainer.max_steps",
        "trainer.max_epochs",
        "trainer.max_time",
        "trainer.min_steps",
        "trainer.min_epochs",
    }
)


@dataclass(frozen=True)
class Fingerprint:
    """A digest and the canonical configuration it was computed from.

    Attributes
    ----------
    digest : str
        Hex SHA-256 of the canonical configuration (64 characters).
    config : dict
        The configuration with ignored fields removed and input paths replaced by
        ``"file:<blake2b>"`` / ``"folder:<blake2b>"`` content digests.
    """

    digest: str
    config: dict = field(compare=False)

    @property
    def short(self) -> str:
        """The first 8 hex digits, for folder names and messages."""
        return self.digest[:8]


def file_digest(path: Path, chunk: int = 1 << 23) -> str:
    """BLAKE2b digest (hex) of a file's bytes, read in ``chunk``-byte blocks."""
    digest = hashlib.blake2b(digest_size=16)
    with path.open("rb") as handle:
        while block := handle.read(chunk):
            digest.update(block)
    return digest.hexdigest()


def folder_digest(path: Path) -> str:
    """BLAKE2b digest (hex) of the names and contents of the files directly inside a folder."""
    digest = hashlib.blake2b(digest_size=16)
    for item in sorted(p for p in path.iterdir() if p.is_file()):
        digest.update(f"{item.name}\0{file_digest(item)}\0".encode())
    return digest.hexdigest()


def _looks_like_path(text: str) -> bool:
    return ("/" in text or "." in text) and Path(text).exists()


def canonical(value, prefix: str = ""):
    """Drop ignored fields and replace existing paths by their content digests, recursively."""
    if isinstance(value, dict):
        return {
            key: canonical(item, f"{prefix}{key}.")
            for key, item in sorted(value.items())
            if f"{prefix}{key}" not in IGNORED
        }
    if isinstance(value, (list, tuple)):
        return [canonical(item, prefix) for item in value]
    if isinstance(value, str) and _looks_like_path(value):
        path = Path(value)
        return f"file:{file_digest(path)}" if path.is_file() else f"folder:{folder_digest(path)}"
    return value


def fingerprint(config: dict) -> Fingerprint:
    """The fingerprint of a resolved configuration (a plain dict, e.g. a parsed config dump)."""
    content = canonical(config)
    text = json.dumps(content, sort_keys=True, default=str, separators=(",", ":"))
    return Fingerprint(hashlib.sha256(text.encode()).hexdigest(), content)


def _flatten(value, prefix: str = "") -> dict[str, object]:
    if isinstance(value, dict) and value:
        return {
            key: item
            for name, child in value.items()
            for key, item in _flatten(child, f"{prefix}{name}.").items()
        }
    return {prefix.rstrip("."): value}


def differing_keys(
    old: dict, new: dict, ignore: frozenset[str] = frozenset()
) -> list[tuple[str, object, object]]:
    """``(dotted key, old value, new value)`` for every field in which two canonical
    configurations differ (``"<unset>"`` where one lacks it), sorted by key; the keys in
    ``ignore`` left out."""
    before, after = _flatten(old), _flatten(new)
    return [
        (key, before.get(key, "<unset>"), after.get(key, "<unset>"))
        for key in sorted(set(before) | set(after))
        if key not in ignore and before.get(key, "<unset>") != after.get(key, "<unset>")
    ]


def differing_fields(
    old: dict, new: dict, limit: int = 4, ignore: frozenset[str] = frozenset()
) -> str:
    """``"seed_everything 0 -> 1, data.init_args.measurement (input contents differ)"``: the
    fields in which two canonical configurations differ (at most ``limit`` named, then a count;
    the keys in ``ignore`` left out); empty when none does."""
    changes = [
        f"{key} (input contents differ)"
        if any(isinstance(v, str) and v.startswith(("file:", "folder:")) for v in (a, b))
        else f"{key} {a!r} -> {b!r}"
        for key, a, b in differing_keys(old, new, ignore)
    ]
    shown = ", ".join(changes[:limit])
    return shown + (f" and {len(changes) - limit} more" if len(changes) > limit else "")


def read_record(folder: str | Path) -> dict | None:
    """The run record of ``folder`` (``fingerprint.json``), or ``None`` if it has none or it is
    unreadable."""
    path = Path(folder) / RECORD
    try:
        record = json.loads(path.read_text())
    except (OSError, ValueError):
        return None
    return record if isinstance(record, dict) and "fingerprint" in record else None


def write_record(folder: str | Path, fp: Fingerprint, **status) -> Path:
    """Write ``folder/fingerprint.json`` atomically: the fingerprint, its configuration and
    ``status`` fields (``status="running"|"finished"``, ``run_id``, ``results``...)."""
    from fgat.io.files import atomic_path  # imported when used: keeps start-up fast

    folder = Path(folder)
    record = {"fingerprint": fp.digest, **status, "config": fp.config}
    try:
        folder.mkdir(parents=True, exist_ok=True)
        with atomic_path(folder / RECORD) as temporary:
            temporary.write_text(json.dumps(record, indent=1, default=str) + "\n")
    except OSError as error:
        raise ValueError(
            f"cannot write the run record {folder / RECORD}: {error.strerror or error}"
        ) from None
    return folder / RECORD


def run_folder(base: str | Path, fp: Fingerprint) -> tuple[Path, str | None]:
    """Where a run of ``fp`` goes: ``base`` when it is free or holds this fingerprint, else
    ``base-<fingerprint[:8]>``. Returns the folder and, when ``base`` holds another
    configuration, a sentence saying which fields differ."""
    base = Path(base)
    record = read_record(base)
    if record is None and not (base.is_dir() and any(base.iterdir())):
        return base, None
    if record is not None and record["fingerprint"] == fp.digest:
        return base, None
    other = (
        f"holds a run of another configuration "
        f"({differing_fields(record.get('config', {}), fp.config)})"
        if record is not None
        else "holds files of an earlier run without a fingerprint"
    )
    return base.with_name(f"{base.name}-{fp.short}"), f"{base} {other}"


def resume_checkpoint(folder: str | Path, fp: Fingerprint, finished: bool = True) -> Path | None:
    """``folder/checkpoints/last.ckpt`` when ``folder`` holds a run of ``fp`` that saved one (a
    killed or failed run of this configuration, resumed from there), else ``None``.

    ``finished``: whether a run that finished counts too. Resuming it runs no step and writes
    its results again (what a pipeline stage whose results are gone needs); a trial run again
    after it finished (``--refit``, or a tracking store that lacks its run) must fit afresh, or
    its new MLflow run would hold no history."""
    record = read_record(folder)
    checkpoint = Path(folder) / "checkpoints" / "last.ckpt"
    if record is None or record["fingerprint"] != fp.digest or not checkpoint.is_file():
        return None
    if not finished and record.get("status") == "finished":
        return None
    return checkpoint


LOCK = "fit.lock"
"""The lock file of a run folder held by the fit writing into it: ``<PID> <host>``."""


def _holder(path: Path) -> tuple[int, str] | None:
    """``(PID, host)`` written in a lock file; ``None`` if it is gone or unreadable."""
    try:
        pid, host = path.read_text().split()
        return int(pid), host
    except (OSError, ValueError):
        return None


def _dead(pid: int, host: str) -> bool:
    """Whether ``pid`` on ``host`` is known to be no longer running (only a process of this
    host can be asked)."""
    from fgat.io.files import process_alive  # imported when used: keeps start-up fast

    return host == socket.gethostname() and pid != os.getpid() and not process_alive(pid)


def lock_folder(folder: str | Path, field: str = "trainer.default_root_dir") -> tuple[Path, str]:
    """Take ``folder/fit.lock`` for this process, so two fits never write into one folder.

    The lock file is created whole (written under a temporary name, then hard-linked to its
    name, which fails when it exists). A lock whose holder is no longer running (a fit killed by
    SIGKILL never removes it) is taken over.

    Parameters
    ----------
    folder : str or Path
        The run folder (created if missing).
    field : str
        Its option, for the error line.

    Returns
    -------
    path : Path
        The lock file, for :func:`unlock_folder`.
    note : str
        Empty, or a sentence saying a stale lock was taken over.

    Raises
    ------
    ValueError
        The folder is held by a running process (or one of another host), naming it and its PID.
    """
    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    path = folder / LOCK
    mine = folder / f".{LOCK}.{os.getpid()}"
    mine.write_text(f"{os.getpid()} {socket.gethostname()}\n")
    note = ""
    try:
        for _ in range(3):  # another process may take a stale lock over at the same time
            try:
                os.link(mine, path)
                return path, note
            except FileExistsError:
                holder = _holder(path)
            if holder is not None and not _dead(*holder):
                where = "" if holder[1] == socket.gethostname() else f" on {holder[1]}"
                raise ValueError(
                    f"{field} {folder} is in use by another fit (PID {holder[0]}{where}, lock "
                    f"{path}); wait for it to end, or choose another folder"
                )
            if holder is not None:
                note = f"took over the lock {path} of PID {holder[0]}, which is no longer running"
                path.unlink(missing_ok=True)
        raise ValueError(f"{field} {folder}: cannot take the lock {path}; try again")
    finally:
        mine.unlink(missing_ok=True)


def unlock_folder(path: Path) -> None:
    """Remove a lock file taken by :func:`lock_folder`, if this process still holds it."""
    if _holder(path) == (os.getpid(), socket.gethostname()):
        path.unlink(missing_ok=True)


def process_fields() -> dict[str, object]:
    """``pid`` and ``host`` of this process, for a run record: a record still ``running`` whose
    process is dead (:func:`orphaned`) belongs to a fit that was killed."""
    return {"pid": os.getpid(), "host": socket.gethostname()}


def orphaned(record: dict | None) -> bool:
    """Whether a run record says ``running`` but its process (``pid`` on ``host``) is dead: a
    fit killed (SIGKILL, power loss) before it could say so."""
    if record is None or record.get("status") != "running":
        return False
    pid, host = record.get("pid"), record.get("host")
    return isinstance(pid, int) and isinstance(host, str) and _dead(pid, host)
