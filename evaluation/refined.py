"""The offline smoother's effect on the reconstruction: the multiview fit with the refined drone positions, scored
beside the fit with the reported ones against the simulator's truth (``skycap refine --reconstruct``)."""

from __future__ import annotations

import json
import logging

from evaluation.flight import reconstruction_accuracy
from flightdata.folder import FlightFolder
from reconstruction.api import reconstruct_flight
from reconstruction.multiview.run import MultiviewConfig

log = logging.getLogger(__name__)

__all__ = ["reconstruct_with_refined_poses"]


def reconstruct_with_refined_poses(flight, sortie: int | None = None) -> dict:
    """Multiview reconstruction with the refined drone positions into ``reconstruction_refined/``; MPJPE of it
    and of the plain ``reconstruction/`` (when present) against the simulator truth; added to
    ``refined_track.json`` under ``reconstruction``. Logs the reconstruction's summary."""
    flight = flight if isinstance(flight, FlightFolder) else FlightFolder(flight)
    out = flight.refined_reconstruction_dir
    result = reconstruct_flight(flight, "multiview", MultiviewConfig(use_refined_poses=True), sortie=sortie, out_dir=out)
    log.info("reconstruction with the refined poses: %s", json.dumps(result.summary))
    js = flight.refined_json_path
    summary = json.loads(js.read_text()) if js.is_file() else {}
    window = summary.get("evaluation", {}).get("fleet", {}).get("window_s")
    res = {"refined_poses": reconstruction_accuracy(flight.path, out / "motion.npz", window_s=window)}
    plain = flight.reconstruction_dir("multiview") / "motion.npz"
    if plain.is_file():
        res["reported_poses"] = reconstruction_accuracy(flight.path, plain, window_s=window)
    res = {k: {kk: vv for kk, vv in v.items() if not kk.startswith("per_group")} for k, v in res.items()}
    if js.is_file():
        summary["reconstruction"] = res
        js.write_text(json.dumps(summary, indent=2))
    return res
