"""Benchmark / diagnostic: which cause carries how much of a simulated flight's multiview error
(:mod:`evaluation.ablation`): the flight refitted with the recorded poses, true positions, true attitude (all, tilt
only, pan only), true poses, and true poses with exact 2D; plus optional fit variants.

    python bench/bench_ablation.py FLIGHT_DIR [--rows recorded,true_pose] [--variant 'fine:cam_knot_s=0.25'] [--json out.json]

Fly the flight first, e.g. ``skycap demo --drones 3 --duration 40 --out flights/abl --set reconstruct_keypoints='"sim"'``.
Prints the machine line (load matters: the fits take 10-120 s each) and the table of ``format_ablation``.
"""

from __future__ import annotations

import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))

from _machine import describe_machine  # noqa: E402

from evaluation.ablation import main  # noqa: E402

if __name__ == "__main__":
    print(describe_machine())
    rc = main(sys.argv[1:])
    print(describe_machine("after"))
    raise SystemExit(rc)
