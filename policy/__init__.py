"""Diffusion policy, denoising-vector-field uncertainty, baselines, training (arrives with the policy issue)."""
