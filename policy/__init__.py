"""Diffusion policy, denoising-vector-field uncertainty, calibration, assistance signals, rollouts and
fine-tuning (the benchmarks are in ``bench``, their simulated operator's rollouts in ``lab``).

- ``config``: the policy's typed configuration; ``networks``: FiLM-conditioned 1D temporal U-Net and MLP
  noise predictors; ``diffusion``: noise schedule, forward noising, DDIM steps; ``normalizer``: min-max
  normalization kept in the policy; ``frames``: observations and actions in the object's frame
- ``diffusion_policy``: ``DiffusionPolicy`` (compute_loss, predict_action_chunk, select_action, reset,
  noise_prediction)
- ``uncertainty`` / ``gmm`` / ``gmm_numba``: the metric and its Gaussian-mixture back ends
- ``train``, ``mixing`` (mini-batches mixing two datasets), ``checkpoint``, ``devices``
- ``calibrate`` (the denoising threshold), ``heldout`` (are these the held-out episodes?), ``signal_data``
  and ``signals`` (the assistance signals behind one interface)
- ``controller`` (the one control step; ``hand_back``: the names of its hand-back rule), ``inference``
  (its batched network calls), ``lockstep`` (in-process robots around it), ``evaluate`` (autonomous
  rollouts: ``hitl rollout`` and the fine-tuning job's evaluation); the assisted rollouts of the
  benchmarks are in ``lab.assisted``
- ``finetune``: fine-tuning on takeover data, its recalibration, evaluation and promotion gate
"""
