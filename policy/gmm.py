"""Gaussian-mixture fits of the denoising vectors, n = 1..N modes, two back ends.

- ``sklearn``: the reference, ``GaussianMixture`` (full covariances) per robot per n.
- ``torch``: batched EM over all robots x all n at once, with k-means++ seeding
  and Lloyd refinement, sklearn-style covariance regularisation, and a seeded
  generator for determinism.
- ``numba``: the same EM compiled per fit (``gmm_numba``): each robot's n = 1..N fits
  stop on their own, with no per-operator dispatch; the CPU default (``auto``).

Both return a ``MixtureFit`` for the selected n of every robot. Shapes: B robots,
S vectors of dimension d, N = max_modes; arrays are padded to N modes.

Selection criteria: ``bic`` (default) picks the n with the lowest Bayesian
information criterion; ``likelihood`` picks the highest log-likelihood, as the
paper's text states it. Raw likelihood never decreases with n (a mixture with
more modes can always reproduce one with fewer), so ``likelihood`` picks N on
almost every state and D then measures how a single blob was cut into N
pieces; BIC charges each extra mode its parameter count, so a second mode is
kept only when the field really has two directions.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import torch

CRITERIA = ("bic", "likelihood")
# "auto": numba for tensors on the CPU (each fit stops on its own; several times faster than the batched
# torch EM there, docs/benchmarks/serving.md), torch on an accelerator (one batched EM for the whole fleet)
BACKENDS = ("auto", "numba", "torch", "sklearn")


@dataclass
class MixtureFit:
    """Selected mixture per robot.

    n: (B,) modes; means: (B, N, d); weights: (B, N) (0 beyond n); labels: (B, S) hard
    assignments; log_likelihood and bic: (B, N) per candidate n (index n - 1).
    """

    n: torch.Tensor
    means: torch.Tensor
    weights: torch.Tensor
    labels: torch.Tensor
    log_likelihood: torch.Tensor
    bic: torch.Tensor


def astuple_fit(fit: MixtureFit) -> tuple[torch.Tensor, ...]:
    return (fit.n, fit.means, fit.weights, fit.labels, fit.log_likelihood, fit.bic)


def num_parameters(n: int, d: int) -> int:
    """Free parameters of a full-covariance mixture: means, covariances, weights."""
    return n * (d + d * (d + 1) // 2) + n - 1


def _bic(ll: torch.Tensor, d: int, s: int) -> torch.Tensor:
    """ll: (B, N) total log-likelihood of the n = 1..N fits on s samples of dimension d -> (B, N) BIC."""
    p = torch.tensor([num_parameters(n, d) for n in range(1, ll.shape[1] + 1)], dtype=ll.dtype, device=ll.device)
    return -2 * ll + p * math.log(s)


def _select(ll: torch.Tensor, bic: torch.Tensor, criterion: str) -> torch.Tensor:
    """(B,) index of the selected n (0-based)."""
    if criterion == "bic":
        return bic.argmin(dim=1)
    return ll.argmax(dim=1)


# -- sklearn reference -------------------------------------------------------------
def fit_sklearn(
    x: np.ndarray | torch.Tensor, max_modes: int, criterion: str = "bic", seed: int = 0, reg_covar: float = 1e-6
) -> MixtureFit:
    from sklearn.mixture import GaussianMixture

    x = np.asarray(x, dtype=np.float64)
    b, s, d = x.shape
    ll = np.zeros((b, max_modes))
    bic = np.zeros((b, max_modes))
    models = []
    for i in range(b):
        row = []
        for n in range(1, max_modes + 1):
            gm = GaussianMixture(n, covariance_type="full", reg_covar=reg_covar, random_state=seed).fit(x[i])
            ll[i, n - 1] = gm.score(x[i]) * s
            bic[i, n - 1] = gm.bic(x[i])
            row.append(gm)
        models.append(row)
    ll_t, bic_t = torch.from_numpy(ll), torch.from_numpy(bic)
    pick = _select(ll_t, bic_t, criterion)
    means = np.zeros((b, max_modes, d))
    weights = np.zeros((b, max_modes))
    labels = np.zeros((b, s), dtype=np.int64)
    for i in range(b):
        gm = models[i][int(pick[i])]
        n = gm.n_components
        means[i, :n], weights[i, :n], labels[i] = gm.means_, gm.weights_, gm.predict(x[i])
    return MixtureFit(
        pick + 1, torch.from_numpy(means), torch.from_numpy(weights), torch.from_numpy(labels), ll_t, bic_t
    )


# -- batched torch EM -------------------------------------------------------------------
# Components of all candidate fits share one axis: slot c = f * N + k is component k of the
# fit with n = f + 1 modes (valid when k <= f). Every step is a batched matmul against
# per-sample sufficient statistics (x and the flattened outer products x x^T), so no
# (components x samples x d) tensor is ever formed.


def _slot_mask(max_modes: int, device: torch.device | None = None) -> torch.Tensor:
    """(F * K,) True where slot c = f * K + k is a component of the fit with n = f + 1 modes."""
    f = torch.arange(max_modes, device=device)
    return (f[None, :] <= f[:, None]).reshape(-1)


def _sq_dist(x: torch.Tensor, xsq: torch.Tensor, centres: torch.Tensor) -> torch.Tensor:
    """x (B, S, d), xsq (B, S), centres (B, C, d) -> squared distances (B, C, S)."""
    return (xsq[:, None, :] - 2 * centres @ x.transpose(1, 2) + (centres**2).sum(-1, keepdim=True)).clamp_min(0)


def _kmeans_pp(x: torch.Tensor, xsq: torch.Tensor, max_modes: int, g: torch.Generator) -> torch.Tensor:
    """k-means++ seeding of every candidate fit. x: (B, S, d) -> centres (B, F * K, d)."""
    b, s, d = x.shape
    f = max_modes
    rows = torch.arange(b, device=x.device)[:, None]
    first = torch.randint(0, s, (b, f), generator=g, device=g.device)
    centres = x[rows, first][:, :, None].expand(b, f, f, d).clone()  # (B, F, K, d)
    closest = _sq_dist(x, xsq, centres[:, :, 0])  # (B, F, S)
    for j in range(1, f):
        pick = torch.multinomial(closest.reshape(b * f, s) + 1e-30, 1, generator=g).view(b, f)
        new = x[rows, pick]  # (B, F, d)
        centres[:, j:, j] = new[:, j:]  # only fits with more than j modes get a (j+1)-th centre
        closest = torch.minimum(closest, _sq_dist(x, xsq, new))
    return centres.reshape(b, f * f, d)


def _hard_resp(x, xsq, centres, mask, max_modes: int) -> torch.Tensor:
    """One-hot responsibilities (B, C, S) of the nearest valid centre within each fit."""
    b, s = xsq.shape
    dist = _sq_dist(x, xsq, centres).masked_fill(~mask[None, :, None], math.inf)
    lab = dist.view(b, max_modes, max_modes, s).transpose(2, 3).contiguous().argmin(dim=-1)  # (B, F, S)
    return torch.nn.functional.one_hot(lab, max_modes).permute(0, 1, 3, 2).reshape(b, -1, s).to(x.dtype)


def _m_step(x, xx, resp, mask, reg: float):
    """Weights (B, C), means (B, C, d), covariances (B, C, d, d) from responsibilities (B, C, S)."""
    s, d = x.shape[1], x.shape[2]
    nk = resp.sum(-1) + 10 * torch.finfo(x.dtype).eps
    means = resp @ x / nk[..., None]
    second = (resp @ xx / nk[..., None]).view(*nk.shape, d, d)
    cov = second - means[..., :, None] * means[..., None, :] + reg * torch.eye(d, dtype=x.dtype, device=x.device)
    return nk / s * mask, means, cov


def _e_step(x, xx, weights, means, cov, mask, max_modes: int):
    """(responsibilities (B, C, S), per-sample log-likelihood of every fit (B, F, S))."""
    b, s, d = x.shape
    chol = torch.linalg.cholesky(cov)
    prec = torch.cholesky_inverse(chol)  # (B, C, d, d)
    p_mu = (prec @ means[..., None])[..., 0]  # (B, C, d)
    maha = prec.flatten(-2) @ xx.transpose(1, 2) - 2 * p_mu @ x.transpose(1, 2) + (p_mu * means).sum(-1)[..., None]
    logdet = 2 * torch.log(torch.diagonal(chol, dim1=-2, dim2=-1)).sum(-1)
    log_w = torch.log(weights.clamp_min(1e-30)).masked_fill(~mask[None], -math.inf)
    logp = (log_w - 0.5 * (d * math.log(2 * math.pi) + logdet))[..., None] - 0.5 * maha
    grouped = logp.view(b, max_modes, max_modes, s)
    top = grouped.amax(dim=2, keepdim=True)
    e = torch.exp(grouped - top)  # one exp serves both the likelihood and the responsibilities
    total = e.sum(dim=2, keepdim=True)
    norm = (torch.log(total) + top)[:, :, 0]  # (B, F, S)
    return (e / total).view(b, -1, s), norm


def fit_torch(
    x: torch.Tensor,
    max_modes: int,
    criterion: str = "bic",
    seed: int = 0,
    reg_covar: float = 1e-6,
    max_iter: int = 100,
    tol: float = 1e-3,
    kmeans_iter: int = 10,
    dtype: torch.dtype = torch.float32,
) -> MixtureFit:
    """Batched EM. x: (B, S, d). Stops when every fit's mean log-likelihood changes by < tol (as sklearn).

    Runs in float32 on per-robot centred data (likelihoods, BIC and labels do not
    depend on the shift; the means are shifted back), on ``x``'s device, with a generator there.
    """
    x = torch.as_tensor(x)
    shift = x.to(torch.float64).mean(1, keepdim=True)
    x = (x.to(torch.float64) - shift).to(dtype)
    b, s, d = x.shape
    f = max_modes
    mask = _slot_mask(f, x.device)
    g = torch.Generator(device=x.device).manual_seed(seed)
    xsq = (x**2).sum(-1)
    xx = (x[..., :, None] * x[..., None, :]).flatten(-2)  # (B, S, d * d)
    centres = _kmeans_pp(x, xsq, f, g)
    resp = _hard_resp(x, xsq, centres, mask, f)
    for _ in range(kmeans_iter):
        cnt = resp.sum(-1, keepdim=True)
        centres = torch.where(cnt > 0, resp @ x / cnt.clamp_min(1), centres)
        new = _hard_resp(x, xsq, centres, mask, f)
        if torch.equal(new, resp):
            break
        resp = new
    weights, means, cov = _m_step(x, xx, resp, mask, reg_covar)
    prev = torch.full((b, f), -math.inf, dtype=x.dtype, device=x.device)
    for _ in range(max_iter):
        resp, norm = _e_step(x, xx, weights, means, cov, mask, f)
        bound = norm.mean(-1)  # (B, F)
        if torch.all((bound - prev).abs() < tol):
            break
        prev = bound
        weights, means, cov = _m_step(x, xx, resp, mask, reg_covar)
    else:
        resp, norm = _e_step(x, xx, weights, means, cov, mask, f)
    ll = norm.sum(-1)  # (B, F)
    bic = _bic(ll, d, s)
    pick = _select(ll, bic, criterion)
    rows = torch.arange(b, device=x.device)
    slots = pick[:, None] * f + torch.arange(f, device=x.device)  # the selected fit's K slots
    return MixtureFit(
        n=pick + 1,
        means=means[rows[:, None], slots].to(torch.float64) + shift,
        weights=weights[rows[:, None], slots].to(torch.float64),
        labels=resp[rows[:, None], slots].argmax(dim=1),
        log_likelihood=ll.to(torch.float64),
        bic=bic.to(torch.float64),
    )


# -- numba EM, one fit at a time (the CPU fast path) ----------------------------------------------------
def fit_numba(
    x,
    max_modes: int,
    criterion: str = "bic",
    seed: int = 0,
    reg_covar: float = 1e-6,
    max_iter: int = 100,
    tol: float = 1e-3,
) -> MixtureFit:
    """x: (B, S, d). Each robot's n = 1..N fits stop on their own (``gmm_numba``); float64 throughout."""
    from policy.gmm_numba import fit_all

    x = torch.as_tensor(x)
    b, s, d = x.shape
    fits = fit_all(x.detach().cpu().numpy(), max_modes, seed, reg_covar, max_iter, tol)
    ll = torch.from_numpy(fits["log_likelihood"])
    bic = _bic(ll, d, s)
    pick = _select(ll, bic, criterion)
    rows = torch.arange(b)
    return MixtureFit(
        n=pick + 1,
        means=torch.from_numpy(fits["means"])[rows, pick],
        weights=torch.from_numpy(fits["weights"])[rows, pick],
        labels=torch.from_numpy(fits["labels"])[rows, pick],
        log_likelihood=ll,
        bic=bic,
    )


_warm = False


def warm_up() -> None:
    """Compiles the numba EM (or loads it from numba's on-disk cache) once per process."""
    global _warm
    if not _warm:
        fit_numba(torch.randn((1, 16, 3), generator=torch.Generator().manual_seed(0), dtype=torch.float64), 2)
        _warm = True


def fit_mixtures(x, max_modes: int, criterion: str, backend: str, seed: int = 0, reg_covar: float = 1e-6) -> MixtureFit:
    if criterion not in CRITERIA:
        raise ValueError(f"criterion must be one of {CRITERIA}, got {criterion!r}")
    if backend == "auto":
        backend = "numba" if torch.as_tensor(x).device.type == "cpu" else "torch"
    if backend == "numba":
        return fit_numba(x, max_modes, criterion, seed, reg_covar)
    if backend == "torch":
        return fit_torch(x, max_modes, criterion, seed, reg_covar)
    if backend == "sklearn":
        return fit_sklearn(x, max_modes, criterion, seed, reg_covar)
    raise ValueError(f"backend must be one of {BACKENDS}, got {backend!r}")
