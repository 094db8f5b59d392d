"""A stand-in for the processing pipeline with its shape (``fn(flight_dir, cfg, *, progress, cancel)``, the steps
boxes -> keypoints -> fit -> export, a plain-data result like ``process_summary``), run by a real jobs runner in
the ground station's job tests. ``cfg``: a list of ``key=value`` strings (``fail=1``, ``step_s=0.2``)."""

from __future__ import annotations

import json
import time
from pathlib import Path


class _Event:
    def __init__(self, step, fraction, eta_s, message):
        self.step, self.fraction, self.eta_s, self.message = step, fraction, eta_s, message


def run(flight_dir: Path, cfg, *, progress=None, cancel=None) -> dict:
    opts = dict(o.split("=", 1) for o in (cfg or []))
    step_s = float(opts.get("step_s", "0.05"))
    for step in ("boxes", "keypoints", "fit", "export"):
        for i in range(4):
            if cancel is not None and cancel.is_set():
                raise RuntimeError(f"cancelled in {step}")
            if progress is not None:
                progress(_Event(step, i / 4, step_s * (4 - i), f"{step} {i}/4"))
            time.sleep(step_s)
            if step == "fit" and opts.get("fail") == "1":
                raise ValueError("the fit diverged (a test failure)")
    out = Path(flight_dir) / "reconstruction" / "multiview"
    out.mkdir(parents=True, exist_ok=True)
    (out / "motion.bvh").write_text("HIERARCHY\n")
    summary = {"method": "multiview", "frames": 7, "cameras": 2, "keypoints_source": "fake"}
    (out / "summary.json").write_text(json.dumps(summary))
    return {"method": "multiview", "summary": summary, "out_dir": str(out), "outputs": {"bvh": str(out / "motion.bvh")}}
