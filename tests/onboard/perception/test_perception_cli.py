"""``skycap detect`` and ``skycap keypoints`` end to end (real models, in-process CLI)."""

from __future__ import annotations

import json

import cv2
import numpy as np
import pytest

from apps.cli import main


@pytest.fixture(scope="module")
def plaza_png(tmp_path_factory, aerial_dir):
    img = cv2.imread(str(aerial_dir / "general_example.png"))
    path = tmp_path_factory.mktemp("cli") / "plaza.png"
    cv2.imwrite(str(path), img[200:700, 450:950])  # 500x500: the group of pedestrians
    return path


def test_detect_json_and_png(plaza_png, tmp_path, capsys) -> None:
    out_png = tmp_path / "boxes.png"
    assert main(["detect", str(plaza_png), "--mode", "tiles", "--json", "--png", str(out_png)]) == 0
    data = json.loads(capsys.readouterr().out)
    assert data["mode"] == "tiles" and data["width_px"] == 500 and data["detector"] == "nanodet"
    assert len(data["detections"]) >= 8
    d = data["detections"][0]
    assert set(d) >= {"x_min_px", "y_min_px", "x_max_px", "y_max_px", "score", "var_x_min_px2", "var_y_max_px2"}
    png = cv2.imread(str(out_png))
    assert png is not None and png.shape == (500, 500, 3)


def test_detect_roi_table_output(plaza_png, capsys) -> None:
    assert main(["detect", str(plaza_png), "--roi", "100,20,320,320", "--threads", "2"]) == 0
    out = capsys.readouterr().out
    assert "(roi, 1 inferences" in out and "score=" in out


def test_detect_errors_are_one_line(plaza_png, tmp_path, capsys) -> None:
    assert main(["detect", str(plaza_png), "--roi", "1,2,3"]) == 2
    assert "x,y,w,h" in capsys.readouterr().err
    assert main(["detect", str(tmp_path / "nope.png")]) == 2
    assert "does not exist" in capsys.readouterr().err
    assert main(["detect", str(plaza_png), "--mode", "roi"]) == 2
    assert "--roi" in capsys.readouterr().err


def test_keypoints_json_and_png(grace_hopper, tmp_path, capsys) -> None:
    img = tmp_path / "gh.png"
    cv2.imwrite(str(img), grace_hopper)
    out_png = tmp_path / "kp.png"
    args = ["keypoints", str(img), "--box", "20,30,492,570", "--model", "movenet_lightning", "--model", "blazepose_full"]
    assert main([*args, "--json", "--png", str(out_png)]) == 0
    data = json.loads(capsys.readouterr().out)
    assert set(data["models"]) == {"movenet_lightning", "blazepose_full"}
    nose = data["models"]["movenet_lightning"]["keypoints"]["nose"]
    assert abs(nose["x_px"] - 265) < 30 and abs(nose["y_px"] - 237) < 30
    assert cv2.imread(str(out_png)).shape == grace_hopper.shape


def test_keypoints_without_box_uses_the_detector(grace_hopper, tmp_path, capsys) -> None:
    img = tmp_path / "gh.png"
    cv2.imwrite(str(img), grace_hopper)
    assert main(["keypoints", str(img), "--model", "movenet_thunder"]) == 0
    out = capsys.readouterr().out
    assert "left_shoulder" in out and "movenet_thunder" in out


def test_keypoints_without_a_person_says_so(tmp_path, capsys) -> None:
    img = tmp_path / "grey.png"
    cv2.imwrite(str(img), np.full((200, 200, 3), 128, np.uint8))
    assert main(["keypoints", str(img)]) == 2
    assert "no person found" in capsys.readouterr().err
