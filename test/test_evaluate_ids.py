"""maem-eval identities: --pred writes track ids, IDF1 / ID switches with temporal on and off."""
from __future__ import annotations

import numpy as np
import pytest
from helpers_scene import exact_scene
from test_evaluate import run_eval

from maem_ros.core.interchange import SceneFolder
from maem_ros.tools.eval import evaluate


@pytest.mark.parametrize("temporal", ["on", "off"])
def test_pred_ids_follow_each_person_and_score_idf1(tmp_path, capsys, temporal):
    folder = exact_scene(tmp_path / "scene", frames=8)
    pred = tmp_path / "pred.npz"
    rep = run_eval(folder.root, tmp_path, "humanm3.yaml", "--pred", str(pred), "--temporal", temporal)
    out = capsys.readouterr().out
    assert ("track-assisted association" if temporal == "on" else "post-hoc 3D tracker") in out
    assert rep["recall"] == 1.0 and rep["id_switches"] == 0
    # frames 0 and 1 are tentative (confirm after 3 hits): 18 of 24 GT person-frames carry an id
    assert rep["idp"] == 1.0 and rep["idr"] == pytest.approx(18 / 24)
    assert rep["idf1"] == pytest.approx(2 * 18 / (24 + 18))
    with np.load(pred) as z:
        ids, pose = z["id"], z["pose"]
        assert ids.shape == (8, 3) and ids.dtype == np.int64
        assert np.all(ids[:2] == -1) and np.all(ids[2:] >= 0)
        gt = SceneFolder(folder.root).gt()[0][..., :3]
        owner = {}  # track id -> GT person, must never change
        for f in range(2, 8):
            d = np.linalg.norm(pose[f][:, None] - gt[f][None], axis=-1).mean(-1)
            for k, person in enumerate(d.argmin(1)):
                assert owner.setdefault(int(ids[f, k]), int(person)) == person
        assert sorted(owner.values()) == [0, 1, 2]


def test_bad_temporal_value_exits_2(tmp_path, capsys):
    with pytest.raises(SystemExit) as e:
        evaluate.main([str(tmp_path), "--temporal", "maybe"])
    assert e.value.code == 2 and "--temporal" in capsys.readouterr().err
