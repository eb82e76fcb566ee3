"""Identifying a policy's held-out and pretraining episodes: by their steps, or by the recipe that
recorded them again; never by their files' sizes."""

import numpy as np
import pytest
import torch

from policy.config import DiffusionPolicyConfig
from policy.diffusion_policy import DiffusionPolicy
from policy.finetune import FinetuneDataError, pretraining_split
from policy.heldout import HeldOutError, check_held_out, episode_digest, recorded_by
from sim.demos import DemoRecipe
from storage import keys
from storage.dataset import DatasetConfig, load_dataset
from storage.episodes import EpisodeWriter

OBS_DIM = 5
RECIPE = DemoRecipe("unit", 12, seed=0, pos_noise=0.01, rot_noise=0.15)
NOISE = {"pos": 0.01, "rot": 0.15}


def _record(folder, seeds, *, noise=NOISE, shift=0.0, failed=(), task="unit"):
    """One episode per seed, its steps a function of the seed alone (plus ``shift``)."""
    folder.mkdir(parents=True, exist_ok=True)
    for s in seeds:
        rng = np.random.default_rng(s)
        meta = {"task": task, "seed": s, "source": keys.SOURCE_EXPERT, "execution_noise": noise}
        with EpisodeWriter(folder / f"unit_seed{s:06d}.mcap", meta, object_names=[]) as w:
            n, ok = 6 + s % 3, s not in failed
            for t in range(n):
                act = np.r_[rng.uniform(-0.1, 0.1, 3) + shift, [0, 1, 0, -1, 0, 0], [1.0 if t > 2 else -1.0]]
                quat = np.array([1.0, 0, 0, 0])
                w.write_step(
                    t, rng.normal(size=OBS_DIM), act, act[:3], quat, 0.04, ok and t == n - 1, keys.SOURCE_EXPERT, {}
                )
            w.finish(ok, n, "success" if ok else "horizon")
    return folder


def _trained(folder, recipe=RECIPE):
    """A tiny policy and the config.json ``hitl train`` would write for ``folder``."""
    ds = load_dataset(folder, DatasetConfig())
    torch.manual_seed(0)
    p = DiffusionPolicy(
        DiffusionPolicyConfig(obs_dim=OBS_DIM, network="mlp", mlp_hidden=16, step_embed_dim=8, obs_encoder_dims=(8,))
    )
    p.fit_normalizers(ds.obs, ds.actions)
    train, val = ds.split()
    info = {
        "dataset": {
            "train_episodes": [ds.names[i] for i in train],
            "val_episodes": [ds.names[i] for i in val],
            "val_episode_digest": {ds.names[i]: episode_digest(ds, i) for i in val},
            "recipe": recipe.to_dict() if recipe else None,
        }
    }
    return p, info


def test_the_digest_is_the_steps_not_the_file(tmp_path):
    a = load_dataset(_record(tmp_path / "a", [3]), DatasetConfig())
    b = load_dataset(_record(tmp_path / "b", [3]), DatasetConfig())  # recorded again: other timestamps
    c = load_dataset(_record(tmp_path / "c", [3], shift=1e-6), DatasetConfig())
    assert episode_digest(a, 0) == episode_digest(b, 0) != episode_digest(c, 0)
    assert episode_digest(a, 0).startswith("sha256:")


def test_provenance_is_the_recipes_task_seeds_expert_and_noise():
    meta = {"task": "unit", "seed": 4, "source": keys.SOURCE_EXPERT, "execution_noise": NOISE}
    assert recorded_by(meta, RECIPE)
    assert not recorded_by(meta | {"seed": 12}, RECIPE)  # outside the recipe's seeds
    assert not recorded_by(meta | {"task": "other"}, RECIPE)
    assert not recorded_by(meta | {"execution_noise": None}, RECIPE)  # recorded without the noise
    assert not recorded_by(meta | {"source": keys.SOURCE_OPERATOR}, RECIPE)
    assert recorded_by(meta | {"execution_noise": None}, DemoRecipe("unit", 12))


def test_held_out_episodes_are_identified_by_content_or_by_their_recipe(tmp_path):
    seeds = range(12)
    policy, info = _trained(_record(tmp_path / "orig", seeds))
    # the same steps: identical
    same = load_dataset(_record(tmp_path / "same", seeds), DatasetConfig())
    val = [same.names.index(n) for n in info["dataset"]["val_episodes"]]
    assert check_held_out(same, val, info).to_dict() == {"identical": len(val), "by_recipe": 0, "unverified": 0}
    # recorded again by the recipe on a machine whose physics differs in the last digits: re-recorded
    other = load_dataset(_record(tmp_path / "other", seeds, shift=1e-6), DatasetConfig())
    assert check_held_out(other, val, info).by_recipe == len(val)
    # the same names, recorded without the recipe's noise: refused, whatever the files
    plain = load_dataset(_record(tmp_path / "plain", seeds, noise=None, shift=1e-6), DatasetConfig())
    with pytest.raises(HeldOutError, match="not the ones the policy was trained and validated on"):
        check_held_out(plain, val, info)
    # a policy without a recipe accepts only its own steps
    no_recipe = {"dataset": {**info["dataset"], "recipe": None}}
    with pytest.raises(HeldOutError, match="its steps differ from the ones the policy held out"):
        check_held_out(other, val, no_recipe)
    # a policy that recorded neither (older) trusts the names
    old = {"dataset": {"val_episodes": info["dataset"]["val_episodes"]}}
    assert check_held_out(other, val, old).unverified == len(val)


def test_the_pretraining_split_leaves_out_what_failed_when_recorded_again(tmp_path):
    seeds = range(12)
    policy, info = _trained(_record(tmp_path / "orig", seeds))
    train_names = info["dataset"]["train_episodes"]
    lost = train_names[0]
    lost_seed = int(lost.rsplit("seed", 1)[1].split(".")[0])
    # recorded again elsewhere: other digits, and one episode the expert failed there
    again = _record(tmp_path / "again", seeds, shift=1e-6, failed=(lost_seed,))
    policy_info = {"dataset": {**info["dataset"]}}
    # 1 of 12 is over MAX_LEFT_OUT (5%): refused, saying what is missing and why
    with pytest.raises(FinetuneDataError, match=f"{lost}: unsuccessful"):
        pretraining_split(policy, policy_info, again)
    import policy.finetune as finetune

    with pytest.MonkeyPatch.context() as mp:
        mp.setattr(finetune, "MAX_LEFT_OUT", 0.1)
        split = pretraining_split(policy, policy_info, again)
    assert split.left_out == {lost: "unsuccessful when recorded again"}
    assert split.train_names == [n for n in train_names if n != lost]
    assert split.checked["by_recipe"] == len(seeds) - 1
    rows = sum(6 + int(n.rsplit("seed", 1)[1].split(".")[0]) % 3 for n in split.train_names)
    assert len(split.train[keys.OBS]) == rows
    # without a recipe the folder cannot have been recorded again: a missing episode is refused
    with pytest.raises(FinetuneDataError, match="is this the folder it was trained from"):
        pretraining_split(policy, {"dataset": {**info["dataset"], "recipe": None}}, again)
    # a named episode whose file is gone is refused, recipe or not
    (again / lost).unlink()
    with pytest.raises(FinetuneDataError, match="no such file"):
        pretraining_split(policy, policy_info, again)
