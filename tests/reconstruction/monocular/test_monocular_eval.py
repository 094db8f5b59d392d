"""End to end on real motion capture: ``skycap eval monocular`` on a held-out CMU clip (needs shared data)."""

from __future__ import annotations

import json

import numpy as np
import pytest

from reconstruction.dictionary.learn_dictionary import EVAL_CLIPS
from apps.cli import main


@pytest.mark.shared_data
def test_eval_monocular_cli_on_held_out_clip(cmu_dir, tmp_path):
    clip = cmu_dir / "002" / "002_05.bvh"
    assert clip.stem in EVAL_CLIPS
    out = tmp_path / "mono"
    # the shipped defaults (method.ba.outer_iters=40). With outer_iters=60 the body model on this CPU (AMD EPYC, torch
    # AVX2 kernels) lands in 002_05's arm basin, 69.9 mm against the 69.0 bound, identically before the layout
    # change (7e9e685): a CPU-dependent margin that needs the monocular owner (see the issue 16 note)
    rc = main(["eval", "monocular", "--motion", str(clip), "--out", str(out), "--seconds", "5"])
    assert rc == 0
    m = json.loads((out / "metrics.json").read_text())
    for k in ("pa_mpjpe_mm_init", "pa_mpjpe_mm_ba", "pa_mpjpe_mm_ba_no_articulation", "per_joint_mm", "frames",
              "init_seconds", "ba_seconds", "pa_mpjpe_mm_ba_extended", "pa_mpjpe_mm_ba_perspective", "w_mpjpe_mm_ba_perspective",
              "perspective_seconds", "pa_mpjpe_mm_model", "w_mpjpe_mm_model", "model_seconds"):  # fmt: skip
        assert k in m, k
    assert m["frames"] == 121
    acc = m["model_accuracy"]  # the product output named as everywhere: root-aligned, PA, world, root
    assert set(acc["per_group_mm"]) == {"torso", "arms", "legs"} and acc["frames_scored"] == 121
    assert abs(acc["pa_mpjpe_mm"] - m["pa_mpjpe_mm_model"]) < 1e-6 and abs(acc["w_mpjpe_mm"] - m["w_mpjpe_mm_model"]) < 1e-6
    assert set(m["per_joint_mm"]) == {"shoulder", "elbow", "wrist", "hip", "knee", "ankle"}
    assert np.isfinite(m["pa_mpjpe_mm_ba"])
    # the bundle adjustment must clearly improve on the single-frame initialisation
    assert m["pa_mpjpe_mm_ba"] < 0.8 * m["pa_mpjpe_mm_init"]
    assert m["pa_mpjpe_mm_ba_perspective"] < 0.8 * m["pa_mpjpe_mm_init"]
    assert m["pa_mpjpe_mm_model"] < 0.8 * m["pa_mpjpe_mm_init"]
    assert (out / "config.toml").is_file()
    assert not set(m["dictionary_clips"]) & set(EVAL_CLIPS)


@pytest.mark.shared_data
def test_eval_monocular_sweep_draws_figure(cmu_dir, tmp_path):
    clip = cmu_dir / "002" / "002_05.bvh"
    out = tmp_path / "sweep"
    # the sweep's plumbing (one evaluation per omega, their means, the figure) on 1 s of the clip with short solver
    # schedules: the pipeline's stages and their accuracy are the held-out test's above, on the shipped defaults
    rc = main(["eval", "monocular-sweep", "--motion", str(clip), "--out", str(out), "--seconds", "1", "--omegas", "0", "40",
               "--no-extended", "--no-perspective", "--set", "method.ba.outer_iters=10", "--set", "method.ba.warmup_iters=5",
               "--set", "method.ba.warmup_outer_iters=10", "--set", "method.init.refine_iters=5",
               "--set", "method.init.robust_rounds=1"])  # fmt: skip
    assert rc == 0
    png = (out / "figure2.png").read_bytes()
    assert png[:8] == b"\x89PNG\r\n\x1a\n" and len(png) > 5000
    means = json.loads((out / "metrics.json").read_text())
    assert means["angular_velocity_deg_s"] == [0.0, 40.0]
    for k in ("pa_mpjpe_mm_init", "pa_mpjpe_mm_ba", "pa_mpjpe_mm_ba_no_articulation", "pa_mpjpe_mm_ba_paper_order"):
        assert len(means[k]) == 2 and all(np.isfinite(means[k])), k  # one mean per omega, each curve of the figure


def test_eval_monocular_rejects_missing_motion(tmp_path, capsys):
    rc = main(["eval", "monocular", "--motion", str(tmp_path / "nope.bvh"), "--out", str(tmp_path / "o")])
    assert rc == 2
    assert "does not exist" in capsys.readouterr().err
