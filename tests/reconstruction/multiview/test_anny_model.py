"""The optional Anny body model behind the same BodyModel interface.

Anny's first start takes ~75-140 s on this 2-core machine and writes a ~790 MB cache
(``$ANNY_CACHE_DIR``, else the repository's gitignored ``.cache/anny``); the session fixture builds it once
when absent (a clean CI clone pays that once) and later runs start in seconds. Set SKYCAP_SKIP_ANNY=1 to
skip these tests on a machine without the disk space.
"""

from __future__ import annotations

import os
from pathlib import Path

import pytest
import torch
from tests.helpers.paths import REPO

CACHE = Path(os.environ.get("ANNY_CACHE_DIR", REPO / ".cache" / "anny"))


@pytest.fixture(scope="session")
def anny_model():
    pytest.importorskip("anny")
    if os.environ.get("SKYCAP_SKIP_ANNY"):
        pytest.skip("SKYCAP_SKIP_ANNY is set")
    CACHE.mkdir(parents=True, exist_ok=True)  # first use builds the cache (slow once)
    from reconstruction.body.model import AnnyBodyModel

    return AnnyBodyModel(cache_dir=CACHE)


def test_anny_forward_and_gradients(anny_model):
    m = anny_model
    B = 2
    pose = torch.zeros(B, m.num_pose, 3, dtype=torch.float64, requires_grad=True)
    ro = torch.zeros(B, 3, dtype=torch.float64, requires_grad=True)
    tr = torch.tensor([[0.0, 0.0, 0.0], [1.0, 2.0, 3.0]], dtype=torch.float64)
    shape = torch.full((B, m.num_shape), 0.5, dtype=torch.float64, requires_grad=True)
    J = m(ro, pose, tr, shape)
    assert J.shape == (B, 17, 3)
    # body frame: y up (nose above ankles), x = left (left shoulder at +x), translation applied
    assert J[0, 0, 1] > J[0, 15, 1] + 1.0 and J[0, 5, 0] > J[0, 6, 0]
    torch.testing.assert_close(J[1] - J[0], tr[1].expand(17, 3))
    J[:, 9].sum().backward()  # left wrist
    assert torch.isfinite(pose.grad).all() and pose.grad.abs().sum() > 0 and shape.grad.abs().sum() > 0
