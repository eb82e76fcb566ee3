"""Typed, validated configuration of the diffusion policy."""

from __future__ import annotations

from dataclasses import asdict, dataclass, fields

from policy.frames import ObjectFrame
from sim.vision import CameraSpec

NETWORKS = ("unet", "mlp")
ACTIVATIONS = ("silu", "mish")


@dataclass(frozen=True)
class DiffusionPolicyConfig:
    """Conditional diffusion policy on a state vector and, with ``cameras``, on images.

    obs_horizon H and action_horizon C default to the paper's simulated tasks
    (1 and 1). ``n_action_steps`` of each predicted chunk are executed before
    the next prediction (default: the whole chunk). ``obs_dim`` is the state
    vector's size (the robot's own state for a policy that sees cameras).

    cameras: what the policy sees besides the state (``sim.vision.CameraSpec``: name, rendered size,
    crop), each through its own encoder (``policy.vision``: ``image_channels`` wide, ``image_keypoints``
    spatial-softmax keypoints, ``image_features`` out); none: a state-only policy.
    """

    obs_dim: int
    action_dim: int = 10
    obs_horizon: int = 1
    action_horizon: int = 1
    n_action_steps: int | None = None
    network: str = "unet"
    activation: str = "silu"
    down_dims: tuple[int, ...] = (64, 128)
    kernel_size: int = 5
    n_groups: int = 8
    step_embed_dim: int = 64
    obs_encoder_dims: tuple[int, ...] = (256, 256)
    # sin/cos of 2^j * pi * x (j < octaves) of each normalized observation value feed the encoder MLP
    obs_fourier_octaves: int = 0
    mlp_hidden: int = 128
    mlp_layers: int = 2
    num_train_steps: int = 100
    num_inference_steps: int = 10
    clip_margin: float = 0.25  # x̂_0 is clipped to [-margin, 1 + margin] in normalized space
    # None: the world frame. Otherwise the network sees observations and predicts actions in the
    # frame of the object's pose on the table (policy/frames.py); inputs and outputs stay world.
    object_frame: ObjectFrame | None = None
    cameras: tuple[CameraSpec, ...] = ()
    image_channels: int = 32
    image_keypoints: int = 32
    image_features: int = 64

    def __post_init__(self) -> None:
        def positive_int(name: str) -> None:
            v = getattr(self, name)
            if not (isinstance(v, int) and not isinstance(v, bool) and v >= 1):
                raise ValueError(f"{name} must be an integer >= 1, got {v!r}")

        for name in (
            "obs_dim",
            "action_dim",
            "obs_horizon",
            "action_horizon",
            "kernel_size",
            "n_groups",
            "step_embed_dim",
            "mlp_hidden",
            "mlp_layers",
            "num_train_steps",
            "num_inference_steps",
            "image_channels",
            "image_keypoints",
            "image_features",
        ):
            positive_int(name)
        if self.n_action_steps is None:
            object.__setattr__(self, "n_action_steps", self.action_horizon)
        positive_int("n_action_steps")
        if self.n_action_steps > self.action_horizon:
            raise ValueError(f"n_action_steps ({self.n_action_steps}) exceeds action_horizon ({self.action_horizon})")
        if self.network not in NETWORKS:
            raise ValueError(f"network must be one of {NETWORKS}, got {self.network!r}")
        if self.activation not in ACTIVATIONS:
            raise ValueError(f"activation must be one of {ACTIVATIONS}, got {self.activation!r}")
        object.__setattr__(self, "down_dims", tuple(self.down_dims))
        if not self.down_dims or any(not isinstance(d, int) or d < 1 for d in self.down_dims):
            raise ValueError(f"down_dims must be a non-empty tuple of positive integers, got {self.down_dims!r}")
        object.__setattr__(self, "obs_encoder_dims", tuple(self.obs_encoder_dims))
        if any(not isinstance(d, int) or d < 1 for d in self.obs_encoder_dims):
            raise ValueError(f"obs_encoder_dims must be positive integers, got {self.obs_encoder_dims!r}")
        if any(d % self.n_groups for d in self.down_dims):
            raise ValueError(f"every down_dims entry must be divisible by n_groups={self.n_groups}: {self.down_dims}")
        if self.kernel_size % 2 == 0:
            raise ValueError(f"kernel_size must be odd, got {self.kernel_size}")
        if self.step_embed_dim % 2 or self.step_embed_dim < 4:
            raise ValueError(f"step_embed_dim must be even and >= 4, got {self.step_embed_dim}")
        if self.num_inference_steps > self.num_train_steps:
            raise ValueError(
                f"num_inference_steps ({self.num_inference_steps}) exceeds num_train_steps ({self.num_train_steps})"
            )
        if not (isinstance(self.obs_fourier_octaves, int) and 0 <= self.obs_fourier_octaves <= 8):
            raise ValueError(f"obs_fourier_octaves must be an integer in [0, 8], got {self.obs_fourier_octaves!r}")
        if self.obs_fourier_octaves and not self.obs_encoder_dims:
            raise ValueError("obs_fourier_octaves needs an observation encoder (obs_encoder_dims)")
        if not 0 <= self.clip_margin <= 10:
            raise ValueError(f"clip_margin must be in [0, 10], got {self.clip_margin!r}")
        if isinstance(self.object_frame, dict):
            try:
                object.__setattr__(self, "object_frame", ObjectFrame(**self.object_frame))
            except TypeError as exc:
                raise ValueError(f"object_frame: {exc}") from exc
        if self.object_frame is not None:
            if not isinstance(self.object_frame, ObjectFrame):
                raise ValueError(f"object_frame must be an ObjectFrame, a dict or None, got {self.object_frame!r}")
            self.object_frame.check(self.obs_dim)
        try:
            cams = tuple(c if isinstance(c, CameraSpec) else CameraSpec.from_json(c) for c in self.cameras)
        except (KeyError, TypeError, ValueError) as exc:
            raise ValueError(f"cameras: {exc}") from exc
        object.__setattr__(self, "cameras", cams)
        if len({c.name for c in cams}) != len(cams):
            raise ValueError(f"cameras named twice: {[c.name for c in cams]}")
        if cams and self.object_frame is not None:
            raise ValueError("a policy that sees cameras has no object pose for an object frame")

    @property
    def image_feature_dim(self) -> int:
        """The width of what the cameras' encoders add to each observation step (0 without cameras)."""
        return len(self.cameras) * self.image_features

    def to_dict(self) -> dict:
        d = asdict(self)
        d["down_dims"] = list(self.down_dims)
        d["obs_encoder_dims"] = list(self.obs_encoder_dims)
        if self.cameras:
            d["cameras"] = [c.to_json() for c in self.cameras]
        else:  # state-only configs read as before
            for name in ("cameras", "image_channels", "image_keypoints", "image_features"):
                del d[name]
        if self.object_frame is None:
            del d["object_frame"]  # world-frame configs read as before
        else:
            d["object_frame"] = self.object_frame.to_dict()
        return d

    @classmethod
    def from_dict(cls, d: dict) -> DiffusionPolicyConfig:
        known = {f.name for f in fields(cls)}
        unknown = sorted(set(d) - known)
        if unknown:
            raise ValueError(f"unknown policy config keys: {unknown}")
        return cls(**d)
