"""Where the policies and the uncertainty run (``--device``, the ``device`` setting).

The physics always runs on CPU workers. On an accelerator the network calls and the mixture fits run
there (``DiffusionPolicy.device``; ``gmm``'s ``auto`` back end picks the batched torch EM), while the
controller and the signals keep CPU tensors at their edges.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import torch

if TYPE_CHECKING:
    from policy.diffusion_policy import DiffusionPolicy


def check_device(name: str) -> torch.device:
    """The torch device called ``name`` if this machine has it (ValueError saying why not)."""
    try:
        device = torch.device(name)
    except RuntimeError as exc:
        raise ValueError(f"unknown device {name!r}: {exc}") from exc
    if device.type == "cuda":
        if not torch.cuda.is_available():
            raise ValueError(f"device {name!r}: this machine's torch has no CUDA device")
        if device.index is not None and device.index >= torch.cuda.device_count():
            raise ValueError(f"device {name!r}: only {torch.cuda.device_count()} CUDA device(s)")
    elif device.type != "cpu":
        raise ValueError(f"device {name!r}: only cpu and cuda are served")
    return device


def prepare_for_serving(policy: DiffusionPolicy, device: str = "cpu", trace: bool = True) -> DiffusionPolicy:
    """The policy ready to serve: on ``device`` (ValueError when this machine lacks it), in eval mode, its
    noise network traced and frozen when ``trace`` (``server.fleet.slots.load_slot`` and the benchmarks)."""
    policy.to(check_device(device)).eval()
    if trace:
        policy.freeze_for_inference()
    return policy
