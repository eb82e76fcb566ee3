"""Diffusion policy, denoising-vector-field uncertainty, calibration, rollouts, figures and benchmarks.

- ``diffusion``: noise schedule, forward noising, DDIM steps (shapes in docstrings)
- ``networks``: FiLM-conditioned 1D temporal U-Net and MLP noise predictors
- ``diffusion_policy``: ``DiffusionPolicy`` (compute_loss, predict_action_chunk, select_action, reset,
  noise_prediction)
- ``uncertainty`` / ``gmm``: the metric and its sklearn and batched torch mixture back ends
- ``train``, ``checkpoint``, ``calibrate``, ``evaluate``, ``plots``, ``bench``, ``report``
"""
