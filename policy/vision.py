"""What a policy makes of its cameras: a small convolutional encoder per camera, shaped like
diffusion_policy's and LeRobot's image encoders but sized for a CPU.

Per camera: conv 5x5 stride 2, conv 3x3 stride 2, two conv 3x3, each with GroupNorm and ReLU
(``channels`` wide), then a spatial softmax (``keypoints`` expected image coordinates, as in
diffusion_policy and LeRobot) and a linear layer to ``features``. Frames come in as rendered,
(..., size, size, 3) uint8; the encoder sees a ``crop`` x ``crop`` window of each: at a random place per
frame in training (augmentation), in the centre otherwise, as diffusion_policy and LeRobot do.

``DiffusionPolicy.encode_observation`` runs it once per robot-step; the denoising steps, the paper's
probe and every signal reuse what it gives (policy/diffusion_policy.py).
"""

from __future__ import annotations

import torch
from torch import nn

from sim.vision import CameraSpec


class SpatialSoftmax(nn.Module):
    """(N, C, h, w) feature maps -> (N, 2 K): the expected (x, y) in [-1, 1] of each of K keypoint maps
    (a 1x1 convolution of the features), the softmax over the image as its distribution."""

    def __init__(self, channels: int, height: int, width: int, keypoints: int) -> None:
        super().__init__()
        self.keypoints = nn.Conv2d(channels, keypoints, 1)
        ys, xs = torch.meshgrid(torch.linspace(-1, 1, height), torch.linspace(-1, 1, width), indexing="ij")
        self.register_buffer("grid", torch.stack([xs.reshape(-1), ys.reshape(-1)], dim=1), persistent=False)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        k = self.keypoints(x).flatten(2)  # (N, K, h * w)
        return (k.softmax(-1) @ self.grid).flatten(1)  # (N, 2 K)


class CameraEncoder(nn.Module):
    """One camera's frames (N, 3, crop, crop) float in [0, 1] -> (N, features)."""

    def __init__(self, crop: int, channels: int, keypoints: int, features: int) -> None:
        super().__init__()
        groups = max(1, channels // 8)

        def block(c_in: int, kernel: int, stride: int) -> list[nn.Module]:
            return [nn.Conv2d(c_in, channels, kernel, stride), nn.GroupNorm(groups, channels), nn.ReLU()]

        self.trunk = nn.Sequential(
            *block(3, 5, 2), *block(channels, 3, 2), *block(channels, 3, 1), *block(channels, 3, 1)
        )
        side = crop
        for kernel, stride in ((5, 2), (3, 2), (3, 1), (3, 1)):
            side = (side - kernel) // stride + 1
        if side < 1:
            raise ValueError(f"a crop of {crop} pixels is too small for the camera encoder (at least 29)")
        with torch.no_grad():
            h, w = self.trunk(torch.zeros(1, 3, crop, crop)).shape[-2:]
        self.pool = SpatialSoftmax(channels, h, w, keypoints)
        self.out = nn.Linear(2 * keypoints, features)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return self.out(self.pool(self.trunk(x * 2.0 - 1.0)))


def crop_frames(frames: torch.Tensor, crop: int, generator: torch.Generator | None = None) -> torch.Tensor:
    """(N, size, size, 3) uint8 -> (N, 3, crop, crop) float in [0, 1]: a window at a random place per frame
    when ``generator`` is given (training), else the centre one."""
    n, size = frames.shape[0], frames.shape[1]
    if frames.shape[1:] != (size, size, 3):
        raise ValueError(f"frames must be (N, size, size, 3), got {tuple(frames.shape)}")
    x = frames.permute(0, 3, 1, 2).float() / 255.0
    if crop == size:
        return x
    if generator is None:
        lo = (size - crop) // 2
        return x[:, :, lo : lo + crop, lo : lo + crop]
    off = torch.randint(0, size - crop + 1, (n, 2), generator=generator).to(frames.device)  # a CPU generator
    rows = (off[:, 0:1] + torch.arange(crop, device=frames.device))[:, None, :, None]  # (N, 1, crop, 1)
    cols = (off[:, 1:2] + torch.arange(crop, device=frames.device))[:, None, None, :]  # (N, 1, 1, crop)
    idx = torch.arange(n, device=frames.device)[:, None, None, None]
    return x[idx, torch.arange(3, device=frames.device)[None, :, None, None], rows, cols]


class VisionEncoder(nn.Module):
    """Every camera's encoder: {camera: (B, H, size, size, 3) uint8} -> (B, H, cameras x features), in the
    order of ``cameras``."""

    def __init__(self, cameras: tuple[CameraSpec, ...], channels: int, keypoints: int, features: int) -> None:
        super().__init__()
        self.cameras = cameras
        self.encoders = nn.ModuleDict({c.name: CameraEncoder(c.crop, channels, keypoints, features) for c in cameras})
        self.out_dim = len(cameras) * features

    def forward(self, images: dict[str, torch.Tensor], generator: torch.Generator | None = None) -> torch.Tensor:
        missing = [c.name for c in self.cameras if c.name not in images]
        if missing:
            raise ValueError(f"the policy sees cameras {[c.name for c in self.cameras]}; no frames of {missing}")
        out = []
        for c in self.cameras:
            frames = torch.as_tensor(images[c.name])
            if frames.dim() != 5 or frames.shape[2:] != (c.size, c.size, 3):
                raise ValueError(
                    f"camera {c.name!r}: frames must be (B, H, {c.size}, {c.size}, 3) uint8, got {tuple(frames.shape)}"
                )
            b, h = frames.shape[:2]
            device = next(self.parameters()).device
            x = crop_frames(frames.reshape(b * h, *frames.shape[2:]).to(device), c.crop, generator)
            out.append(self.encoders[c.name](x).reshape(b, h, -1))
        return torch.cat(out, dim=-1)
