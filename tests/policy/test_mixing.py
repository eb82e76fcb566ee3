"""The fine-tuning sampler: every mini-batch holds exactly the configured share of each set."""

import pytest
import torch

from policy.mixing import MixedSampler
from policy.train import TrainConfig, train_policy
from storage import keys
from tests.policy.test_policy import _policy, _toy_data


@pytest.mark.parametrize(("ratio", "batch", "expected"), [(0.5, 256, 128), (0.5, 7, 4), (0.25, 64, 16), (1.0, 10, 10)])
def test_every_batch_holds_the_configured_share_of_each_set(ratio, batch, expected):
    sampler = MixedSampler(first=30, second=500, ratio=ratio)
    g = torch.Generator().manual_seed(0)
    for _ in range(20):
        idx = sampler(batch, g)
        assert idx.shape == (batch,) and idx.dtype == torch.int64
        assert int((idx < 30).sum()) == expected  # the first set's rows
        assert idx.min() >= 0 and idx.max() < 530
    # with replacement, uniform within each set: a small first set is seen whole
    seen = torch.cat([sampler(batch, g) for _ in range(200)])
    if expected:
        assert set(seen[seen < 30].tolist()) == set(range(30))


def test_the_same_seed_gives_the_same_batches():
    sampler = MixedSampler(10, 100)
    a = sampler(32, torch.Generator().manual_seed(3))
    b = sampler(32, torch.Generator().manual_seed(3))
    assert torch.equal(a, b)


@pytest.mark.parametrize(
    ("first", "second", "ratio", "message"),
    [
        (10, 10, 1.5, "ratio"),
        (0, 10, 0.5, "first set is empty"),
        (10, 0, 0.5, "second set is empty"),
        (-1, 5, 0.0, ">= 0"),
    ],
)
def test_impossible_mixes_are_refused(first, second, ratio, message):
    with pytest.raises(ValueError, match=message):
        MixedSampler(first, second, ratio)


def test_train_policy_draws_its_batches_from_the_sampler():
    data = _toy_data(chunk=8, horizon=2)
    n = data[keys.OBS].shape[0]
    policy = _policy("mlp", horizon=2, chunk=8)
    policy.fit_normalizers(data[keys.OBS], data[keys.ACTION])
    drawn = []
    inner = MixedSampler(first=5, second=n - 5, ratio=0.5)

    def sampler(batch, g):
        drawn.append(inner(batch, g))
        return drawn[-1]

    train_policy(
        policy, data, None, TrainConfig(steps=3, batch_size=16, warmup_steps=1), progress=False, sampler=sampler
    )
    assert len(drawn) == 3 and all(int((d < 5).sum()) == 8 for d in drawn)
