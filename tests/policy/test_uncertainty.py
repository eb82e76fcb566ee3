import numpy as np
import pytest
import torch

from policy.gmm import fit_mixtures, fit_numba, fit_sklearn, fit_torch
from policy.gmm_numba import fit_all
from policy.uncertainty import (
    UncertaintyConfig,
    UncertaintyEstimator,
    mixture_variance,
    mode_divergence,
    sample_ball,
)

CENTER = torch.full((3, 10), 0.5)
SIGMA = 0.02


def _gaussian_eps(mus: torch.Tensor):
    """ε of a Gaussian mixture with modes at ``mus`` (M, 3) and std SIGMA: ε = -σ ∇log p(x)."""

    def eps_fn(obs, actions, k):
        pos = actions[..., :3]
        d = pos[..., None, :] - mus  # (..., M, 3)
        w = torch.softmax(-(d**2).sum(-1) / (2 * SIGMA**2), dim=-1)
        out = torch.zeros_like(actions)
        out[..., :3] = (w[..., None] * d).sum(-2) / SIGMA
        return out

    return eps_fn


ONE = _gaussian_eps(torch.tensor([[0.51, 0.50, 0.49]]))
# two modes on opposite sides of the sample ball (radius 0.05 around 0.5), each 0.1 beyond its edge
TWO = _gaussian_eps(torch.tensor([[0.5, 0.65, 0.5], [0.5, 0.35, 0.5]]))


@pytest.mark.parametrize("backend", ["numba", "torch", "sklearn"])
def test_single_gaussian_field_has_no_divergence(backend):
    out = UncertaintyEstimator(UncertaintyConfig(backend=backend))(ONE, None, CENTER)
    assert out.fit.n.tolist() == [1, 1, 1]
    assert torch.all(out.D.abs() < 1e-9)
    assert torch.all(torch.isfinite(out.U)) and torch.all(out.U > 0)  # the within-mode variance remains


@pytest.mark.parametrize("backend", ["numba", "torch", "sklearn"])
def test_two_separated_gaussians_score_clearly_higher(backend):
    est = UncertaintyEstimator(UncertaintyConfig(backend=backend))
    one, two = est(ONE, None, CENTER), est(TWO, None, CENTER)
    assert torch.all(two.fit.n >= 2)
    assert torch.all(two.D > 0.5)
    assert torch.all(two.U > one.U + 0.5)


@pytest.mark.parametrize("backend", ["numba", "torch", "sklearn"])
@pytest.mark.parametrize("criterion", ["bic", "likelihood"])
def test_every_backend_and_criterion_scores_without_nan(backend, criterion):
    cfg = UncertaintyConfig(backend=backend, criterion=criterion, num_samples=64)
    out = UncertaintyEstimator(cfg)(TWO, None, CENTER)
    r = out.robot(0)
    assert r.samples.shape == (64, 3) and r.vectors.shape == (64, 3) and r.labels.shape == (64,)
    assert r.means.shape == (r.n, 3) and r.weights.shape == (r.n,)
    assert np.isclose(r.weights.sum(), 1.0) and set(np.unique(r.labels)) <= set(range(r.n))
    assert np.all(np.linalg.norm(r.samples - 0.5, axis=1) <= 0.05 + 1e-9)
    assert np.isfinite([r.D, r.var_g, r.U]).all()
    if criterion == "likelihood":
        # raw likelihood never prefers fewer modes (up to EM noise), which is why bic is the default
        assert r.n >= 3


def _blobs(count: int = 40, seed: int = 0) -> tuple[torch.Tensor, list[int]]:
    """(count, 128, 3) samples of 1, 2 or 3 separated blobs each, and each row's blob count."""
    g = torch.Generator().manual_seed(seed)
    blobs, counts = [], []
    for i in range(count):
        n = i % 3 + 1
        centres = torch.randn((n, 3), generator=g) * 2
        lab = torch.randint(0, n, (128,), generator=g)
        blobs.append(centres[lab] + 0.2 * torch.randn((128, 3), generator=g))
        counts.append(n)
    return torch.stack(blobs).double(), counts


@pytest.mark.parametrize("fit", [fit_torch, fit_numba], ids=["torch", "numba"])
def test_backends_agree_with_sklearn_on_seeded_synthetic_data(fit):
    x, _ = _blobs()
    a, b = fit(x, 4, "bic", seed=0), fit_sklearn(x, 4, "bic", seed=0)
    assert (a.n == b.n).double().mean() >= 0.95
    same = a.n == b.n
    ua = mode_divergence(a.means, a.n) + 0.1 * mixture_variance(x, a.labels, a.weights)
    ub = mode_divergence(b.means, b.n) + 0.1 * mixture_variance(x, b.labels, b.weights)
    assert torch.allclose(ua[same], ub[same], atol=0.02)
    # the selected fits reach the same likelihood (other n may settle in different local optima)
    rows = torch.arange(len(x))[same]
    ll_a, ll_b = a.log_likelihood[rows, a.n[same] - 1], b.log_likelihood[rows, b.n[same] - 1]
    torch.testing.assert_close(ll_a, ll_b, rtol=1e-3, atol=0.5)


def test_numba_finds_the_blobs_and_sklearn_s_means():
    x, counts = _blobs()
    a, b = fit_numba(x, 4, "bic", seed=0), fit_sklearn(x, 4, "bic", seed=0)
    assert (a.n == b.n).double().mean() >= 0.95
    assert (a.n == torch.tensor(counts)).double().mean() >= 0.95
    # for the selected n both find the same optimum on separated blobs: same likelihood, same means
    rows = torch.arange(len(x))
    same = a.n == b.n
    for i in rows[same].tolist():
        n = int(a.n[i])
        ma, mb = a.means[i, :n], b.means[i, :n]
        dist = torch.cdist(ma, mb)  # the two back ends may order the modes differently
        assert dist.min(dim=1).values.max() < 0.01  # blobs 2 apart, 0.2 wide: the same modes


def test_numba_fit_of_a_robot_does_not_depend_on_its_batch():
    """Unstructured vectors, where the over-split fits (n > 1) end wherever their seeding sends them: a
    robot's fits are still the same alone and in a batch, exactly."""
    x = torch.randn((6, 64, 3), generator=torch.Generator().manual_seed(2), dtype=torch.float64)
    whole = fit_all(x.numpy(), 4, seed=3)
    for i in (0, 4):
        alone = fit_all(x[i : i + 1].numpy(), 4, seed=3)
        for key in ("means", "weights", "labels", "log_likelihood", "em_iterations"):
            np.testing.assert_array_equal(alone[key][0], whole[key][i])
    other = fit_all(x[4:5].numpy(), 4, seed=4)  # and the seed matters there
    assert not np.array_equal(other["labels"][0, 1:], whole["labels"][4, 1:])


def test_numba_fits_stop_on_their_own():
    """Each candidate fit runs its own EM iterations: a single blob converges at once for n = 1, while the
    over-split fits of the same data keep iterating (the batched torch EM runs all until the last stops)."""
    x, counts = _blobs(9)
    iters = fit_all(x.numpy(), 4)["em_iterations"]
    assert (iters[:, 0] <= 3).all()  # one Gaussian: the first M-step is already the optimum
    assert iters.max() > iters[:, 0].max()
    assert len(np.unique(iters)) > 2


def test_auto_backend_is_numba_on_the_cpu():
    x, _ = _blobs(4)
    auto = fit_mixtures(x, 4, "bic", "auto", seed=1)
    numba = fit_numba(x, 4, "bic", seed=1)
    assert torch.equal(auto.n, numba.n) and torch.equal(auto.labels, numba.labels)


def test_torch_backend_is_deterministic():
    x = torch.randn(8, 128, 3, generator=torch.Generator().manual_seed(1)).double()
    a, b = fit_torch(x, 4, seed=3), fit_torch(x, 4, seed=3)
    assert torch.equal(a.labels, b.labels) and torch.equal(a.means, b.means)
    e1 = UncertaintyEstimator(UncertaintyConfig(seed=5))(TWO, None, CENTER)
    e2 = UncertaintyEstimator(UncertaintyConfig(seed=5))(TWO, None, CENTER)
    assert torch.equal(e1.U, e2.U) and torch.equal(e1.samples, e2.samples)


def test_score_golden_values():
    means = torch.tensor(
        [
            [[1.0, 0, 0], [-1.0, 0, 0], [0, 0, 0]],  # opposite: D = 2
            [[1.0, 0, 0], [0, 1.0, 0], [0, 0, 1.0]],  # orthogonal: D = 1
            [[1.0, 2, 3], [9.0, 9, 9], [9.0, 9, 9]],
        ]
    ).double()  # one mode: D = 0
    d = mode_divergence(means, torch.tensor([2, 3, 1]))
    torch.testing.assert_close(d, torch.tensor([2.0, 1.0, 0.0], dtype=torch.float64))
    v = torch.tensor([[[0.0, 0, 0], [2, 0, 0], [10, 0, 0], [10, 4, 0]]]).double()
    labels = torch.tensor([[0, 0, 1, 1]])
    weights = torch.tensor([[0.25, 0.75]]).double()
    # mode 0: variance of {0, 2} along x = 1; mode 1: variance of {0, 4} along y = 4
    torch.testing.assert_close(mixture_variance(v, labels, weights), torch.tensor([0.25 * 1 + 0.75 * 4]).double())


def test_ball_samples_fill_the_ball_uniformly():
    s = sample_ball(1, 20000, 0.05, torch.Generator().manual_seed(0))[0]
    r = s.norm(dim=-1)
    assert float(r.max()) <= 0.05
    # uniform in volume: a quarter of the radius... P(r < R/2) = 1/8
    assert abs(float((r < 0.025).double().mean()) - 0.125) < 0.01
    assert float(s.mean(0).abs().max()) < 2e-3


def test_probe_holds_other_dimensions_and_the_chunk():
    seen = {}

    def eps_fn(obs, actions, k):
        seen["a"], seen["k"] = actions, k
        return torch.zeros_like(actions)

    center = torch.rand(2, 10)
    UncertaintyEstimator(UncertaintyConfig(num_samples=16))(eps_fn, None, center, chunk=8)
    a = seen["a"]
    assert a.shape == (2, 16, 8, 10) and seen["k"] == 0
    torch.testing.assert_close(a[..., 3:], center[:, None, None, 3:].expand(2, 16, 8, 7))
    torch.testing.assert_close(a[:, :, 0], a[:, :, 7])


@pytest.mark.parametrize(
    ("kwargs", "match"),
    [
        ({"radius": 0}, "radius"),
        ({"criterion": "aic"}, "criterion"),
        ({"backend": "jax"}, "backend"),
        ({"max_modes": 0}, "max_modes"),
        ({"alpha": float("nan")}, "alpha"),
        ({"num_samples": 1}, "num_samples"),
    ],
)
def test_config_errors_name_the_bad_value(kwargs, match):
    with pytest.raises(ValueError, match=match):
        UncertaintyConfig(**kwargs)


def test_bad_centres_are_rejected():
    est = UncertaintyEstimator()
    with pytest.raises(ValueError, match="NaN"):
        est(ONE, None, torch.tensor([[0.5, float("nan"), 0.5]]))
    with pytest.raises(ValueError, match="chunk_step"):
        UncertaintyEstimator(UncertaintyConfig(chunk_step=2))(ONE, None, CENTER, chunk=1)


def test_a_chunk_probe_moves_the_whole_chunk_and_reads_the_step_it_names():
    """With a plan, every step of the chunk is moved by the same offset, and the vectors are read at
    ``chunk_step``: a field that pulls step 2 toward a point and leaves the others alone is seen there."""
    from policy.uncertainty import UncertaintyConfig, UncertaintyEstimator

    target = torch.tensor([0.3, -0.2, 0.1])

    def eps(obs, actions, k):  # (B, S, C, D): step 2 is pulled toward target, the others feel nothing
        out = torch.zeros_like(actions)
        out[:, :, 2, :3] = actions[:, :, 2, :3] - target
        return out

    plan = torch.zeros(1, 4, 10)
    plan[0, :, :3] = torch.linspace(0, 0.3, 4)[:, None]  # the chunk walks away from the current pose
    est = UncertaintyEstimator(UncertaintyConfig(num_samples=32, chunk_step=2, backend="torch"))
    result = est(eps, None, plan[:, 0], chunk=4, plan=plan)
    assert torch.allclose(result.samples.mean(dim=1).float(), plan[0, 2, :3], atol=0.03)  # around step 2's pose
    assert result.vectors.norm(dim=-1).min() > 0  # step 2's field, not step 0's (zero)
    with pytest.raises(ValueError, match="plan must have shape"):
        est(eps, None, plan[:, 0], chunk=4, plan=plan[:, :3])
