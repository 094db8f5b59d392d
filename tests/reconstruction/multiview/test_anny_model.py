"""The optional Anny body model behind the same BodyModel interface.

Anny's first start takes ~75-200 s on a 2-core machine and writes a ~600-790 MB cache
(``$ANNY_CACHE_DIR``, else Anny's own per-user cache ``~/.cache/anny``: versioned and keyed by content hashes, so
one build serves every checkout and every later CI run on the machine -- a cache inside the clone was rebuilt by
each clean CI clone); the session fixture builds it once when absent and later runs start in seconds. Set
SKYCAP_SKIP_ANNY=1 to skip these tests on a machine without the disk space.
"""

from __future__ import annotations

import os
from pathlib import Path

import pytest
import torch

CACHE = Path(os.environ.get("ANNY_CACHE_DIR", Path.home() / ".cache" / "anny"))


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
