"""Monocular reconstruction from one orbiting drone: the DroCap pipeline (Zhou et al., ICRA 2018).

Modules: ``dictionary`` (pose dictionary, canonical body frame, sparse coding), ``tracks`` (2D track
cleaning), ``single_frame`` (convex-relaxation initialisation, Zhou et al. PAMI 2017), ``ba`` (multi-frame
bundle adjustment: nuclear norm + rank-1 articulation term, and the extensions), ``perspective`` (beyond
the paper: perspective BA in the world frame with the drone's camera poses, robust reprojection, metric
articulation, smoothness, low rank), ``pipeline`` (the stages together, world placement), ``reconstruct`` (a capture -> exported motion), ``evaluate`` / ``cli``
(``skycap eval monocular``, ``skycap eval monocular-sweep``, ``skycap reconstruct --method monocular``),
``orbit`` (the orthographic camera of the paper's synthetic test), ``linalg`` (proximal operators,
Stiefel-manifold steps). Results: ``results/RESULTS.md``.
"""
