"""Initial-guess cleaning of triangulated joint tracks (pure numpy)."""

from __future__ import annotations

import numpy as np

from reconstruction.multiview.observations import fill_gaps, median_in_time, reject_blunders
from reconstruction.synth import procedural_walker


def test_reject_blunders_at_clip_end_with_missing_tail():
    X, *_ = procedural_walker(num_frames=30)
    Xr = X.copy()
    Xr[-3, 12] += [0.0, 0.8, -0.3]  # a two-view blunder three frames before the end ...
    Xr[-2:, 12] = np.nan  # ... then too few views: fill_gaps alone would copy the blunder to the end
    Xr[10, 5] += [0.5, 0.0, 0.0]  # and one mid-clip
    naive = median_in_time(fill_gaps(Xr))
    clean = reject_blunders(Xr)
    assert np.isnan(clean[-3, 12]).all() and np.isnan(clean[10, 5]).all()
    assert np.isfinite(clean).sum() == np.isfinite(Xr).sum() - 6  # nothing else removed
    fixed = median_in_time(fill_gaps(clean))
    assert np.linalg.norm(naive[-1, 12] - X[-1, 12]) > 0.5
    assert np.linalg.norm(fixed - X, axis=-1).max() < 0.15  # the 3-frame tail is held (walker: 4 cm per frame)
