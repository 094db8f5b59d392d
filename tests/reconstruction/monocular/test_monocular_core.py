"""Monocular (DroCap) core: proximal operators, rank-1 update, Stiefel steps, initialisation, bundle adjustment."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from reconstruction.monocular.ba import (
    BAConfig,
    _Problem,
    bundle_adjust,
    limb_index_arrays,
    prior_limb_proportions,
    proportion_inconsistency,
    rank1_fixed_proportions,
    squared_limb_lengths,
)
from reconstruction.monocular.dictionary import (
    DEFAULT_DICTIONARY,
    PoseDictionary,
    canonicalize_poses,
    load_dictionary,
)
from reconstruction.monocular.linalg import (
    polar_2x3,
    project_l1_ball,
    prox_spectral_2x3,
    rank1_approx,
    stiefel_mm_step,
    svt,
)
from reconstruction.monocular.single_frame import InitConfig, initialise
from reconstruction.monocular.tracks import temporal_outlier_mask
from skycap.skeleton import COCO17_LIMBS


@pytest.fixture(scope="module")
def dictionary() -> PoseDictionary:
    return load_dictionary()


# ---------------------------------------------------------------- proximal operators (hand-computed)


def test_svt_diagonal_hand_computed():
    X = np.array([[3.0, 0.0, 0.0], [0.0, 1.0, 0.0]])
    Y, nn = svt(X, 0.5)
    np.testing.assert_allclose(Y, [[2.5, 0, 0], [0, 0.5, 0]], atol=1e-12)
    assert nn == pytest.approx(3.0)
    Y, nn = svt(X, 2.0)  # the small singular value is killed
    np.testing.assert_allclose(Y, [[1.0, 0, 0], [0, 0, 0]], atol=1e-12)
    assert nn == pytest.approx(1.0)
    Y, nn = svt(X, 5.0)
    np.testing.assert_allclose(Y, 0.0, atol=1e-12)
    assert nn == 0.0


def test_svt_rotated_hand_computed():
    # X = U diag(4, 2) V^T with 45-degree rotations; SVT(1) = U diag(3, 1) V^T
    c = np.sqrt(0.5)
    U = np.array([[c, -c], [c, c]])
    V = np.array([[1.0, 0.0], [0.0, 1.0]])
    X = U @ np.diag([4.0, 2.0]) @ V.T
    Y, nn = svt(X, 1.0)
    np.testing.assert_allclose(Y, U @ np.diag([3.0, 1.0]) @ V.T, atol=1e-12)
    np.testing.assert_allclose(Y, [[3 * c, -c], [3 * c, c]], atol=1e-12)
    assert nn == pytest.approx(4.0)


def test_ba_proximal_step_is_svt_of_stacked_poses():
    # Two frames, one joint: S# = [[2, 0], [0, 0], [0, 0]] (3 x 2): threshold alpha * step = 0.5
    T = 2
    W = np.zeros((T, 2, 1))
    prob = _Problem(W, np.ones((T, 1)), [], BAConfig(alpha=0.5 / np.sqrt(T)), None)
    X = np.zeros((T, 3, 1))
    X[0, 0, 0] = 2.0
    Y, nn = prob.prox(X, 1.0)
    assert Y[0, 0, 0] == pytest.approx(1.5)
    assert np.count_nonzero(np.abs(Y) > 1e-12) == 1
    assert nn == pytest.approx(1.5)


def test_project_l1_ball_hand_computed():
    np.testing.assert_allclose(project_l1_ball(np.array([3.0, 1.0]), 1.0), [1.0, 0.0])
    np.testing.assert_allclose(project_l1_ball(np.array([3.0, 1.0]), 3.0), [2.5, 0.5])
    np.testing.assert_allclose(project_l1_ball(np.array([0.5, -0.25]), 1.0), [0.5, -0.25])  # inside
    np.testing.assert_allclose(project_l1_ball(np.array([-2.0, 2.0]), 2.0), [-1.0, 1.0])


def test_prox_spectral_hand_computed():
    M = np.array([[3.0, 0.0, 0.0], [0.0, 1.0, 0.0]])
    # singular values (3, 1); minus their projection on the l1 ball of radius tau
    np.testing.assert_allclose(prox_spectral_2x3(M, 1.0), [[2, 0, 0], [0, 1, 0]], atol=1e-12)
    np.testing.assert_allclose(prox_spectral_2x3(M, 3.0), [[0.5, 0, 0], [0, 0.5, 0]], atol=1e-12)
    np.testing.assert_allclose(prox_spectral_2x3(M, 4.0), 0.0, atol=1e-12)


def test_prox_spectral_minimises_its_objective():
    rng = np.random.default_rng(1)
    M = rng.normal(size=(50, 2, 3))
    tau = 0.7
    Y = prox_spectral_2x3(M, tau)

    def obj(Z):
        return 0.5 * np.sum((Z - M) ** 2, axis=(-1, -2)) + tau * np.linalg.norm(Z, ord=2, axis=(-2, -1))

    base = obj(Y)
    for _ in range(20):
        assert np.all(obj(Y + 1e-3 * rng.normal(size=Y.shape)) >= base - 1e-12)


# ---------------------------------------------------------------- rank-1 update, Stiefel


def test_rank1_update_hand_computed_and_exact_for_scaled_skeleton():
    X = np.array([[3.0, 0.0], [0.0, 1.0]])
    np.testing.assert_allclose(rank1_approx(X), [[3.0, 0.0], [0.0, 0.0]], atol=1e-12)
    X = np.outer([1.0, 2.0], [1.0, 1.0, 2.0])
    np.testing.assert_allclose(rank1_approx(X), X, atol=1e-12)
    # a skeleton whose size changes over time: l(S) is rank 1, so L = l(S) (articulation term is 0)
    rng = np.random.default_rng(0)
    S0 = rng.normal(size=(3, 17))
    scales = np.linspace(0.5, 2.0, 7)
    Rs = Rotation.random(7, random_state=1).as_matrix()
    S = np.stack([s * R @ S0 for s, R in zip(scales, Rs)])
    a = np.array([l[0] for l in COCO17_LIMBS])
    b = np.array([l[1] for l in COCO17_LIMBS])
    ell = squared_limb_lengths(S, a, b)
    np.testing.assert_allclose(rank1_approx(ell), ell, rtol=1e-10, atol=1e-12)
    # with noise, it is the SVD truncation (Eckart-Young): residual = the other singular values
    noisy = ell + 0.01 * rng.normal(size=ell.shape)
    s = np.linalg.svd(noisy, compute_uv=False)
    assert np.linalg.norm(noisy - rank1_approx(noisy)) == pytest.approx(np.sqrt(np.sum(s[1:] ** 2)))


def test_polar_and_stiefel_mm_never_increase():
    rng = np.random.default_rng(2)
    M = rng.normal(size=(100, 2, 3))
    P = polar_2x3(M)
    np.testing.assert_allclose(P @ np.swapaxes(P, 1, 2), np.broadcast_to(np.eye(2), (100, 2, 2)), atol=1e-10)
    U, _, Vt = np.linalg.svd(M, full_matrices=False)
    np.testing.assert_allclose(P, U @ Vt, atol=1e-10)
    S = rng.normal(size=(100, 3, 17))
    W = rng.normal(size=(100, 2, 17))
    w = rng.random((100, 17))
    A = np.einsum("tij,tj,tkj->tik", S, w, S)
    C = np.einsum("tij,tj,tkj->tik", W, w, S)
    R = polar_2x3(rng.normal(size=(100, 2, 3)))

    def f(R):
        return np.einsum("tij,tj->t", (W - R @ S) ** 2, w)

    prev = f(R)
    for _ in range(30):
        R = stiefel_mm_step(R, A, C)
        cur = f(R)
        assert np.all(cur <= prev + 1e-10)
        prev = cur


# ---------------------------------------------------------------- dictionary and initialisation


def test_shipped_dictionary_is_documented(dictionary):
    assert DEFAULT_DICTIONARY.is_file() and DEFAULT_DICTIONARY.stat().st_size < 200_000
    assert dictionary.bases.shape == (64, 3, 17)
    np.testing.assert_allclose(np.linalg.norm(dictionary.bases.reshape(64, -1), axis=1), 1.0, rtol=1e-5)
    np.testing.assert_allclose(dictionary.bases.mean(axis=2), 0.0, atol=1e-5)  # centred atoms
    assert "mocap.cs.cmu.edu" in dictionary.credit
    from reconstruction.dictionary.learn_dictionary import EVAL_CLIPS

    assert dictionary.clips and not set(dictionary.clips) & set(EVAL_CLIPS)


def test_canonical_frame_removes_rotation_and_translation():
    rng = np.random.default_rng(3)
    J = rng.normal(size=(5, 17, 3))
    R = Rotation.random(5, random_state=4).as_matrix()
    J2 = np.einsum("nij,nkj->nki", R, J) + rng.normal(size=(5, 1, 3))
    np.testing.assert_allclose(canonicalize_poses(J), canonicalize_poses(J2), atol=1e-10)


def _dictionary_poses(d: PoseDictionary, T: int, seed: int) -> np.ndarray:
    rng = np.random.default_rng(seed)
    c = np.zeros((T, d.num_bases))
    for t in range(T):
        k = rng.choice(d.num_bases, 3, replace=False)
        c[t, k] = rng.uniform(0.5, 1.0, 3) * rng.choice([-1.0, 1.0], 3) * np.array([2.0, 0.5, 0.5])
    S = d.compose(c)
    # (R, c) and (-R, -c) project identically; the initialisation returns the upright one
    return S * np.sign(np.einsum("tij,ij->t", S, d.mean_pose))[:, None, None]


def test_init_recovers_exact_dictionary_pose_under_known_rotation(dictionary):
    T = 8
    S = _dictionary_poses(dictionary, T, seed=5)  # (T, 3, 17) exact sparse combinations
    # a rotation about the vertical axis seen from slightly above, the setting of an orbiting drone
    yaw = np.radians(np.linspace(0, 300, T))
    Rfull = Rotation.from_euler("xy", np.stack([np.full(T, 0.3), yaw], 1)).as_matrix()
    R = Rfull[:, :2]
    W = 400.0 * (R @ S) + np.array([900.0, 500.0])[None, :, None]
    # independent frames: the single-frame estimate alone (no temporal choice between depth interpretations)
    res = initialise(W, None, dictionary, InitConfig(resolve_flips=False))
    rms = np.sqrt(np.mean(np.sum(S**2, axis=1), axis=1))
    scale = np.sqrt(np.mean(np.sum(res.S**2, axis=1), axis=1))
    S_hat = res.S * (rms / scale)[:, None, None]
    err = np.sqrt(np.mean(np.sum((S_hat - S) ** 2, axis=1), axis=1)) / rms  # no alignment: same frame
    assert np.median(err) < 0.02, err
    assert np.mean(err < 0.05) >= 0.75, err
    # rotation recovered (rows of R) for the frames whose pose is recovered
    ok = err < 0.05
    assert np.max(np.abs(res.R[ok] - R[ok])) < 0.05
    assert np.all(res.inlier)
    # reprojection matches the input
    assert np.median(np.abs(res.reprojection() - W)) < 2.0


def test_init_flags_gross_outliers(dictionary):
    T = 6
    S = _dictionary_poses(dictionary, T, seed=7)
    yaw = np.radians(np.linspace(0, 200, T))
    R = Rotation.from_euler("xy", np.stack([np.full(T, 0.2), yaw], 1)).as_matrix()[:, :2]
    W = 400.0 * (R @ S) + 800.0
    bad = np.zeros((T, 17), bool)
    # rigid-torso and head keypoints (a moved wrist could be explained by another arm pose)
    bad[np.arange(T), [0, 5, 6, 11, 12, 1]] = True
    W_out = W.copy()
    W_out[:, 0][bad] += 250.0
    res = initialise(W_out, None, dictionary)
    assert np.all(~res.inlier[bad])
    assert np.mean(~res.inlier[~bad]) < 0.05


def test_temporal_outlier_mask_finds_jumps():
    T = 50
    t = np.arange(T)[:, None]
    W = np.stack([100 + 5.0 * t + np.arange(17)[None] * 10.0, 200 + 2.0 * t + np.arange(17)[None] * 20.0], axis=1)
    conf = np.ones((T, 17))
    W2 = W.copy()
    W2[10, :, 3] += 150.0
    W2[30, :, 9] -= 120.0
    conf[20, 4] = 0.0
    m = temporal_outlier_mask(W2, conf)
    assert m[10, 3] and m[30, 9]
    assert m.sum() == 2


# ---------------------------------------------------------------- bundle adjustment


def _noisy_orthographic_sequence(d: PoseDictionary, T=40, seed=11, noise=0.01):
    """Smooth motion of dictionary poses seen by an orthographic camera turning about the vertical."""
    rng = np.random.default_rng(seed)
    keys = _dictionary_poses(d, 5, seed)
    s = np.linspace(0, 4, T)
    i = np.minimum(s.astype(int), 3)
    f = (s - i)[:, None, None]
    S = (1 - f) * keys[i] + f * keys[i + 1]
    yaw = np.radians(25.0 * np.arange(T) / 10.0)  # 25 deg/s at 10 fps
    R = Rotation.from_euler("xy", np.stack([np.full(T, 0.3), yaw], 1)).as_matrix()[:, :2]
    W = R @ S + noise * rng.normal(size=(T, 2, 17))
    return S, R, W


def _perturbed_start(S, R, seed):
    """A BA start near the truth: poses and rotations jittered by 0.05, rotations back on the Stiefel manifold."""
    rng = np.random.default_rng(seed)
    return S + 0.05 * rng.normal(size=S.shape), polar_2x3(R + 0.05 * rng.normal(size=R.shape))


def test_bundle_adjust_decreases_objective_monotonically(dictionary):
    S, R, W = _noisy_orthographic_sequence(dictionary)
    T = W.shape[0]
    S0, R0 = _perturbed_start(S, R, 12)
    w = np.ones((T, 17))
    for cfg in (
        BAConfig.paper(gamma=1.0, outer_iters=25, tol=0.0),
        BAConfig(gamma=0.0, outer_iters=25, tol=0.0),
        BAConfig.paper(gamma=1.0, outer_iters=25, tol=0.0, smooth_S=0.5, smooth_R=0.5, rot_prior=1.0),
        BAConfig(gamma=1.0, outer_iters=25, tol=0.0, warmup_iters=0, L_update="prior"),  # adult-proportion L
    ):
        res = bundle_adjust(W, w, S0, R0, COCO17_LIMBS, cfg, R_prior=R)
        F = res.objective
        assert len(F) == 26
        assert np.all(np.diff(F) <= 1e-9 * F[0]), np.diff(F)
        assert F[-1] < 0.8 * F[0]
        np.testing.assert_allclose(res.R @ np.swapaxes(res.R, 1, 2), np.broadcast_to(np.eye(2), (T, 2, 2)), atol=1e-9)


def test_stiefel_newton_step_never_increases_and_beats_mm():
    from reconstruction.monocular.linalg import stiefel_newton_step, stiefel_quadratic

    rng = np.random.default_rng(21)
    S = rng.normal(size=(200, 3, 17)) * np.array([1.0, 0.5, 0.1])[None, :, None]  # anisotropic, like a body
    W = rng.normal(size=(200, 2, 17))
    w = rng.random((200, 17))
    A = np.einsum("tij,tj,tkj->tik", S, w, S)
    C = np.einsum("tij,tj,tkj->tik", W, w, S)
    R0 = polar_2x3(rng.normal(size=(200, 2, 3)))
    Rn, Rm = R0.copy(), R0.copy()
    prev = stiefel_quadratic(R0, A, C)
    for _ in range(10):
        Rn = stiefel_newton_step(Rn, A, C)
        Rm = stiefel_mm_step(Rm, A, C)
        cur = stiefel_quadratic(Rn, A, C)
        assert np.all(cur <= prev + 1e-10)
        prev = cur
    np.testing.assert_allclose(Rn @ np.swapaxes(Rn, 1, 2), np.broadcast_to(np.eye(2), (200, 2, 2)), atol=1e-9)
    assert np.mean(stiefel_quadratic(Rn, A, C)) < np.mean(stiefel_quadratic(Rm, A, C))


# ---------------------------------------------------------------- adult-proportion L, articulation warm-up


def _adult_skeleton_sequence(T=9, seed=5):
    """Poses (T, 3, 17) whose prior limbs have exactly the adult bone lengths, at per-frame scales."""
    from reconstruction.monocular.perspective import ADULT_BONES_M

    rng = np.random.default_rng(seed)
    face = rng.normal(scale=0.05, size=(5, 3)) + [0.18, -0.2, 0.0]  # rigid head (face limbs: constant too)
    parent = {7: 5, 9: 7, 8: 6, 10: 8, 13: 11, 15: 13, 14: 12, 16: 14}
    out = []
    for t in range(T):
        X = np.zeros((17, 3))
        X[5], X[6] = [-0.18, -0.5, 0.0], [0.18, -0.5, 0.05]
        X[6] = X[5] + ADULT_BONES_M[(5, 6)] * (X[6] - X[5]) / np.linalg.norm(X[6] - X[5])
        X[11] = X[5] + ADULT_BONES_M[(5, 11)] * np.array([0.02, 1.0, 0.0]) / np.hypot(0.02, 1.0)
        # right hip: at the hip width from 11 and the flank length from 6
        a, b = X[11], X[6]
        d = np.linalg.norm(b - a)
        r1, r2 = ADULT_BONES_M[(11, 12)], ADULT_BONES_M[(6, 12)]
        x = (d * d + r1 * r1 - r2 * r2) / (2 * d)
        e = (b - a) / d
        n = np.cross(e, [0.0, 0.0, 1.0])
        n /= np.linalg.norm(n)
        X[12] = a + x * e + np.sqrt(max(r1 * r1 - x * x, 0.0)) * n
        for j in (7, 9, 8, 10, 13, 15, 14, 16):
            v = rng.normal(size=3)
            X[j] = X[parent[j]] + ADULT_BONES_M[(parent[j], j)] * v / np.linalg.norm(v)
        X[:5] = X[5] + face
        out.append((0.5 + rng.random()) * X.T)
    return np.stack(out)


def test_rank1_fixed_proportions_exact_and_least_squares():
    S = _adult_skeleton_sequence()
    a, b = limb_index_arrays(COCO17_LIMBS)
    u, known = prior_limb_proportions(COCO17_LIMBS)
    assert known.sum() == 12 and not known[12:].any()  # face limbs are not in the prior
    ell = squared_limb_lengths(S, a, b)
    ratio = ell[known] / u[known, None]  # the fixture: every prior limb at the adult length x the frame's scale
    np.testing.assert_allclose(ratio, np.broadcast_to(ratio[:1], ratio.shape), rtol=1e-9)
    L = rank1_fixed_proportions(ell, u, known)
    np.testing.assert_allclose(L, ell, rtol=1e-9)  # adult proportions at any scale (rigid face): exact
    assert np.linalg.matrix_rank(L, tol=1e-9 * np.abs(L).max()) == 1
    assert proportion_inconsistency(S, COCO17_LIMBS) < 1e-9
    # a stretched forearm: the fit is the least-squares one over v (hand check: v_t = <u, l_t> / ||u||^2)
    S2 = S.copy()
    S2[:, :, 9] = S2[:, :, 7] + 1.5 * (S2[:, :, 9] - S2[:, :, 7])
    ell2 = squared_limb_lengths(S2, a, b)
    L2 = rank1_fixed_proportions(ell2[known], u[known], np.ones(12, dtype=bool))
    v = u[known] @ ell2[known] / (u[known] @ u[known])
    np.testing.assert_allclose(L2, np.outer(u[known], v), rtol=1e-12)
    assert proportion_inconsistency(S2, COCO17_LIMBS) > 0.05
    # the free (face) rows never make the fit worse than the first v-only step
    L3 = rank1_fixed_proportions(ell2, u, known, sweeps=5)
    L1 = rank1_fixed_proportions(ell2, u, known, sweeps=1)
    assert np.linalg.norm(ell2 - L3) <= np.linalg.norm(ell2 - L1) + 1e-12


def test_warmup_accept_reject_and_paper_fallback(dictionary):
    S, R, W = _noisy_orthographic_sequence(dictionary)
    T = W.shape[0]
    S0, R0 = _perturbed_start(S, R, 13)
    w = np.ones((T, 17))
    paper = bundle_adjust(W, w, S0, R0, COCO17_LIMBS, BAConfig.paper(outer_iters=15, tol=0.0))
    assert paper.warmup_accepted is None
    # impossible acceptance ratio: the warm-up is discarded and the result is exactly the paper's BA
    rej = bundle_adjust(W, w, S0, R0, COCO17_LIMBS, BAConfig(outer_iters=15, tol=0.0, warmup_iters=5, warmup_accept_ratio=1e-12))
    assert rej.warmup_accepted is False
    np.testing.assert_array_equal(rej.S, paper.S)
    np.testing.assert_array_equal(rej.objective, paper.objective)
    # always accepted: gamma = 0 history (warm-up), then the articulated run; each monotone
    acc = bundle_adjust(W, w, S0, R0, COCO17_LIMBS,
                        BAConfig(tol=0.0, warmup_iters=5, warmup_accept_ratio=0.0, warmup_outer_iters=10))  # fmt: skip
    assert acc.warmup_accepted is True
    F = acc.objective
    assert len(F) == 6 + 11
    assert np.all(np.diff(F[:6]) <= 1e-9 * F[0]) and np.all(np.diff(F[6:]) <= 1e-9 * F[6])
    assert F[6] >= F[5]  # switching gamma on adds the non-negative articulation term
    # the warm-up is pure gamma = 0 BA: same poses as running it alone
    g0 = bundle_adjust(W, w, S0, R0, COCO17_LIMBS, BAConfig(gamma=0.0, outer_iters=5, tol=0.0))
    np.testing.assert_allclose(F[:6], g0.objective)


def test_pipeline_runs_paper_order_ablation(dictionary):
    from reconstruction.monocular.pipeline import MonocularConfig, reconstruct_monocular

    S, R, W = _noisy_orthographic_sequence(dictionary, noise=0.5)
    W = 200.0 * W + 500.0  # pixels
    cfg = MonocularConfig()
    cfg.ba.warmup_accept_ratio = 0.0  # always keep the warm-up: the default then differs from the paper's BA
    res = reconstruct_monocular(W, None, dictionary, cfg)
    assert res.ba.warmup_accepted is True and res.ba_paper is not None and res.ba_paper is not res.ba
    ref = bundle_adjust(W, res.weights, res.init.S, res.init.R, dictionary.limbs, BAConfig.paper())
    np.testing.assert_array_equal(res.ba_paper.S, ref.S)
    # the cleaned confidence (what the body model fits): the BA's weights are it times the init's inliers
    assert res.confidence.shape == res.weights.shape
    np.testing.assert_array_equal(res.weights, res.confidence * res.init.inlier)
    cfg.ba = BAConfig.paper()  # the paper's own config: no duplicate run
    assert reconstruct_monocular(W, None, dictionary, cfg).ba_paper is None
