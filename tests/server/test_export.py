"""A served fleet's data as a LeRobotDataset: a takeover labelled over REST, its whole episode recorded,
exported with ``hitl export lerobot`` from the service's database and read back with Hugging Face
``datasets``."""

from __future__ import annotations

import json

import datasets
import httpx
import numpy as np
import pandas as pd

from hitl.cli import main
from server.auth import create_token
from server.db import SegmentRecord, make_engine, migrate, session_factory
from server.settings import RobotGroup, Settings
from storage import keys
from storage.episodes import read_episode
from tests.helpers import Service, free_port, tiny_policy_folder, wait_for


def _fleet(tmp_path):
    policy = tiny_policy_folder(tmp_path / "policy", "lift-cube", threshold=-1.0)  # asks at once
    settings = Settings(
        data_dir=tmp_path / "var",
        port=free_port(),
        robots=[RobotGroup(task="lift-cube", count=1, policy=policy)],
        control_hz=20,
        controller={"budget": 100},  # the takeover lasts until the hand-back
        recording={"episodes": True},
        console=False,
    )
    migrate(settings.db_url)
    sessions = session_factory(make_engine(settings.db_url))
    tokens = {role: create_token(sessions, f"{role}-1", role) for role in ("viewer", "operator", "admin")}
    return settings, sessions, {role: {"Authorization": f"Bearer {t}"} for role, t in tokens.items()}


def test_labels_over_rest_and_the_fleet_export_with_the_takeover_inside_its_episode(tmp_path, capsys):
    settings, sessions, h = _fleet(tmp_path)
    with Service(settings) as svc:
        api = svc.url + "/api/v1"
        robot = lambda: httpx.get(api + "/robots/0", headers=h["viewer"]).json()  # noqa: E731
        wait_for(lambda: robot()["mode"] == "waiting", 120)
        [request] = httpx.get(api + "/assistance", headers=h["viewer"]).json()
        assert httpx.post(api + "/robots/0/claim", headers=h["operator"]).status_code == 200
        sent = []
        for i in range(4):
            before = robot()["assisted_steps"]
            cmd = {"delta_pos": [0.0, 0.002 * (i + 1), 0.0], "delta_rot": [0.0, 0.0, 0.05], "gripper": 1.0}
            assert httpx.post(api + "/robots/0/command", json=cmd, headers=h["operator"]).status_code == 200
            sent.append(cmd)
            wait_for(lambda b=before: robot()["assisted_steps"] > b)
        assert httpx.post(api + "/robots/0/release", headers=h["operator"]).status_code == 200
        [segment] = httpx.get(api + "/segments", headers=h["viewer"]).json()
        sid = segment["id"]
        assert segment["label"] is None and segment["discarded"] is False  # unlabelled until an operator says
        # the request it answered, in the queue's numbers, and the paper's U then
        asked = ("signal", "score", "threshold", "reason")
        assert [segment[k] for k in asked] == [request[k] for k in asked] and isinstance(segment["paper_u"], float)

        # labels over REST: only what is sent changes; who and when are recorded
        patch = lambda body, role="operator", i=sid: httpx.patch(  # noqa: E731
            f"{api}/segments/{i}", json=body, headers=h[role]
        )
        r = patch({"label": "good", "note": "slid under the handle"})
        assert r.status_code == 200, r.text
        body = r.json()
        assert (body["label"], body["note"], body["labelled_by"], body["discarded"]) == (
            "good",
            "slid under the handle",
            "operator-1",
            False,
        )
        assert body["labelled_at"] is not None
        discarded = patch({"discarded": True}).json()
        assert discarded["discarded"] is True and (discarded["label"], discarded["note"]) == ("good", body["note"])
        assert discarded["labelled_at"] >= body["labelled_at"]
        assert patch({"label": None}).json()["label"] is None  # null removes the verdict
        assert patch({"label": "bad"}).json()["label"] == "bad"
        assert patch({"label": "good"}, role="viewer").status_code == 403
        assert patch({}).status_code == 422  # nothing to change
        assert patch({"label": "meh"}).status_code == 422
        assert patch({"discarded": "yes"}).status_code == 422 and patch({"discarded": 1}).status_code == 422
        assert patch({"note": "x" * 501}).status_code == 422
        assert patch({"label": "good", "extra": 1}).status_code == 422
        assert patch({"label": "good"}, i=999_999).status_code == 404
        listed = httpx.get(api + "/segments", headers=h["viewer"]).json()[0]
        assert (listed["label"], listed["discarded"], listed["note"]) == ("bad", True, "slid under the handle")

        # the episode ends (a reset), so it is exported whole
        assert httpx.post(api + "/robots/0/reset", headers=h["admin"]).status_code == 200
        wait_for(lambda: any(e["outcome"] for e in httpx.get(api + "/episodes", headers=h["viewer"]).json()), 60)

    with sessions() as s:
        assert s.get(SegmentRecord, sid).labelled_by == "operator-1"
    # the episode's file records the paper's U at each policy step, beside the asking signal's score
    recorded = read_episode(settings.data_dir / "episodes" / f"robot000_ep{segment['episode_id']:06d}.mcap")
    scored = [e for e, source in zip(recorded.extras, recorded.sources, strict=True) if source == keys.SOURCE_POLICY]
    assert scored and all(isinstance(e[keys.STEP_PAPER_U], float) and keys.STEP_SCORE in e for e in scored)
    root = tmp_path / "export"
    store = ["--data-dir", str(settings.data_dir), "--database-url", settings.db_url]
    episode = ["--episode", str(segment["episode_id"])]  # the attempt with the takeover (the next one ran on)
    assert main(["export", "lerobot", str(root), *store, "--task", "lift-cube", *episode, "--quiet"]) == 0
    report = json.loads(capsys.readouterr().out)
    assert report["kinds"] == {"episode": 1}, report
    files = sorted(str(p) for p in root.glob("data/chunk-*/file-*.parquet"))
    frames = datasets.load_dataset("parquet", data_files=files, split="train").with_format("numpy")[:]
    operator = frames["intervention"]
    assert operator.sum() == len(sent)  # the takeover's steps, inside the whole attempt
    assert len(frames["index"]) > len(sent)  # and the policy's before it
    commands = frames["operator.command"][operator]
    assert np.allclose(commands[:, :3], [c["delta_pos"] for c in sent], atol=1e-6)
    assert np.allclose(commands[:, 3:6], [c["delta_rot"] for c in sent], atol=1e-6) and np.allclose(commands[:, 6], 1)
    assert (frames["takeover.id"][operator] == sid).all() and (frames["takeover.id"][~operator] == -1).all()
    assert (frames["takeover.label"][operator] == -1).all() and frames["takeover.discarded"][operator].all()
    policy_steps = frames["action_source"] == keys.SOURCES.index(keys.SOURCE_POLICY)
    assert policy_steps.any() and frames["asking.scored"][policy_steps].all()
    # the asking signal's score and threshold, as the request that asked for help showed them
    assert np.allclose(frames["asking.threshold"][frames["asking.scored"]], request["threshold"])
    assert np.isclose(frames["asking.score"][frames["asking.scored"]], request["uncertainty"], rtol=1e-5).any()
    assert (frames["policy_version"] >= 1).all()
    info = json.loads((root / "meta" / "info.json").read_text())
    assert info["codebase_version"] == "v3.0" and info["total_frames"] == len(frames["index"])
    # each takeover's label comes with the request it answered
    [episodes_file] = (root / "meta" / "episodes").glob("chunk-*/file-*.parquet")
    [episode_row] = pd.read_parquet(episodes_file).to_dict("records")
    takeover = json.loads(episode_row["hitl/takeovers"])[str(sid)]
    assert takeover["request"] == {k: segment[k] for k in (*asked, "paper_u")}

    # the takeover alone
    alone = tmp_path / "alone"
    assert main(["export", "lerobot", str(alone), *store, "--takeovers-only", "--quiet"]) == 0
    assert json.loads(capsys.readouterr().out)["kinds"] == {"takeover": 1}
    frames = datasets.load_dataset(
        "parquet", data_files=sorted(str(p) for p in alone.glob("data/*/*.parquet")), split="train"
    ).with_format("numpy")[:]
    assert len(frames["index"]) == len(sent) and frames["intervention"].all()
    # an unknown lineage is a clear error
    assert main(["export", "lerobot", str(tmp_path / "none"), *store, "--lineage", "nope", "--quiet"]) == 2
    assert "no policy named 'nope'" in capsys.readouterr().err
