"""Cross-view people of every frame given an approximate rig: epipolar matching and clustering.

For each frame and camera pair, every detection pair's cost is the median over joints of the
symmetric epipolar distance (px) in the rectified images, also with b's sides swapped; pairs
under the gate are merged greedily, cheapest first, into clusters holding at most one
detection per camera (union-find that tracks each member's side swap relative to its
cluster). A cluster seen by two or more cameras is one person at that frame.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..geometry.multiview import dlt
from ..tracking.track_geometry import nanmedian
from .people_data import PeopleData


@dataclass
class Clusters:
    """People of all frames: member rows (M,) with ``person`` (M,) cluster id, ``frame``,
    ``camera``, ``det`` (row in that camera's flat arrays) and ``swapped`` (bool: the member's
    sides are swapped relative to the cluster's majority). Cluster ids 0..num-1."""

    person: np.ndarray
    frame: np.ndarray
    camera: np.ndarray
    det: np.ndarray
    swapped: np.ndarray

    @property
    def num(self) -> int:
        return int(self.person.max(initial=-1)) + 1


def fundamental(K_a, R_a, t_a, K_b, R_b, t_b) -> np.ndarray:
    """F with x_a^T F x_b = 0 (homogeneous rectified px), world -> camera poses."""
    R = R_a @ R_b.T
    t = t_a - R @ t_b
    tx = np.array([[0, -t[2], t[1]], [t[2], 0, -t[0]], [-t[1], t[0], 0]])
    return np.linalg.inv(K_a).T @ tx @ R @ np.linalg.inv(K_b)


def _epipolar_cost(F: np.ndarray, ua: np.ndarray, ub: np.ndarray) -> np.ndarray:
    """(na,nb) median over joints of the symmetric epipolar distance (px) between detections
    ua (na,J,2) and ub (nb,J,2); NaN joints ignored; inf with fewer than 3 common joints."""
    ha = np.concatenate([ua, np.ones(ua.shape[:2] + (1,))], axis=2)
    hb = np.concatenate([ub, np.ones(ub.shape[:2] + (1,))], axis=2)
    la = hb @ F.T  # lines in a of b's points (nb,J,3)
    lb = ha @ F  # lines in b of a's points (na,J,3)
    num = np.abs(np.einsum("ajk,bjk->abj", ha, la))
    da = num / np.linalg.norm(la[None, :, :, :2], axis=3)
    db = num / np.linalg.norm(lb[:, None, :, :2], axis=3)
    d = 0.5 * (da + db)
    enough = np.sum(np.isfinite(d), axis=2) >= 3
    med = nanmedian(np.where(np.isfinite(d), d, np.nan)) if d.size else d[..., 0]
    return np.where(enough, med, np.inf)


def match_frames(data: PeopleData, R: np.ndarray, t: np.ndarray, gate_px: float) -> Clusters:
    """Clusters of every frame under the rig (R, t) (cameras with NaN poses are left out)."""
    C = data.num_cameras
    ok = np.all(np.isfinite(t), axis=1)
    P = np.stack(
        [
            data.rig[c].K_rect @ np.hstack([R[c], t[c][:, None]]) if ok[c] else np.full((3, 4), np.nan)
            for c in range(C)
        ]
    )
    Fs = {
        (a, b): fundamental(data.rig[a].K_rect, R[a], t[a], data.rig[b].K_rect, R[b], t[b])
        for a in range(C)
        for b in range(a + 1, C)
        if ok[a] and ok[b]
    }
    out: list[list] = [[] for _ in range(5)]
    next_id = 0
    for f in range(data.num_frames):
        edges = []
        for (a, b), F in Fs.items():
            sa, sb = data.cameras[a].frame(f), data.cameras[b].frame(f)
            if sa.stop == sa.start or sb.stop == sb.start:
                continue
            ua, ub = data.cameras[a].kpts2d[sa], data.cameras[b].kpts2d[sb]
            cost = np.stack([_epipolar_cost(F, ua, ub), _epipolar_cost(F, ua, ub[:, data.flip])])
            sw, i, j = np.nonzero(cost < gate_px)
            for s_, i_, j_ in zip(sw, i, j):
                edges.append((float(cost[s_, i_, j_]), a, sa.start + i_, b, sb.start + j_, int(s_)))
        members = _greedy_clusters(edges, _Consistency(data, P, gate_px))
        for rows in members.values():
            if len(rows) < 2:
                continue
            swaps = np.array([r[2] for r in rows], bool)
            if swaps.sum() * 2 > len(swaps):
                swaps = ~swaps
            for (cam, det, _), s_ in zip(rows, swaps):
                for lst, v in zip(out, (next_id, f, cam, det, s_)):
                    lst.append(v)
            next_id += 1
    return Clusters(
        *(np.asarray(v, dt) for v, dt in zip(out, (np.int64, np.int64, np.int64, np.int64, bool)))
    )


class _Consistency:
    """Whether detections (camera, row, swapped) are one person: the median reprojection
    error (px) of their joints triangulated together stays under the gate (with three or more
    views this rejects the wrong pairs an epipolar line alone cannot tell apart, e.g. people
    in a row seen from cameras at their height)."""

    def __init__(self, data: PeopleData, P: np.ndarray, gate_px: float):
        self.data, self.P, self.gate = data, P, gate_px

    def __call__(self, members: list[tuple[int, int, int]]) -> bool:
        if len(members) < 3:
            return True
        cams = np.array([m[0] for m in members])
        uv = np.stack(
            [
                self.data.cameras[c].kpts2d[r][self.data.flip] if s else self.data.cameras[c].kpts2d[r]
                for c, r, s in members
            ]
        )
        X = dlt(self.P[cams], np.swapaxes(uv, 0, 1))
        h = np.einsum("cij,jk->cik", self.P[cams][:, :, :3], X.T) + self.P[cams][:, :, 3:]
        with np.errstate(all="ignore"):
            err = np.linalg.norm(h[:, :2].transpose(0, 2, 1) / h[:, 2:].transpose(0, 2, 1) - uv, axis=2)
        # a point at zero depth (inf error) counts as a large error, not as missing
        med = nanmedian(np.where(np.isinf(err), 1e300, err).ravel())
        return bool(np.isfinite(med) and med < self.gate)


def _greedy_clusters(edges: list, consistent) -> dict:
    """Union-find over (cost, cam a, det a, cam b, det b, swapped) edges, cheapest first, never
    joining two clusters that share a camera or whose union is not ``consistent``; returns
    {root: [(camera, det, swap vs root)]}."""
    parent: dict = {}
    swap: dict = {}  # swap of a node relative to its parent
    cams: dict = {}
    seen: dict = {}  # node -> order of first appearance
    members: dict = {}  # root -> its cluster's nodes in order of first appearance

    def find(x):
        path_swap = 0
        root = x
        while parent[root] != root:
            path_swap ^= swap[root]
            root = parent[root]
        return root, path_swap

    for _cost, a, i, b, j, s in sorted(edges):
        for node, cam in (((a, i), a), ((b, j), b)):
            if node not in parent:
                parent[node], swap[node], cams[node] = node, 0, {cam}
                seen[node], members[node] = len(seen), [node]
        (ra, sa), (rb, sb) = find((a, i)), find((b, j))
        if ra == rb or cams[ra] & cams[rb]:
            continue
        srb = sa ^ sb ^ s
        union = [(n[0], n[1], find(n)[1]) for n in members[ra]] + [
            (n[0], n[1], find(n)[1] ^ srb) for n in members[rb]
        ]
        if not consistent(union):
            continue
        parent[rb] = ra
        swap[rb] = srb
        cams[ra] |= cams.pop(rb)
        members[ra] = sorted(members[ra] + members.pop(rb), key=seen.__getitem__)
    groups: dict = {}
    for node in parent:
        root, s = find(node)
        groups.setdefault(root, []).append((node[0], node[1], s))
    return groups
