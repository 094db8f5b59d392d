"""Finding, checking and opening the ONNX model files shipped inside the skycap packages.

The models live beside the code that uses them (package data, installed with the project):

- ``onboard/detector/models/``        person detector (``nanodet.onnx``)
- ``reconstruction/keypoints/models/`` 2D keypoint models (``movenet_lightning.onnx``, ...)

Each folder holds ``SHA256SUMS.txt``; a file is checked against it before onnxruntime opens it, so a
truncated or corrupt file gives a clear :class:`ModelFileError` (naming the file and the command that
restores it) instead of a cryptic protobuf error or, worse, wrong outputs.

``SKYCAP_MODELS_DIR`` (environment) points to another folder to take model files from (for example a
folder of re-generated or fine-tuned models); a file there is checked against that folder's own
``SHA256SUMS.txt`` when it has one, else against the shipped manifest. Nothing is ever downloaded.
"""

from __future__ import annotations

import hashlib
import logging
import os
import threading
from dataclasses import dataclass
from pathlib import Path

from skycap.errors import SkycapError

log = logging.getLogger(__name__)

ENV_MODELS_DIR = "SKYCAP_MODELS_DIR"
MANIFEST = "SHA256SUMS.txt"
RESTORE_HINT = (
    "restore it from the project (in a checkout: `git checkout -- {rel}`; or reinstall skycap), "
    "or regenerate it with `bash scripts/make_models/make_models.sh --only {stem}`"
)

_verified: dict[tuple[str, int, int], str] = {}
_lock = threading.Lock()


class ModelFileError(SkycapError, FileNotFoundError):
    """A shipped model file is missing, corrupt or cannot be opened by onnxruntime."""


@dataclass(frozen=True)
class ThreadSettings:
    """onnxruntime threading: ``intra_op`` threads inside one operator, ``inter_op`` across operators.

    ``allow_spinning``: let idle worker threads busy-wait for the next operator (lower latency on
    dedicated cores, wasted CPU on a companion computer shared with the tracker and the link; off).
    """

    intra_op: int = 1
    inter_op: int = 1
    allow_spinning: bool = False


def _read_manifest(folder: Path) -> dict[str, str]:
    p = folder / MANIFEST
    if not p.is_file():
        return {}
    out = {}
    for line in p.read_text().splitlines():
        parts = line.split()
        if len(parts) == 2:
            out[parts[1].lstrip("*")] = parts[0].lower()
    return out


def sha256_file(path: Path) -> str:
    with open(path, "rb") as f:
        return hashlib.file_digest(f, "sha256").hexdigest()


def resolve_model(filename: str, package_dir: Path, rel_hint: str) -> Path:
    """Path of a verified model file.

    Args:
        filename: e.g. ``"nanodet.onnx"``.
        package_dir: the package's own ``models/`` folder (holds the shipped manifest).
        rel_hint: the file's path in a checkout, used in the error message.
    Raises:
        ModelFileError: missing file, or a sha256 that differs from the manifest.
    """
    stem = Path(filename).stem
    hint = RESTORE_HINT.format(rel=rel_hint, stem=stem)
    override = os.environ.get(ENV_MODELS_DIR)
    folder = Path(override) if override else package_dir
    path = folder / filename
    if not path.is_file():
        where = f" (from {ENV_MODELS_DIR}={override})" if override else ""
        raise ModelFileError(f"model file {path}{where} is missing; {hint}")
    expected = _read_manifest(folder).get(filename) or _read_manifest(package_dir).get(filename)
    if expected is None:
        raise ModelFileError(f"no sha256 for {filename} in {folder / MANIFEST} or {package_dir / MANIFEST}; {hint}")
    st = path.stat()
    key = (str(path.resolve()), st.st_size, st.st_mtime_ns)
    with _lock:
        if _verified.get(key) == expected:
            return path
    got = sha256_file(path)
    if got != expected:
        raise ModelFileError(
            f"model file {path} is corrupt or changed (sha256 {got[:16]}..., expected {expected[:16]}..., "
            f"{st.st_size} bytes); {hint}"
        )
    with _lock:
        _verified[key] = expected
    return path


def open_session(path: Path, threads: ThreadSettings, rel_hint: str):
    """An onnxruntime CPU session with explicit thread settings (sequential execution, all graph optimisations)."""
    import onnxruntime as ort

    so = ort.SessionOptions()
    so.intra_op_num_threads = int(threads.intra_op)
    so.inter_op_num_threads = int(threads.inter_op)
    so.execution_mode = ort.ExecutionMode.ORT_SEQUENTIAL
    so.graph_optimization_level = ort.GraphOptimizationLevel.ORT_ENABLE_ALL
    so.log_severity_level = 3
    so.add_session_config_entry("session.intra_op.allow_spinning", "1" if threads.allow_spinning else "0")
    so.add_session_config_entry("session.inter_op.allow_spinning", "1" if threads.allow_spinning else "0")
    try:
        return ort.InferenceSession(str(path), sess_options=so, providers=["CPUExecutionProvider"])
    except Exception as e:  # onnxruntime raises its own exception types
        stem = path.stem
        raise ModelFileError(
            f"onnxruntime cannot open model file {path}: {e}; "
            + RESTORE_HINT.format(rel=rel_hint, stem=stem)
        ) from e
