"""Bake the Anny body meshes the simulator renders (:mod:`simulator.scene.anny_body`) into a small npz,
so that the simulator needs neither torch nor the ``anny`` package at run time.

    ANNY_CACHE_DIR=.cache/anny python -m simulator.scene.anny_bake [--shapes 12] [--seed 0]

What it writes (``simulator/data/anny_bodies.npz``, ~0.3 MB):

* ``faces`` (F, 3) triangles of Anny's decimated ``notoes_collapse10pc`` topology (1229 vertices,
  2454 triangles) shipped with the package;
* ``rest_vertices`` (K, V, 3) and ``rest_bone_heads`` (K, B, 3): the rest (identity-pose) mesh and bone
  heads of K adult phenotypes drawn uniformly (``phenotypes`` (K, 6), labels ``phenotype_labels``), in
  Anny's frame (x = left, y = back, z = up, metres);
* ``vertex_bone_indices`` / ``vertex_bone_weights`` (V, N): Anny's own skinning weights;
  ``bone_labels``, ``bone_parents``.

Licence: Anny (NAVER Corp.) code Apache-2.0, assets CC0-1.0; the baked file is derived from the CC0 assets
only and is CC0-1.0 as well. Anny's SMPL interop (non-commercial data) is never used. The first Anny start
compiles kernels and builds the model (minutes on a loaded 2-core machine).
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np

OUT = Path(__file__).resolve().parents[1] / "data" / "anny_bodies.npz"
TOPOLOGY = "notoes_collapse10pc"


def bake(shapes: int, seed: int) -> dict[str, np.ndarray]:
    import torch

    import anny

    model = anny.Anny(topology=TOPOLOGY)
    labels = list(model.phenotype_labels)
    rng = np.random.default_rng(seed)
    ph = rng.uniform(0.0, 1.0, (shapes, len(labels)))
    ph[:, labels.index("age")] = rng.uniform(0.55, 0.95, shapes)  # adults
    ph[:, labels.index("gender")] = np.linspace(0.0, 1.0, shapes)  # women to men, evenly
    ph[:, labels.index("weight")] = rng.uniform(0.2, 0.8, shapes)
    with torch.no_grad():
        pose = torch.eye(4, dtype=model.dtype)[None, None].expand(shapes, model.bone_count, 4, 4).clone()
        o = model(pose_parameters=pose, phenotype_kwargs=torch.tensor(ph, dtype=model.dtype))
    return dict(
        faces=model.faces.cpu().numpy().astype(np.int32),
        rest_vertices=o["rest_vertices"].cpu().numpy().astype(np.float32),
        rest_bone_heads=o["rest_bone_heads"].cpu().numpy().astype(np.float32),
        vertex_bone_indices=model.vertex_bone_indices.cpu().numpy().astype(np.int16),
        vertex_bone_weights=model.vertex_bone_weights.cpu().numpy().astype(np.float32),
        bone_labels=np.array(model.bone_labels),
        bone_parents=np.array(model.bone_parents, dtype=np.int16),
        phenotypes=ph.astype(np.float32),
        phenotype_labels=np.array(labels),
        topology=np.array(TOPOLOGY),
        anny_version=np.array(anny.__version__),
        licence=np.array("CC0-1.0, derived from Anny (NAVER Corp.) assets, CC0-1.0; made by simulator/scene/anny_bake.py"),
    )


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--shapes", type=int, default=12)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--out", type=Path, default=OUT)
    a = ap.parse_args(argv)
    d = bake(a.shapes, a.seed)
    a.out.parent.mkdir(parents=True, exist_ok=True)
    np.savez_compressed(a.out, **d)
    for k, v in d.items():
        print(k, v.shape, v.dtype)
    print(f"wrote {a.out} ({a.out.stat().st_size / 1e3:.0f} kB)")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
