"""The step cache of ``skycap process`` in the flight folder (``processing/<step>/``, via
:meth:`flightdata.folder.FlightFolder.processing_step_dir`).

Every entry is named by a key: a short hash of what it was computed from (the recordings' identity, the earlier
steps' keys, the step's settings), so a changed setting or recording is recomputed and an unchanged one is read
back. Writes are atomic (a temporary file in the same folder, then ``os.replace``): a crash or a cancel leaves
either the whole entry or none; the temporary file a killed writer leaves (``.<name>.<pid>.tmp``, its process gone)
is removed when that entry is written next. The recordings themselves are only read.
"""

from __future__ import annotations

import glob
import hashlib
import io
import json
import os
import shutil
from pathlib import Path
from typing import Any

import numpy as np

__all__ = ["atomic_write_bytes", "atomic_write_json", "atomic_write_npz", "file_identity", "make_key", "read_npz",
           "remove_stale_temporaries"]


def make_key(*parts: Any) -> str:
    """A 16-hex-digit key of JSON-able ``parts`` (dataclasses as dicts, paths as strings)."""
    blob = json.dumps(parts, sort_keys=True, default=_default, separators=(",", ":"))
    return hashlib.sha256(blob.encode()).hexdigest()[:16]


def _default(o: Any) -> Any:
    import dataclasses

    if dataclasses.is_dataclass(o):
        return dataclasses.asdict(o)
    if isinstance(o, Path):
        return str(o)
    if isinstance(o, (np.integer, np.floating)):
        return o.item()
    if isinstance(o, (set, frozenset, tuple)):
        return list(o)
    raise TypeError(f"cannot key {type(o).__name__}")


def file_identity(path: str | Path, probe_bytes: int = 1 << 16) -> list:
    """What identifies a recording cheaply: its name, size and a hash of its first and last ``probe_bytes``
    (a copied flight keeps its keys; a changed file gets new ones)."""
    p = Path(path)
    size = p.stat().st_size
    h = hashlib.sha256()
    with open(p, "rb") as f:
        h.update(f.read(probe_bytes))
        if size > probe_bytes:
            f.seek(max(probe_bytes, size - probe_bytes))
            h.update(f.read(probe_bytes))
    return [p.name, size, h.hexdigest()[:16]]


def atomic_write_bytes(path: str | Path, data: bytes) -> Path:
    """Write ``data`` to ``path`` whole or not at all (temporary file beside it, fsync, rename)."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    remove_stale_temporaries(path)
    tmp = path.with_name(f".{path.name}.{os.getpid()}.tmp")
    try:
        with open(tmp, "wb") as f:
            f.write(data)
            f.flush()
            os.fsync(f.fileno())
        os.replace(tmp, path)
    except BaseException:
        tmp.unlink(missing_ok=True)
        raise
    return path


def remove_stale_temporaries(path: str | Path) -> list[Path]:
    """Remove the temporary files of ``path`` left by a writer that was killed (SIGKILL, power loss) before its
    rename: ``.<name>.<pid>.tmp`` whose process is gone. A live writer's (another job on the same flight) stays.
    Returns what was removed."""
    path = Path(path)
    removed = []
    for tmp in path.parent.glob(f".{glob.escape(path.name)}.*.tmp"):
        pid = tmp.name[len(path.name) + 2 : -4]
        if not pid.isdigit() or (int(pid) != os.getpid() and _alive(int(pid))):
            continue
        try:
            tmp.unlink()
            removed.append(tmp)
        except FileNotFoundError:
            pass
    return removed


def _alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:  # another user's process
        return True
    return True


def atomic_write_npz(path: str | Path, **arrays: Any) -> Path:
    """``np.savez_compressed`` of ``arrays`` to ``path``, atomically."""
    buf = io.BytesIO()
    np.savez_compressed(buf, **{k: np.asarray(v) for k, v in arrays.items()})
    return atomic_write_bytes(path, buf.getvalue())


def atomic_write_json(path: str | Path, obj: Any) -> Path:
    return atomic_write_bytes(path, json.dumps(obj, indent=2, default=_json_default).encode())


def _json_default(o: Any) -> Any:
    if isinstance(o, (np.integer, np.floating)):
        return o.item()
    if isinstance(o, np.ndarray):
        return o.tolist()
    if isinstance(o, Path):
        return str(o)
    raise TypeError(type(o).__name__)


def read_npz(path: str | Path) -> dict[str, np.ndarray] | None:
    """The arrays of a cache entry, or None when it is absent or unreadable (then it is recomputed)."""
    p = Path(path)
    if not p.is_file():
        return None
    try:
        with np.load(p, allow_pickle=False) as z:
            return {k: z[k] for k in z.files}
    except Exception:  # a damaged entry (it cannot be partial: writes are atomic) is recomputed
        return None


def remove_tree(path: str | Path) -> None:
    shutil.rmtree(path, ignore_errors=True)
