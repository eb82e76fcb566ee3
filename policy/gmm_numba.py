"""The CPU fast path of the Gaussian-mixture fits: EM compiled with numba, one fit at a time.

The batched torch EM (``gmm.fit_torch``) pays PyTorch's per-operator dispatch on every iteration of
every candidate n, and runs every fit of the batch until the slowest has converged. Here each robot's
n = 1..N fits run their own k-means++ seeding, Lloyd refinement and EM, and each stops as soon as its
mean log-likelihood changes by less than ``tol`` (sklearn's rule). The arithmetic is that of
``fit_torch`` and of sklearn's ``GaussianMixture(covariance_type="full")``: covariances regularised by
``reg_covar``, in float64.

Each robot's fits are seeded with ``seed`` afresh, so a robot's result depends on its own vectors only,
not on which other robots share its batch. Compiled on first use and cached on disk (``cache=True``).
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit

_LOG_2PI = math.log(2 * math.pi)


@njit(cache=True)
def _sq(a, b):
    s = 0.0
    for j in range(a.shape[0]):
        t = a[j] - b[j]
        s += t * t
    return s


@njit(cache=True)
def _kmeans(x, n, kmeans_iter, labels):
    """k-means++ seeding and Lloyd refinement of n centres; fills ``labels`` (S,)."""
    s, d = x.shape
    centres = np.empty((n, d))
    centres[0] = x[np.random.randint(s)]
    closest = np.empty(s)
    for i in range(s):
        closest[i] = _sq(x[i], centres[0])
    for j in range(1, n):
        total = closest.sum()
        pick = s - 1
        if total > 0:
            u = np.random.random() * total
            acc = 0.0
            for i in range(s):
                acc += closest[i]
                if acc >= u:
                    pick = i
                    break
        else:
            pick = np.random.randint(s)
        centres[j] = x[pick]
        for i in range(s):
            closest[i] = min(closest[i], _sq(x[i], centres[j]))
    for it in range(kmeans_iter + 1):
        changed = False
        for i in range(s):
            best, arg = np.inf, 0
            for k in range(n):
                dist = _sq(x[i], centres[k])
                if dist < best:
                    best, arg = dist, k
            if it == 0 or labels[i] != arg:
                changed = True
            labels[i] = arg
        if not changed or it == kmeans_iter:
            break
        sums = np.zeros((n, d))
        count = np.zeros(n)
        for i in range(s):
            sums[labels[i]] += x[i]
            count[labels[i]] += 1
        for k in range(n):
            if count[k] > 0:
                centres[k] = sums[k] / count[k]


@njit(cache=True)
def _m_step(x, resp, reg, weights, means, chol, logdet):
    """Weights, means and the Cholesky factors (and log-determinants) of the covariances."""
    s, d = x.shape
    n = resp.shape[1]
    eps = 10 * np.finfo(np.float64).eps
    for k in range(n):
        nk = eps
        for i in range(s):
            nk += resp[i, k]
        weights[k] = nk / s
        for a in range(d):
            m = 0.0
            for i in range(s):
                m += resp[i, k] * x[i, a]
            means[k, a] = m / nk
        cov = np.zeros((d, d))
        for i in range(s):
            r = resp[i, k]
            if r == 0.0:
                continue
            for a in range(d):
                da = x[i, a] - means[k, a]
                for b in range(a + 1):
                    cov[a, b] += r * da * (x[i, b] - means[k, b])
        ld = 0.0
        for a in range(d):  # Cholesky of cov / nk + reg I (lower triangle)
            for b in range(a + 1):
                v = cov[a, b] / nk + (reg if a == b else 0.0)
                for c in range(b):
                    v -= chol[k, a, c] * chol[k, b, c]
                if a == b:
                    v = math.sqrt(max(v, 1e-300))
                    chol[k, a, a] = v
                    ld += 2 * math.log(v)
                else:
                    chol[k, a, b] = v / chol[k, b, b]
        logdet[k] = ld


@njit(cache=True)
def _e_step(x, weights, means, chol, logdet, resp):
    """Fills ``resp`` (S, n); returns the mean log-likelihood."""
    s, d = x.shape
    n = weights.shape[0]
    logp = np.empty(n)
    const = np.empty(n)
    for k in range(n):
        lw = math.log(weights[k]) if weights[k] > 0 else -np.inf
        const[k] = lw - 0.5 * (d * _LOG_2PI + logdet[k])
    y = np.empty(d)
    total = 0.0
    for i in range(s):
        top = -np.inf
        for k in range(n):
            maha = 0.0
            for a in range(d):  # forward substitution L y = x - mu
                v = x[i, a] - means[k, a]
                for c in range(a):
                    v -= chol[k, a, c] * y[c]
                y[a] = v / chol[k, a, a]
                maha += y[a] * y[a]
            logp[k] = const[k] - 0.5 * maha
            top = max(top, logp[k])
        acc = 0.0
        for k in range(n):
            resp[i, k] = math.exp(logp[k] - top)
            acc += resp[i, k]
        for k in range(n):
            resp[i, k] /= acc
        total += math.log(acc) + top
    return total / s


@njit(cache=True)
def _fit_all(x, max_modes, seed, reg, max_iter, tol, kmeans_iter, means_out, weights_out, labels_out, ll_out, iters):
    """x: (B, S, d). Fills means_out (B, F, F, d), weights_out (B, F, F), labels_out (B, F, S),
    ll_out (B, F) (total log-likelihood) and iters (B, F) (EM iterations) for every n = f + 1."""
    b, s, d = x.shape
    for r in range(b):
        np.random.seed(seed)  # every robot's fits start from the same seed: its result is its data's alone
        xr = x[r]
        for f in range(max_modes):
            n = f + 1
            labels = np.empty(s, dtype=np.int64)
            _kmeans(xr, n, kmeans_iter, labels)
            resp = np.zeros((s, n))
            for i in range(s):
                resp[i, labels[i]] = 1.0
            weights = np.empty(n)
            means = np.empty((n, d))
            chol = np.zeros((n, d, d))
            logdet = np.empty(n)
            _m_step(xr, resp, reg, weights, means, chol, logdet)
            prev = -np.inf
            bound = -np.inf
            converged = False
            it = 0
            while it < max_iter:
                bound = _e_step(xr, weights, means, chol, logdet, resp)
                it += 1
                if abs(bound - prev) < tol:
                    converged = True
                    break
                prev = bound
                _m_step(xr, resp, reg, weights, means, chol, logdet)
            if not converged:
                bound = _e_step(xr, weights, means, chol, logdet, resp)
            iters[r, f] = it
            ll_out[r, f] = bound * s
            for k in range(n):
                weights_out[r, f, k] = weights[k]
                means_out[r, f, k] = means[k]
            for i in range(s):
                best, arg = -1.0, 0
                for k in range(n):
                    if resp[i, k] > best:
                        best, arg = resp[i, k], k
                labels_out[r, f, i] = arg


def fit_all(
    x: np.ndarray,
    max_modes: int,
    seed: int = 0,
    reg_covar: float = 1e-6,
    max_iter: int = 100,
    tol: float = 1e-3,
    kmeans_iter: int = 10,
) -> dict[str, np.ndarray]:
    """Every candidate fit of every robot. x: (B, S, d) -> means (B, F, F, d), weights (B, F, F) (0 past
    n), labels (B, F, S), log_likelihood (B, F) and em_iterations (B, F), with F = ``max_modes``."""
    x = np.ascontiguousarray(x, dtype=np.float64)
    b, s, d = x.shape
    means = np.zeros((b, max_modes, max_modes, d))
    weights = np.zeros((b, max_modes, max_modes))
    labels = np.zeros((b, max_modes, s), dtype=np.int64)
    ll = np.zeros((b, max_modes))
    iters = np.zeros((b, max_modes), dtype=np.int64)
    _fit_all(x, max_modes, int(seed), float(reg_covar), int(max_iter), float(tol), int(kmeans_iter),
             means, weights, labels, ll, iters)  # fmt: skip
    return {"means": means, "weights": weights, "labels": labels, "log_likelihood": ll, "em_iterations": iters}
