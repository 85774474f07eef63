"""What maem-demo reports: accuracy against the bag's ground truth, per-stage timing from the
recorded /diagnostics, end-to-end latency and drops, and the snapshot pictures."""

from __future__ import annotations

import os
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from maem_ros import bagio
from maem_ros.core.colors import id_bgr8
from maem_ros.core.metrics.poses import evaluate_sequence
from maem_ros.core.skeleton import SPORTCENTER_13
from maem_ros.tools.demo.demo_bag import DemoBag, image_topic
from maem_ros.tools.eval.plots import plot_court
from maem_ros.tools.eval.results import format_table
from maem_ros.wire import UNTRACKED_ID, msg_to_poses


@dataclass
class GraphRun:
    """Outcome of one graph replay (tools/demo/demo_graph.run_graph)."""

    exit_codes: dict[str, int | None]
    crashed: dict[str, str]  # process -> what happened (+ log tail)
    image_t: dict[int, int]
    poses_t: dict[int, int]
    wall_s: float
    record: Path


LATENCY_DEFINITION = (
    "latency = wall time (monotonic clock of the demo's listener node) at which /maem/poses with "
    "stamp s is received, minus the wall time at which the listener received the first "
    "/<cam>/image_raw/compressed with stamp s from maem-play; both measured in one process, so "
    "it covers DDS transport, the frontends, synchronisation wait, association, triangulation"
)


# ---------------------------------------------------------------------------------------------
# recorded results
# ---------------------------------------------------------------------------------------------
def recorded_poses(record: Path) -> dict[int, Any]:
    """stamp -> PoseFrame of the recorded /maem/poses (first message per stamp)."""
    out: dict[int, Any] = {}
    if not (record / "metadata.yaml").is_file():
        return out
    for m in bagio.read_messages(record, ["/maem/poses"]):
        pf = msg_to_poses(m.decode(), m.topic)
        out.setdefault(pf.stamp_ns, pf)
    return out


def recorded_diagnostics(record: Path) -> dict[str, dict[str, str]]:
    """node name -> key/values of its last recorded DiagnosticStatus."""
    out: dict[str, dict[str, str]] = {}
    if not (record / "metadata.yaml").is_file():
        return out
    for m in bagio.read_messages(record, ["/diagnostics"]):
        for st in m.decode().status:
            out[st.name] = {kv.key: kv.value for kv in st.values}
    return out


# ---------------------------------------------------------------------------------------------
# accuracy
# ---------------------------------------------------------------------------------------------
def score(
    demo: DemoBag, stamps: Sequence[int], preds: dict[int, tuple[np.ndarray, np.ndarray]]
) -> dict[str, Any]:
    """maem-eval metrics over ``stamps``; a frame without predictions counts as all missed."""
    empty = (np.zeros((0, SPORTCENTER_13.num_joints, 3)), np.zeros(0))
    ps, ss, gts, masks = [], [], [], []
    for s in stamps:
        if s not in demo.gt:
            continue
        joints, scores = preds.get(s, empty)
        keep = np.isfinite(joints).all(-1).any(-1)
        ps.append(joints[keep])
        ss.append(scores[keep])
        g = demo.gt[s]
        m = np.isfinite(g).all(-1)
        gts.append(np.where(m[..., None], g, 0.0))
        masks.append(m)
    if not gts:
        raise ValueError(f"bag {str(demo.path)!r}: no ground truth (/maem/gt_poses) for the played frames")
    metrics = dict(evaluate_sequence(ps, ss, gts, masks))
    metrics["frames"] = len(gts)
    return metrics


def print_accuracy(name: str, metrics: dict[str, Any]) -> None:
    print("\naccuracy against the bag's ground truth (/maem/gt_poses, players, sportcenter_13):")
    print(format_table([(name, metrics)]))


# ---------------------------------------------------------------------------------------------
# timing, latency, drops
# ---------------------------------------------------------------------------------------------
def stage_timing(diags: dict[str, dict[str, str]]) -> list[tuple[str, str, float, float, int, int]]:
    """Rows (node, stage, median ms, p99 ms, processed, dropped); frontends merged into one row
    per stage (median of the cameras' medians, max of their p99)."""
    groups: dict[str, list[dict[str, str]]] = {}
    for name, kv in sorted(diags.items()):
        key = "frontend" if name.endswith("/frontend") else name.strip("/")
        groups.setdefault(key, []).append(kv)
    rows = []
    for key, kvs in groups.items():
        label = f"{key} (x{len(kvs)})" if len(kvs) > 1 else key
        processed = sum(int(kv.get("frames_processed", 0)) for kv in kvs)
        dropped = sum(int(kv.get("frames_dropped", 0)) for kv in kvs)
        stages = sorted({k.split("/")[1] for kv in kvs for k in kv if k.startswith("time_ms/")})
        for st in stages:
            med = [float(kv[f"time_ms/{st}/median"]) for kv in kvs if f"time_ms/{st}/median" in kv]
            p99 = [float(kv[f"time_ms/{st}/p99"]) for kv in kvs if f"time_ms/{st}/p99" in kv]
            rows.append((label, st, float(np.median(med)), float(np.max(p99)), processed, dropped))
    return rows


def format_timing(rows) -> str:
    head = ("node", "stage", "median ms", "p99 ms", "processed", "dropped")
    body = [(n, s, f"{m:.2f}", f"{p:.2f}", str(a), str(d)) for n, s, m, p, a, d in rows]
    widths = [max(len(r[i]) for r in [head] + body) for i in range(len(head))]

    def fmt(r: tuple[str, ...] | list[str]) -> str:
        return "  ".join(c.ljust(w) if i < 2 else c.rjust(w) for i, (c, w) in enumerate(zip(r, widths)))

    return "\n".join([fmt(head), "  ".join("-" * w for w in widths)] + [fmt(r) for r in body])


def latencies_ms(image_t: dict[int, int], poses_t: dict[int, int]) -> np.ndarray:
    return np.array([(poses_t[s] - t) / 1e6 for s, t in image_t.items() if s in poses_t])


def dropped_counters(diags: dict[str, dict[str, str]]) -> dict[str, dict[str, str]]:
    """Per node: its non-zero drop / missing-camera counters."""
    out = {}
    for name, kv in diags.items():
        d = {
            k: v
            for k, v in kv.items()
            if (k.startswith(("dropped/", "missing/")) or k == "frames_dropped") and v != "0"
        }
        if d:
            out[name] = d
    return out


def print_run_summary(
    rate: float, n: int, lat: np.ndarray, dropped: list[int], diags: dict[str, dict[str, str]], run: GraphRun
) -> None:
    """Latency, dropped frames (and the nodes' drop counters), machine load, exit codes."""
    print(
        f"\nend-to-end latency (image received -> /maem/poses received, {len(lat)} frames): "
        + (
            f"median {np.median(lat):.0f} ms, p99 {np.percentile(lat, 99):.0f} ms, max {lat.max():.0f} ms"
            if len(lat)
            else "no frame completed"
        )
    )
    print(
        f"frames dropped: {len(dropped)} of {n} played frames have no /maem/poses"
        + (f" (rate {rate:g}; try a lower --rate)" if dropped and not run.crashed else "")
    )
    for name, d in sorted(dropped_counters(diags).items()):
        print(f"  {name}: " + ", ".join(f"{k}={v}" for k, v in sorted(d.items())))
    print(f"machine: {os.cpu_count()} cores, load average {os.getloadavg()[0]:.1f} (1 min, all users)")
    print(
        f"replay wall time: {run.wall_s:.1f} s; processes: "
        + ", ".join(f"{k}={'killed' if v is None else v}" for k, v in run.exit_codes.items())
    )


# ---------------------------------------------------------------------------------------------
# pictures
# ---------------------------------------------------------------------------------------------
def snapshot_png(path: Path, demo: DemoBag, rig, cam: str, stamp: int, pred: Any) -> Path:
    """Raw camera image at ``stamp`` with GT (white) and estimated skeletons (colour = track id)
    projected through the camera's distortion."""
    msg = next(bagio.read_messages(demo.path, [image_topic(cam)], start_ns=stamp, stop_ns=stamp + 1)).decode()
    img: np.ndarray = cv2.imdecode(  # type: ignore[assignment]  # the demo bag's own JPEGs
        np.asarray(msg.data, np.uint8), cv2.IMREAD_COLOR
    )
    camera = rig[cam]

    def draw(joints: np.ndarray, colour, thick: int, label: str | None) -> None:
        uv = camera.project(joints)
        ok = np.isfinite(uv).all(-1)
        for a, b in SPORTCENTER_13.bones:
            if ok[a] and ok[b]:
                cv2.line(
                    img,
                    tuple(int(v) for v in uv[a]),
                    tuple(int(v) for v in uv[b]),
                    colour,
                    thick,
                    cv2.LINE_AA,
                )
        if label and ok.any():
            top = uv[ok][np.argmin(uv[ok][:, 1])]
            cv2.putText(
                img,
                label,
                (int(top[0]) - 10, int(top[1]) - 10),
                cv2.FONT_HERSHEY_SIMPLEX,
                0.6,
                colour,
                2,
                cv2.LINE_AA,
            )

    for g in demo.gt.get(stamp, []):
        draw(g, (255, 255, 255), 4, None)
    for pid, joints in zip(pred.ids, pred.joints):
        tracked = int(pid) != UNTRACKED_ID
        draw(
            joints, id_bgr8(int(pid)) if tracked else (128, 128, 128), 2, f"#{int(pid)}" if tracked else None
        )
    title = (
        f"{cam}  stamp {stamp}  "
        + ("white = ground truth, " if demo.gt else "")
        + "colour = /maem/poses (track id)"
    )
    (tw, th), _ = cv2.getTextSize(title, cv2.FONT_HERSHEY_SIMPLEX, 0.8, 2)
    cv2.rectangle(img, (10, 10), (30 + tw, 30 + th), (0, 0, 0), cv2.FILLED)
    cv2.putText(img, title, (20, 20 + th), cv2.FONT_HERSHEY_SIMPLEX, 0.8, (255, 255, 255), 2, cv2.LINE_AA)
    if not cv2.imwrite(str(path), img):
        raise ValueError(f"snapshot {str(path)!r}: cv2.imwrite failed")
    return path


def write_pictures(out: Path, demo: DemoBag, rig, stamps: Sequence[int], poses: dict[int, Any]) -> list[Path]:
    """snapshot_<cam>.png and court.png at the middle played frame that has poses (and ground
    truth, when the bag has any; a bag without it, e.g. a real capture, gets a snapshot of every
    camera)."""
    with_poses = [s for s in stamps if s in poses and (s in demo.gt or not demo.gt)]
    if not with_poses:
        return []
    stamp = with_poses[len(with_poses) // 2]
    pred = poses[stamp]
    cams = demo.cameras if not demo.gt else demo.cameras[:1]
    frame = demo.stamps.index(stamp)
    gt = demo.gt.get(stamp, np.zeros((0, SPORTCENTER_13.num_joints, 3)))
    return [snapshot_png(out / f"snapshot_{cam}.png", demo, rig, cam, stamp, pred) for cam in cams] + [
        plot_court(out / "court.png", frame, gt, pred.joints, rig)
    ]
