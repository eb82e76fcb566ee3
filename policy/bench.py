"""``hitl bench uncertainty``: cost of the uncertainty metric against DDIM action sampling.

States (observation history + current end-effector action) and their denoising
vectors come from real policy rollouts in the simulator. For each fleet size B
the same B states are timed with

- DDIM action sampling (``predict_action_chunk``),
- the probe (one ε_θ call on B x S samples),
- the GMM fit + score with the sklearn and the torch back end,

and the two back ends are compared on identical vectors: selected n and U.
"""

from __future__ import annotations

import time

import numpy as np
import torch
from tqdm import tqdm

from policy.diffusion_policy import DiffusionPolicy
from policy.gmm import fit_mixtures
from policy.uncertainty import UncertaintyConfig, UncertaintyEstimator, mixture_variance, mode_divergence


def _time(fn, repeats: int) -> float:
    """Median wall time in seconds over ``repeats`` calls after one warm-up call."""
    fn()
    times = []
    for _ in range(repeats):
        t = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t)
    return float(np.median(times))


def _score(vectors: torch.Tensor, cfg: UncertaintyConfig, backend: str):
    fit = fit_mixtures(vectors, cfg.max_modes, cfg.criterion, backend, cfg.seed, cfg.reg_covar)
    return fit.n, mode_divergence(fit.means, fit.n) + cfg.alpha * mixture_variance(vectors, fit.labels, fit.weights)


def bench_uncertainty(
    policy: DiffusionPolicy,
    obs: np.ndarray,
    centers: np.ndarray,
    fleet_sizes: tuple[int, ...] = (1, 8, 32),
    repeats: int = 5,
    config: UncertaintyConfig | None = None,
    agreement_states: int = 256,
    progress: bool = True,
) -> dict:
    """obs: (M, H, obs_dim) raw histories; centers: (M, 10) normalized current actions."""
    cfg = config or UncertaintyConfig()
    est = UncertaintyEstimator(cfg)
    chunk = policy.config.action_horizon
    rows = []
    bar = tqdm(fleet_sizes, desc="bench", disable=not progress)
    for b in bar:
        o = torch.as_tensor(obs[:b])
        c = torch.as_tensor(centers[:b])
        with torch.no_grad():
            _, actions = est.probe(c, chunk)
            vectors = policy.noise_prediction(o, actions, 0)[:, :, cfg.chunk_step, :3].double()
            ddim = _time(lambda o=o: policy.predict_action_chunk(o), repeats)
            probe = _time(lambda o=o, a=actions: policy.noise_prediction(o, a, 0), repeats)
            torch_fit = _time(lambda v=vectors: _score(v, cfg, "torch"), repeats)
            sk_fit = _time(lambda v=vectors: _score(v, cfg, "sklearn"), max(1, repeats // 2))
        per = 1e3 / b
        rows.append(
            {
                "fleet_size": b,
                "ddim_ms_per_robot_step": ddim * per,
                "probe_ms_per_robot_step": probe * per,
                "torch_gmm_ms_per_robot_step": torch_fit * per,
                "sklearn_gmm_ms_per_robot_step": sk_fit * per,
                "torch_uncertainty_ms_per_robot_step": (probe + torch_fit) * per,
                "sklearn_uncertainty_ms_per_robot_step": (probe + sk_fit) * per,
                "gmm_speedup": sk_fit / torch_fit,
                "uncertainty_over_ddim": (probe + torch_fit) / ddim,
            }
        )
    # agreement of the two back ends on identical vectors
    m = min(agreement_states, len(obs))
    ns, us = {}, {}
    with torch.no_grad():
        vec = []
        for i in range(0, m, 64):
            _, actions = est.probe(torch.as_tensor(centers[i : min(i + 64, m)]), chunk)
            eps = policy.noise_prediction(torch.as_tensor(obs[i : min(i + 64, m)]), actions, 0)
            vec.append(eps[:, :, cfg.chunk_step, :3].double())
        vectors = torch.cat(vec)
    for backend in ("torch", "sklearn"):
        ns[backend], us[backend] = _score(vectors, cfg, backend)
    du = (us["torch"] - us["sklearn"]).abs()
    return {
        "device": "cpu",
        "threads": torch.get_num_threads(),
        "samples_per_robot": cfg.num_samples,
        "max_modes": cfg.max_modes,
        "criterion": cfg.criterion,
        "ddim_steps": policy.config.num_inference_steps,
        "fleet": rows,
        "speedup_at_32": next((r["gmm_speedup"] for r in rows if r["fleet_size"] == 32), None),
        "agreement": {
            "states": m,
            "n_agreement": float((ns["torch"] == ns["sklearn"]).double().mean()),
            "median_abs_delta_u": float(du.median()),
            "p95_abs_delta_u": float(du.quantile(0.95)),
            "median_u": float(us["sklearn"].median()),
            "n_histogram_torch": np.bincount(ns["torch"].numpy(), minlength=cfg.max_modes + 1)[1:].tolist(),
            "n_histogram_sklearn": np.bincount(ns["sklearn"].numpy(), minlength=cfg.max_modes + 1)[1:].tolist(),
        },
    }
