"""Metrics (core/metrics/poses.py, core/geometry/procrustes.py) on hand-computed examples."""
from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings, strategies as st
from scipy.spatial.transform import Rotation

from maem_ros.core.metrics.poses import average_precision, evaluate_sequence, match_frame, mpjpe, pa_mpjpe
from maem_ros.core.geometry.procrustes import procrustes_align

J = 6
SKELETON = np.random.default_rng(42).normal(scale=0.4, size=(J, 3))


def body(x: float, y: float = 0.0) -> np.ndarray:
    """The fixed skeleton moved by (x, y, 0) metres: MPJPE between two bodies = their offset."""
    return SKELETON + [x, y, 0.0]


def ones(p: int) -> np.ndarray:
    return np.ones((p, J), bool)


# -------------------------------------------------------------------------------- per pose
def test_mpjpe_hand_computed_and_masks() -> None:
    gt = np.zeros((4, 3))
    pred = np.array([[0.1, 0, 0], [0, 0.2, 0], [0, 0, 0.3], [5.0, 0, 0]])
    assert mpjpe(pred, gt) == pytest.approx((0.1 + 0.2 + 0.3 + 5.0) / 4)
    assert mpjpe(pred, gt, np.array([1, 1, 1, 0], bool)) == pytest.approx(0.2)
    pred[1] = np.nan  # a missing predicted joint is ignored, not counted as 0 error
    assert mpjpe(pred, gt, np.array([1, 1, 1, 0], bool)) == pytest.approx(0.2)
    assert np.isnan(mpjpe(pred, gt, np.array([0, 1, 0, 0], bool)))


def test_mpjpe_batched_broadcast() -> None:
    gt = np.stack([body(0), body(1)])  # (2,J,3)
    pred = np.stack([body(0.1), body(0.5), body(0.95)])  # (3,J,3)
    cost = mpjpe(pred[:, None], gt[None])
    np.testing.assert_allclose(cost, [[0.1, 0.9], [0.5, 0.5], [0.95, 0.05]], atol=1e-12)


@settings(max_examples=50, deadline=None)
@given(seed=st.integers(0, 2**31 - 1), scale=st.floats(0.2, 5.0),
       shift=st.tuples(*[st.floats(-10, 10)] * 3))
def test_pa_mpjpe_invariant_to_similarity(seed: int, scale: float, shift) -> None:
    rng = np.random.default_rng(seed)
    X = rng.normal(size=(17, 3))
    Y = X + rng.normal(scale=0.05, size=X.shape)
    R = Rotation.random(random_state=seed).as_matrix()
    Xs = scale * X @ R.T + np.asarray(shift)
    assert pa_mpjpe(Xs, X) == pytest.approx(0.0, abs=1e-9)
    assert pa_mpjpe(Xs, Y) == pytest.approx(float(pa_mpjpe(X, Y)), rel=1e-6, abs=1e-12)
    aligned, s, Rf, t = procrustes_align(Xs, X)
    np.testing.assert_allclose(aligned, X, atol=1e-9)
    assert s == pytest.approx(1.0 / scale, rel=1e-9)
    np.testing.assert_allclose(Rf, R.T, atol=1e-9)


def test_pa_mpjpe_no_reflection_and_batched() -> None:
    X = np.random.default_rng(0).normal(size=(3, 10, 3))
    mirrored = X * [-1.0, 1.0, 1.0]  # a reflection is not a rotation: error must stay > 0
    err = pa_mpjpe(mirrored, X)
    assert err.shape == (3,) and np.all(err > 1e-3)
    R = procrustes_align(mirrored, X)[2]
    np.testing.assert_allclose(np.linalg.det(R), 1.0, atol=1e-9)


def test_pa_mpjpe_masks_and_nan() -> None:
    X = np.random.default_rng(1).normal(size=(8, 3))
    Y = 2.0 * X + 1.0
    Y_bad = Y.copy()
    Y_bad[0] += 10.0
    mask = np.ones(8, bool)
    mask[0] = False
    assert pa_mpjpe(X, Y_bad, mask) == pytest.approx(0.0, abs=1e-9)
    X_nan = X.copy()
    X_nan[0] = np.nan
    assert pa_mpjpe(X_nan, Y_bad) == pytest.approx(0.0, abs=1e-9)
    assert np.isnan(pa_mpjpe(X[:2], Y[:2]))  # < 3 joints: similarity undetermined


# -------------------------------------------------------------------------------- matching
def test_hungarian_beats_greedy() -> None:
    gt = np.stack([body(0.0), body(0.3)])  # A at 0, B at 0.3 m
    pred = np.stack([body(0.12), body(-0.15)])  # p1: A 120 / B 180 mm; p2: A 150 / B 450 mm
    rows, cols, cost = match_frame(pred, gt, ones(2))
    assert dict(zip(rows.tolist(), cols.tolist())) == {0: 1, 1: 0}
    np.testing.assert_allclose(sorted(cost), [0.15, 0.18], atol=1e-12)
    res = evaluate_sequence([pred], [np.array([0.9, 0.8])], [gt], [ones(2)])
    assert res["recall"] == 1.0
    assert res["mpjpe_mean"] == pytest.approx(165.0)
    assert res["mpjpe_median"] == pytest.approx(165.0)
    assert res["pa_mpjpe_mean"] == pytest.approx(0.0, abs=1e-6)  # pure translations
    assert res["per_frame_mpjpe"] == [pytest.approx(165.0)]


def test_only_pairs_under_500mm_match() -> None:
    gt = np.stack([body(0.0), body(3.0)])
    pred = np.stack([body(0.6), body(3.499)])  # 600 mm (no) and 499 mm (yes)
    res = evaluate_sequence([pred], [np.ones(2)], [gt], [ones(2)])
    assert res["recall"] == 0.5
    assert res["mpjpe_mean"] == pytest.approx(499.0)
    far = evaluate_sequence([pred[:1]], [np.ones(1)], [gt[:1]], [ones(1)])
    assert far["recall"] == 0.0 and np.isnan(far["mpjpe_mean"]) and np.isnan(far["per_frame_mpjpe"][0])


def test_gt_mask_and_missing_predicted_joints() -> None:
    gt = body(0.0)[None]
    pred = body(0.1)[None].copy()
    pred[0, 0] += 3.0  # huge error on joint 0 ...
    mask = ones(1)
    mask[0, 0] = False  # ... which has no GT
    pred[0, 1] = np.nan  # and a joint that was not triangulated
    res = evaluate_sequence([pred], [np.ones(1)], [gt], [mask])
    assert res["mpjpe_mean"] == pytest.approx(100.0)
    assert res["recall"] == 1.0


# ------------------------------------------------------------------------------------- AP
def test_ap_hand_computed() -> None:
    # frame 0: GT A (x=0), B (x=5); p1 A+50mm (0.9), p2 A+90mm (0.8, duplicate), p3 B+120mm (0.7)
    # frame 1: GT C (x=0); p4 1 m off (0.95) -> false positive everywhere. #GT = 3
    gts = [np.stack([body(0.0), body(5.0)]), body(0.0)[None]]
    preds = [np.stack([body(0.05), body(0.09), body(5.12)]), body(1.0)[None]]
    scores = [np.array([0.9, 0.8, 0.7]), np.array([0.95])]
    res = evaluate_sequence(preds, scores, gts, [ones(2), ones(1)])
    # order p4 p1 p2 p3. d=75/100: TP only p1 -> recall 1/3 at precision envelope 1/2 -> AP 1/6
    assert res["ap75"] == pytest.approx(1 / 6)
    assert res["ap100"] == pytest.approx(1 / 6)
    # d=125/150: p1 and p3 TP; precision envelope 1/2 up to recall 2/3 -> AP 1/3
    assert res["ap125"] == pytest.approx(1 / 3)
    assert res["ap150"] == pytest.approx(1 / 3)
    assert res["recall"] == pytest.approx(2 / 3)
    assert res["frames"] == 2
    assert res["mpjpe_mean"] == pytest.approx((50 + 120) / 2)


def test_ap_closest_not_yet_taken_gt() -> None:
    # GT A (x=0), B (x=0.15). p1 (0.9): A 30 / B 120 mm; p2 (0.8): A 60 / B 90 mm
    gts = [np.stack([body(0.0), body(0.15)])]
    preds = [np.stack([body(0.03), body(0.06)])]
    res = evaluate_sequence(preds, [np.array([0.9, 0.8])], gts, [ones(2)])
    assert res["ap100"] == pytest.approx(1.0)  # p2 takes B (A already taken) at 90 < 100
    assert res["ap75"] == pytest.approx(0.5)  # p2 -> B at 90 >= 75 is a FP: 1/2 * 1
    assert res["mpjpe_mean"] == pytest.approx(60.0)


def test_ap_score_order_matters() -> None:
    costs = [np.array([[0.05], [0.3]])]  # one GT; a good and a bad prediction
    assert average_precision(costs, [np.array([0.9, 0.1])], 0.1) == pytest.approx(1.0)
    # the bad one ranked first: recall 1 reached at precision 1/2
    assert average_precision(costs, [np.array([0.1, 0.9])], 0.1) == pytest.approx(0.5)


def test_ap_degenerate_sequences() -> None:
    empty_pred = evaluate_sequence([np.zeros((0, J, 3))], [np.zeros(0)], [body(0)[None]], [ones(1)])
    assert empty_pred["ap75"] == 0.0 and empty_pred["recall"] == 0.0
    no_gt = evaluate_sequence([body(0)[None]], [np.ones(1)], [np.zeros((0, J, 3))], [np.zeros((0, J), bool)])
    assert np.isnan(no_gt["ap150"]) and np.isnan(no_gt["recall"])
    assert evaluate_sequence([], [], [], [])["frames"] == 0


def test_result_keys() -> None:
    res = evaluate_sequence([body(0)[None]], [np.ones(1)], [body(0)[None]], [ones(1)])
    assert set(res) == {"frames", "recall", "mpjpe_mean", "mpjpe_median", "pa_mpjpe_mean",
                        "pa_mpjpe_median", "ap75", "ap100", "ap125", "ap150", "per_frame_mpjpe"}
    assert res["ap75"] == 1.0 and res["mpjpe_mean"] == pytest.approx(0.0)


# ------------------------------------------------------------------------------ bad input
@pytest.mark.parametrize("preds,scores,gts,masks,field", [
    ([np.zeros((1, J, 2))], [np.ones(1)], [body(0)[None]], [ones(1)], "preds[0]"),
    ([body(0)[None]], [np.ones(2)], [body(0)[None]], [ones(1)], "scores[0]"),
    ([body(0)[None]], [np.array([np.nan])], [body(0)[None]], [ones(1)], "scores[0]"),
    ([body(0)[None]], [np.ones(1)], [body(0)], [ones(1)], "gts[0]"),
    ([body(0)[None]], [np.ones(1)], [body(0)[None]], [np.ones((1, J + 1), bool)], "gt_masks[0]"),
    ([body(0)[None]] * 2, [np.ones(1)], [body(0)[None]], [ones(1)], "preds"),
])
def test_bad_input_names_field(preds, scores, gts, masks, field) -> None:
    with pytest.raises(ValueError, match=field.replace("[", r"\[").replace("]", r"\]")):
        evaluate_sequence(preds, scores, gts, masks)
