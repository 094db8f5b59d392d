"""The shipped model files: present, matching their sha256 manifests, and clear errors when they are not."""

from __future__ import annotations

import shutil
import subprocess
import sys
from pathlib import Path

import pytest

from onboard.detector import detector as det_mod
from onboard.detector.modelfile import MANIFEST, ModelFileError, resolve_model, sha256_file
from reconstruction.keypoints import detectors as kp_mod
from tests.helpers.paths import REPO



def _manifest(folder: Path) -> dict[str, str]:
    return {line.split()[1]: line.split()[0] for line in (folder / MANIFEST).read_text().splitlines() if line.strip()}


@pytest.mark.parametrize("folder", [det_mod.MODELS_DIR, kp_mod.MODELS_DIR])
def test_manifest_lists_every_shipped_model_with_its_sha256(folder: Path) -> None:
    files = sorted(p.name for p in folder.glob("*.onnx"))
    man = _manifest(folder)
    assert files and sorted(man) == files
    for name, digest in man.items():
        assert sha256_file(folder / name) == digest, name
    # modest size: the repository travels
    assert sum((folder / n).stat().st_size for n in files) < 40e6


def test_expected_models_are_shipped() -> None:
    assert (det_mod.MODELS_DIR / "nanodet.onnx").is_file()
    for name in (*kp_mod.KEYPOINT_MODELS, "blazepose_detector"):
        assert (kp_mod.MODELS_DIR / f"{name}.onnx").is_file(), name


def test_missing_model_names_the_file_and_the_restore_command(tmp_path, monkeypatch) -> None:
    monkeypatch.setenv("SKYCAP_MODELS_DIR", str(tmp_path))
    with pytest.raises(ModelFileError) as e:
        det_mod.PersonDetector()
    msg = str(e.value)
    assert str(tmp_path / "nanodet.onnx") in msg and "missing" in msg
    assert "git checkout -- onboard/detector/models/nanodet.onnx" in msg
    assert "scripts/make_models/make_models.sh --only nanodet" in msg


def test_corrupt_model_is_refused_before_onnxruntime_sees_it(tmp_path, monkeypatch) -> None:
    src = kp_mod.MODELS_DIR / "movenet_lightning.onnx"
    bad = tmp_path / src.name
    data = bytearray(src.read_bytes())
    data[len(data) // 2] ^= 0xFF  # one flipped byte in the weights
    bad.write_bytes(bytes(data))
    shutil.copyfile(kp_mod.MODELS_DIR / MANIFEST, tmp_path / MANIFEST)
    monkeypatch.setenv("SKYCAP_MODELS_DIR", str(tmp_path))
    with pytest.raises(ModelFileError) as e:
        kp_mod.load_model("movenet_lightning")
    msg = str(e.value)
    assert str(bad) in msg and "corrupt" in msg
    assert "make_models.sh --only movenet_lightning" in msg


def test_truncated_model_without_local_manifest_is_checked_against_the_shipped_one(tmp_path, monkeypatch) -> None:
    src = det_mod.MODELS_DIR / "nanodet.onnx"
    (tmp_path / src.name).write_bytes(src.read_bytes()[:1000])
    monkeypatch.setenv("SKYCAP_MODELS_DIR", str(tmp_path))
    with pytest.raises(ModelFileError, match="corrupt"):
        resolve_model("nanodet.onnx", det_mod.MODELS_DIR, "onboard/detector/models/nanodet.onnx")


def test_unreadable_model_with_matching_manifest_gives_onnxruntime_error_naming_file(tmp_path, monkeypatch) -> None:
    bad = tmp_path / "nanodet.onnx"
    bad.write_bytes(b"not an onnx model" * 10)
    (tmp_path / MANIFEST).write_text(f"{sha256_file(bad)}  nanodet.onnx\n")
    monkeypatch.setenv("SKYCAP_MODELS_DIR", str(tmp_path))
    with pytest.raises(ModelFileError, match="onnxruntime cannot open model file .*nanodet.onnx"):
        det_mod.PersonDetector()


def test_cli_reports_a_corrupt_model_in_one_line(tmp_path) -> None:
    src = det_mod.MODELS_DIR / "nanodet.onnx"
    data = bytearray(src.read_bytes())
    data[-100] ^= 0x01
    (tmp_path / "nanodet.onnx").write_bytes(bytes(data))
    img = tmp_path / "img.png"
    import cv2
    import numpy as np

    cv2.imwrite(str(img), np.zeros((64, 64, 3), np.uint8))
    env = {**__import__("os").environ, "SKYCAP_MODELS_DIR": str(tmp_path)}
    res = subprocess.run(
        [sys.executable, "-m", "apps.cli", "detect", str(img), "--mode", "full"],
        capture_output=True,
        text=True,
        env=env,
        cwd=REPO,
        timeout=120,
    )
    assert res.returncode == 2
    assert "nanodet.onnx" in res.stderr and "corrupt" in res.stderr and "make_models.sh" in res.stderr
    assert "Traceback" not in res.stderr
