"""maem-eval's options (tools/eval/evaluate.py runs them): the parser and its epilog, which
defines every metric the report prints."""

from __future__ import annotations

import argparse
from pathlib import Path

DESCRIPTION = "maem-eval: run MAEM association + triangulation offline on a scene folder and score it."

EPILOG = """\
Metrics (VoxelPose / Panoptic form, as in the MAEM paper), over the evaluated frames, in the
sportcenter_13 joints (estimated MHR70 poses are mapped with [0,5,6,7,8,62,41,9,10,11,12,13,14]):
  GT person      a person of gt.npz with at least one joint whose mask is 1 in that frame;
                 joints with mask 0 are excluded from every error below.
  MPJPE          mean over a person's GT-masked joints of the Euclidean distance between the
                 estimated and GT joint (world metres, reported in mm); untriangulated (NaN)
                 joints of a prediction are ignored.
  PA-MPJPE       MPJPE after aligning the prediction to the GT with the least-squares
                 similarity (rotation, translation, uniform scale; Umeyama); a matched
                 pair with fewer than 3 common joints has none and is left out of PA-MPJPE.
  matching       per frame, Hungarian assignment of predictions to GT persons on MPJPE; only
                 pairs with MPJPE < 500 mm count as matched. MPJPE / PA-MPJPE mean and median
                 are taken over all matched pairs of the sequence.
  Recall@500     matched GT persons / all GT persons.
  AP@d           d = 75, 100, 125, 150 mm: all predictions of the sequence sorted by score
                 (descending, stable); each is a true positive when its closest not-yet-taken
                 GT person of its frame has MPJPE < d (that person is then taken), else a
                 false positive. After each prediction i: recall_i = TP_i / #GT persons,
                 precision_i = TP_i / (TP_i + FP_i); precision is replaced by its monotone
                 envelope max_{k>=i} precision_k; with recall padded by 0 in front and 1
                 behind and precision by 0 on both ends, AP = sum over the i where recall
                 changes of (r_{i+1} - r_i) * p_{i+1} (VoxelPose / Panoptic area under PR).
  assoc ms       wall-clock time of the association stage per frame (median), this machine.
In --json, recall and AP are fractions (0..1), errors in mm; the table shows percentages.

Input handling (never a crash mid-sequence; every case is counted and reported at the end):
  a camera with no dets/<view>/ folder is left out of every frame; a missing or corrupt
  (unreadable, mis-shaped, NaN) npz leaves that view out of that frame; a frame with no
  readable view at all, or beyond the end of gt.npz, is not evaluated; a frame on which
  association/triangulation raises is evaluated with no predictions (its people are missed).
--oracle adds a row whose association is the ground truth (det_ids.npz, as maem-sim writes it:
                 every kept detection grouped with its true person, people seen by >= k_min
                 cameras) with the same triangulation: the ceiling of any association.
--explain      per configuration, the first cause of every lost GT person-frame (needs
                 det_ids.npz), in pipeline order: frontend (< k_min cameras detect it),
                 reproj_gate / epipolar_gate / cost_cap (its surviving true pairs connect
                 < k_min views), wrong_match (a cluster mixes it with another person), merge
                 (its detections stay in several clusters), conflict (conflict removal), k_min,
                 triangulation (a pure cluster exists, no pose matched). Counts sum to the
                 lost person-frames.
--explain-tracks  per configuration, the first cause of every published pose more than 150 mm
                 from its matched GT person or matched to none (needs det_ids.npz), in order:
                 stale_or_duplicate (right for its members' person, whom another pose holds),
                 prediction (its own triangulation is close, the joint filter's output is not),
                 wrong_track (a track's cluster holds another person's detection),
                 weak_two_view (a pure cluster of two views), wrong_new_cluster (the
                 cross-view association mixed people), triangulation, not_in_gt (bystanders).
--pred writes pose (F,K,13,3) world metres in sportcenter_13 (NaN = joint not triangulated),
valid (F,K) bool, score (F,K), id (F,K) int64 track id (-1 = none: tentative track or no
prediction); F = scene frames considered, K = most people in one frame.
Identities: with temporal on (the params file's 'temporal', on when absent, or --temporal) ids
are the association's track ids (core/tracking/temporal.py), with temporal off those of the post-hoc 3D
tracker (core/tracking/tracks.py, the triangulation node's track_* params; also for the oracle row).
IDF1 / IDP / IDR and ID switches (core/metrics/identity.py: Ristani et al. 2016; CLEAR MOT switches)
are scored against the GT persons of gt.npz (column = identity), MPJPE < 500 mm as a match;
hypotheses matching no GT person of their frame (e.g. tracked referees) are left out ("players
only"; idf1_all_hyp keeps them). --explain breaks down the per-frame association, so it implies
--temporal off.
"""


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(
        prog="maem-eval",
        description=DESCRIPTION,
        epilog=EPILOG,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    p.add_argument("scene", type=Path, help="scene folder (cameras/, dets/, gt.npz)")
    p.add_argument(
        "--params",
        default="sportcenter.yaml",
        help="ROS params file the nodes use (sections 'association', 'triangulation'): a path "
        "or a shipped config name, e.g. config/humanm3.yaml (default sportcenter.yaml)",
    )
    p.add_argument("--json", type=Path, help="write the metrics (and ablation rows, skips) as JSON")
    p.add_argument("--plots", type=Path, help="write PNG plots to this folder")
    p.add_argument(
        "--plot-frame",
        type=int,
        default=None,
        help="scene frame for the top-down court plot (default: middle evaluated frame)",
    )
    p.add_argument(
        "--ablation",
        action="store_true",
        help="also run the paper's ablation rows (reproj only; mesh only; reproj + sparse; full)",
    )
    p.add_argument(
        "--oracle",
        action="store_true",
        help="also run the association from the ground truth (det_ids.npz): the ceiling",
    )
    p.add_argument(
        "--explain",
        action="store_true",
        help="print the first cause of every lost GT person-frame (needs det_ids.npz)",
    )
    p.add_argument(
        "--explain-tracks",
        action="store_true",
        help="print the first cause of every published pose more than 150 mm from its "
        "GT person or matched to none (needs det_ids.npz)",
    )
    p.add_argument("--pred", type=Path, help="write predictions (full configuration) to this npz")
    p.add_argument("--frames", type=int, default=None, help="evaluate only the first N frames")
    p.add_argument(
        "--rig",
        type=Path,
        default=None,
        help="evaluate with this rig instead of the scene's cameras/ (e.g. a "
        "calibrated one moved into the scene's frame)",
    )
    p.add_argument(
        "--temporal",
        choices=("on", "off"),
        default=None,
        help="track-assisted association on/off (default: the params file's 'temporal', "
        "on when absent; off with --explain); off = per-frame association + the "
        "post-hoc 3D tracker",
    )
    p.add_argument("--quiet", action="store_true", help="no progress bar")
    return p
