"""Where association loses people: the first cause per lost ground-truth person-frame.

Needs the ground-truth person of every detection (a scene folder's det_ids.npz, written by
maem-sim). For a GT person that no prediction matched (metrics.match_frame, < 500 mm), the
first stage of the pipeline that made it unreachable, in pipeline order:

  frontend       fewer than k_min cameras have a kept (score >= tau_det) detection of it
  reproj_gate    its true pairs surviving the bbox-centre gate connect fewer than k_min views
  epipolar_gate  likewise after the epipolar gate
  cost_cap       likewise after the cost cap (tau_cost)
  wrong_match    a cluster holding its detections also holds another person's (or a false
                 positive's) detections
  merge          its detections are spread over several clusters (not merged)
  conflict       conflict removal dropped its detections below k_min views (paper pipeline)
  k_min          its cluster has fewer than k_min views
  triangulation  a pure cluster of >= k_min views exists, yet no pose matched the person
"""

from __future__ import annotations

from collections import Counter
from collections.abc import Mapping

import numpy as np
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components

from maem_ros.core.association.pipeline import AssociationResult
from maem_ros.core.detections import PASSED, REJECTED_EPIPOLAR, REJECTED_REPROJ

CAUSES = (
    "frontend",
    "reproj_gate",
    "epipolar_gate",
    "cost_cap",
    "wrong_match",
    "merge",
    "conflict",
    "k_min",
    "triangulation",
)


def row_persons(
    result: AssociationResult, rig_names: list[str], det_ids: Mapping[str, np.ndarray]
) -> np.ndarray:
    """(N,) GT person of every table row (-1 = false positive or unknown)."""
    table = result.table
    assert table is not None, "explain needs the association's table"
    out = np.full(len(table), -1, np.int64)
    for c in np.unique(table.cam):
        ids = det_ids.get(rig_names[int(c)])
        if ids is None:
            continue
        rows = np.flatnonzero(table.cam == c)
        det = table.det[rows]
        ok = det < len(ids)
        out[rows[ok]] = np.asarray(ids)[det[ok]]
    return out


def _max_views_connected(table, pairs, rows_of_p: np.ndarray, allowed: np.ndarray) -> int:
    """Most distinct cameras in one connected component of p's rows over the allowed true pairs."""
    local = -np.ones(len(table), np.int64)
    local[rows_of_p] = np.arange(rows_of_p.size)
    sel = allowed & (local[pairs.i] >= 0) & (local[pairs.j] >= 0)
    n = rows_of_p.size
    g = coo_matrix((np.ones(int(sel.sum())), (local[pairs.i[sel]], local[pairs.j[sel]])), shape=(n, n))
    _, comp = connected_components(g, directed=False)
    cams = table.cam[rows_of_p]
    return max(np.unique(cams[comp == k]).size for k in np.unique(comp))


def explain_frame(result: AssociationResult, persons: np.ndarray, lost: np.ndarray, k_min: int) -> Counter:
    """Counter of CAUSES over the lost GT person ids ``lost`` of one frame set."""
    table, pairs = result.table, result.pairs
    assert table is not None and pairs is not None, "explain needs the association's table"
    out: Counter = Counter()
    group_of = np.full(len(table), -1, np.int64)
    for g, rows in enumerate(result.groups):
        group_of[rows] = g
    conflicted = np.zeros(len(table), np.bool_)
    conflicted[result.conflicts] = True
    stage_ok = {
        "reproj_gate": pairs.stage != REJECTED_REPROJ,
        "epipolar_gate": ~np.isin(pairs.stage, (REJECTED_REPROJ, REJECTED_EPIPOLAR)),
        "cost_cap": pairs.stage == PASSED,
    }
    for p in lost:
        mine = np.flatnonzero(persons == p)
        if np.unique(table.cam[mine]).size < k_min:
            out["frontend"] += 1
            continue
        cause = next(
            (name for name, ok in stage_ok.items() if _max_views_connected(table, pairs, mine, ok) < k_min),
            None,
        )
        if cause is None:
            groups = np.unique(group_of[mine])
            members = np.concatenate([result.groups[g] for g in groups if g >= 0] or [np.zeros(0, int)])
            if np.any(persons[members] != p):
                cause = "wrong_match"
            elif groups.size > 1:
                cause = "merge"
            elif conflicted[mine].any():
                cause = "conflict"
            elif np.unique(table.cam[mine[~conflicted[mine]]]).size < k_min:
                cause = "k_min"
            else:
                cause = "triangulation"
        out[cause] += 1
    return out


def oracle_clusters(
    rig_names: list[str], frames: Mapping, det_ids: Mapping[str, np.ndarray], tau_det: float, k_min: int
) -> list:
    """The perfect association: kept detections grouped by their GT person (one per camera,
    the highest score), people seen by at least k_min cameras; false positives left out."""
    from maem_ros.core.detections import Cluster

    by_person: dict[int, dict[int, tuple[float, int]]] = {}
    for name, fd in frames.items():
        ids = det_ids.get(name)
        if ids is None:
            continue
        c = rig_names.index(name)
        for d in np.flatnonzero((fd.scores >= tau_det) & (np.arange(fd.n) < len(ids))):
            p = int(ids[d])
            if p < 0:
                continue
            best = by_person.setdefault(p, {}).get(c)
            if best is None or fd.scores[d] > best[0]:
                by_person[p][c] = (float(fd.scores[d]), int(d))
    out = []
    for p in sorted(by_person):
        views = by_person[p]
        if len(views) >= k_min:
            members = np.array(sorted((c, d) for c, (_, d) in views.items()), dtype=np.int64)
            out.append(Cluster(members=members, costs=np.full(len(members), np.nan)))
    return out


# ---- published poses far from their person (--explain-tracks) --------------------------------
#: first cause of a published pose more than ``far_m`` from its matched GT person (or matched to
#: none), in this order (doc/tracking.md):
#:   stale_or_duplicate  the pose is within far_m of the person its members show, but another
#:                       pose of the frame holds that person (a second track of one person)
#:   prediction          a pure cluster whose own triangulation is within far_m, the published
#:                       (filtered) pose is not: the joint filter leaned on the track's prediction
#:   wrong_track         a track's cluster (FLAG_TRACKED) holds detections of another person or a
#:                       false positive: a detection explained by the wrong track
#:   weak_two_view       a pure cluster of two views whose triangulation is far (the
#:                       weakest geometry; k_min is 2 on the humanm3 rigs)
#:   wrong_new_cluster   a cluster from the cross-view association mixing people
#:   triangulation       a pure cluster of three views or more, triangulated far off
#:   not_in_gt           every member is a bystander (not in gt.npz): not an error of the pipeline
TRACK_CAUSES = (
    "stale_or_duplicate",
    "prediction",
    "wrong_track",
    "weak_two_view",
    "wrong_new_cluster",
    "triangulation",
    "not_in_gt",
)
#: a published pose further than this from its matched person is explained (m)
FAR_M = 0.15


def member_persons(
    members: np.ndarray, rig_names: list[str], det_ids: Mapping[str, np.ndarray]
) -> np.ndarray:
    """(M,) GT person of each cluster member (camera index, detection index); -1 = false
    positive or unknown."""
    out = np.full(len(members), -1, np.int64)
    for m, (c, d) in enumerate(np.asarray(members, np.int64).reshape(-1, 2).tolist()):
        ids = det_ids.get(rig_names[c])
        if ids is not None and d < len(ids):
            out[m] = int(ids[d])
    return out


def explain_poses(
    published: np.ndarray,
    raw: np.ndarray,
    persons: list[np.ndarray],
    tracked: np.ndarray,
    gt: np.ndarray,
    gt_mask: np.ndarray,
    far_m: float = FAR_M,
) -> list[str | None]:
    """First cause (TRACK_CAUSES) of every published pose of one frame, None for a good one.

    published (K,13,3) world m as published (filtered); raw (K,13,3) this frame's own
    triangulation of the same clusters; persons[k] (M_k,) GT person of each member of pose k
    (member_persons: index into gt's columns, -1 = false positive, >= P = bystander);
    tracked (K,) bool, the cluster was explained by a track (FLAG_TRACKED); gt (P,13,3) and
    gt_mask (P,13) every GT person of the frame (mask all False = absent).
    """
    from maem_ros.core.metrics.poses import match_frame, mpjpe

    P = len(gt)
    present = np.flatnonzero(gt_mask.any(-1))
    rows, cols, cost = match_frame(published, gt[present], gt_mask[present])
    err = np.full(len(published), np.inf)
    err[rows] = cost
    holder = {int(present[c]): int(r) for r, c in zip(rows.tolist(), cols.tolist())}
    out: list[str | None] = []
    for k in range(len(published)):
        if err[k] <= far_m:
            out.append(None)
            continue
        pers = np.asarray(persons[k], np.int64)
        players = pers[(pers >= 0) & (pers < P)]
        if pers.size and (pers >= P).all():
            out.append("not_in_gt")
            continue
        dom = int(np.bincount(players).argmax()) if players.size else -1
        mixed = np.unique(pers).size > 1 or bool((pers < 0).any())
        pub = raw_e = np.inf
        if dom >= 0 and gt_mask[dom].any():
            pub = float(mpjpe(published[k], gt[dom], gt_mask[dom]))
            raw_e = float(mpjpe(raw[k], gt[dom], gt_mask[dom]))
        if pub <= far_m and holder.get(dom, k) != k:
            cause = "stale_or_duplicate"
        elif not mixed and raw_e <= far_m < pub:
            cause = "prediction"
        elif mixed and tracked[k]:
            cause = "wrong_track"
        elif not mixed and pers.size <= 2:
            cause = "weak_two_view"
        elif mixed:
            cause = "wrong_new_cluster"
        elif holder.get(dom, k) != k:
            cause = "stale_or_duplicate"
        else:
            cause = "triangulation"
        out.append(cause)
    return out
