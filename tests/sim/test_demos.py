"""Recording demonstrations again from the recipe a folder (and a policy trained on it) records."""

from __future__ import annotations

import json

import numpy as np
import pytest

from sim.demos import RECIPE_FILE, DemoRecipe, ensure_demos, read_recipe, record_demos
from sim.rollout import ExecutionNoise
from storage.episodes import read_episode
from storage.paths import portable


def test_a_recorded_folder_says_how_to_record_it_again_and_is_recorded_again_seed_for_seed(tmp_path):
    out = tmp_path / "lift"
    paths, _ = record_demos("lift-cube", 2, out, seed=3, progress=False, noise=ExecutionNoise(0.01, 0.15))
    recipe = read_recipe(out)
    assert recipe == DemoRecipe("lift-cube", 2, seed=3, pos_noise=0.01, rot_noise=0.15)
    doc = json.loads((out / RECIPE_FILE).read_text())
    assert doc["command"].startswith("hitl demos --task lift-cube --episodes 2 --seed 3 --pos-noise 0.01")
    assert doc["command"].endswith(f"--out {portable(out)}")

    first = read_episode(paths[1])
    paths[1].unlink()
    assert ensure_demos(recipe, out, progress=False) == [paths[1]]
    again = read_episode(paths[1])
    np.testing.assert_array_equal(again.obs, first.obs)
    np.testing.assert_array_equal(again.actions, first.actions)
    assert again.outcome == first.outcome
    assert ensure_demos(recipe, out, progress=False) == []  # complete: nothing recorded
    assert not any(p.name.endswith(".recording") for p in tmp_path.iterdir())  # no staging folder is left


def test_recording_in_two_processes_gives_the_episodes_one_process_gives(tmp_path):
    recipe = DemoRecipe("lift-cube", 3, seed=11, pos_noise=0.01, rot_noise=0.15)
    one = ensure_demos(recipe, tmp_path / "one", progress=False)
    two = ensure_demos(recipe, tmp_path / "two", progress=False, workers=2)
    assert [p.name for p in two] == [p.name for p in one]
    for a, b in zip(one, two, strict=True):
        ea, eb = read_episode(a), read_episode(b)
        np.testing.assert_array_equal(ea.obs, eb.obs)
        np.testing.assert_array_equal(ea.actions, eb.actions)
    assert read_recipe(tmp_path / "two") == recipe
    with pytest.raises(ValueError, match="workers"):
        ensure_demos(recipe, tmp_path / "three", progress=False, workers=0)


def test_a_fresh_folder_is_recorded_whole_and_a_mixed_folder_keeps_no_recipe(tmp_path):
    out = tmp_path / "fresh" / "lift"
    recipe = DemoRecipe("lift-cube", 1, seed=5)
    [made] = ensure_demos(recipe, out, progress=False)
    assert made.name == "lift-cube_seed000005.mcap" and read_recipe(out) == recipe
    record_demos("lift-cube", 1, out, seed=9, progress=False)  # another run into the same folder
    assert read_recipe(out) is None  # no single recipe made it any more


@pytest.mark.parametrize(
    ("doc", "needle"),
    [
        ({"task": "lift-cube", "episodes": 0}, "episodes must be an integer >= 1"),
        ({"task": "lift-cube", "episodes": 2, "seed": -1}, "seed must be an integer >= 0"),
        ({"task": "lift-cube", "episodes": 2, "pos_noise": "x"}, "pos_noise must be a number"),
        ({"task": "lift-cube", "episodes": 2, "folder": "/elsewhere"}, "unknown fields"),
        ({"episodes": 2}, "task"),
        ([1, 2], "expected an object"),
    ],
)
def test_a_bad_recipe_is_refused_with_what_is_wrong(doc, needle):
    with pytest.raises(ValueError, match=needle):
        DemoRecipe.from_dict(doc)
