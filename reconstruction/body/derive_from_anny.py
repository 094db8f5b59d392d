"""Derive the COCO-17 skeleton's shape prior (mean and covariance of the 16 shape numbers) from the Anny
body model: sample Anny phenotypes (adult ages), regress Anny's COCO keypoints on its rest mesh, measure
the skeleton's shape on them (:func:`reconstruction.body.skeleton17.estimate_shape`).

    ANNY_CACHE_DIR=.cache/anny python -m reconstruction.body.derive_from_anny

Writes ``reconstruction/body/data/skeleton17_anny_shape.npz`` (a few kB). Licence: derived from Anny's
assets (CC0 1.0, Anny code Apache-2.0, NAVER Corp.); this derived file is CC0 as well. Anny's SMPL
interop (non-commercial data) is never used. Needs the ``anny`` package (first start ~75 s).
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np

from reconstruction.body.skeleton17 import estimate_shape

OUT = Path(__file__).with_name("data") / "skeleton17_anny_shape.npz"


def anny_rest_coco17(n: int, seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """(phenotypes (n, 6), rest COCO-17 keypoints (n, 17, 3) in the body frame x=left, y=up, z=forward)."""
    import torch

    import anny

    model = anny.Anny()
    reg = anny.KeypointsRegressor.coco(model)
    rng = np.random.default_rng(seed)
    P = len(model.phenotype_labels)
    ph = rng.uniform(0.0, 1.0, (n, P))
    ages = model.phenotype_labels.index("age")
    ph[:, ages] = rng.uniform(0.5, 1.0, n)  # adults
    out = []
    with torch.no_grad():
        for i in range(0, n, 16):
            b = ph[i : i + 16]
            pose = torch.eye(4, dtype=model.dtype)[None, None].expand(len(b), model.bone_count, 4, 4).clone()
            o = model(pose_parameters=pose, phenotype_kwargs=torch.tensor(b, dtype=model.dtype))
            kp = reg(o)[:, :17].numpy()  # Anny frame: x = left, y = back, z = up
            out.append(np.stack([kp[..., 0], kp[..., 2], -kp[..., 1]], -1))
    return ph, np.concatenate(out)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--samples", type=int, default=256)
    ap.add_argument("--out", type=Path, default=OUT)
    a = ap.parse_args(argv)
    ph, kp = anny_rest_coco17(a.samples)
    S = np.stack([estimate_shape(k[None]) for k in kp])
    mean, cov = S.mean(0), np.cov(S.T)
    a.out.parent.mkdir(parents=True, exist_ok=True)
    np.savez_compressed(a.out, mean=mean, cov=cov, samples=S, phenotypes=ph,
                        licence=np.array("CC0-1.0, derived from Anny (NAVER Corp.) assets, CC0-1.0"))  # fmt: skip
    print("mean", np.round(mean, 3))
    print("std ", np.round(np.sqrt(np.diag(cov)), 3))
    print(f"wrote {a.out}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
