"""The diffusion policy: ``compute_loss``, ``predict_action_chunk``, ``select_action``, ``reset``
and ``noise_prediction`` (the ε_θ the uncertainty metric and several baselines probe).

Raw observations and actions go in and come out; normalization to [0, 1] per
dimension happens inside, with the statistics stored as buffers.

With ``config.cameras`` the policy also sees images (``policy.vision``). ``encode_observation`` turns a
state history and its frames into the *seen* observation, (B, H, obs_dim + image features): the state,
raw, then what the cameras' encoders made of the frames. It runs once per robot-step; every other
method takes that seen observation where a state-only policy takes its state, so the denoising steps,
the paper's probe and every signal reuse one encoding (and repeating an observation per sample repeats
features, not the encoder).

With ``config.object_frame`` the network works in the object's frame (policy/frames.py): the
observation and the actions are turned into it before normalization and the predicted actions
turned back, so every caller still passes and receives world-frame values. ``action_normalizer``
stays the world action space (the one the uncertainty probes and the recordings use);
``frame_action_normalizer`` normalizes the actions the network sees.
"""

from __future__ import annotations

import math
import warnings
from collections import deque

import numpy as np
import torch
from torch import nn

from policy.config import DiffusionPolicyConfig
from policy.diffusion import NoiseSchedule
from policy.networks import ConditionalUnet1D, FilmMLP
from policy.normalizer import MinMaxNormalizer
from policy.vision import VisionEncoder
from storage import keys


class ObsEncoder(nn.Module):
    """Per-robot MLP on the flattened normalized observation history, concatenated with its input.

    It gives the FiLM conditioning nonlinear observation features (the FiLM layers themselves are
    linear in the conditioning); it runs once per robot, not once per probe sample.
    """

    def __init__(self, in_dim: int, dims: tuple[int, ...], fourier_octaves: int = 0) -> None:
        super().__init__()
        self.register_buffer("freqs", math.pi * 2.0 ** torch.arange(fourier_octaves), persistent=False)
        layers: list[nn.Module] = []
        first = in_dim * (1 + 2 * fourier_octaves)
        for d in dims:
            layers += [nn.Linear(first if not layers else layers[-2].out_features, d), nn.Mish()]
        self.mlp = nn.Sequential(*layers)
        self.out_dim = in_dim + (dims[-1] if dims else 0)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        """x: (B, in_dim) normalized -> (B, out_dim): x itself, then the MLP's features of x (and of
        its sin/cos at octave frequencies, which let it follow fast periodic functions of x)."""
        if not len(self.mlp):
            return x
        feats = x
        if len(self.freqs):
            arg = (x[..., None] * self.freqs).flatten(-2)
            feats = torch.cat([x, arg.sin(), arg.cos()], dim=-1)
        return torch.cat([x, self.mlp(feats)], dim=-1)


def _build_network(cfg: DiffusionPolicyConfig, cond: int) -> nn.Module:
    if cfg.network == "unet":
        return ConditionalUnet1D(
            cfg.action_dim,
            cfg.action_horizon,
            cond,
            cfg.down_dims,
            cfg.kernel_size,
            cfg.n_groups,
            cfg.step_embed_dim,
            cfg.activation,
        )
    return FilmMLP(cfg.action_dim, cfg.action_horizon, cond, cfg.mlp_hidden, cfg.mlp_layers, cfg.step_embed_dim)


class DiffusionPolicy(nn.Module):
    def __init__(self, config: DiffusionPolicyConfig) -> None:
        super().__init__()
        self.config = config
        self.obs_normalizer = MinMaxNormalizer(config.obs_dim)
        self.action_normalizer = MinMaxNormalizer(config.action_dim)
        self.frame = config.object_frame
        if self.frame is not None:
            self.frame_action_normalizer = MinMaxNormalizer(config.action_dim)
        self.image_encoder = (
            VisionEncoder(config.cameras, config.image_channels, config.image_keypoints, config.image_features)
            if config.cameras
            else None
        )
        self.seen_dim = config.obs_dim + config.image_feature_dim  # one step of what the policy sees
        self.obs_encoder = ObsEncoder(
            self.seen_dim * config.obs_horizon, config.obs_encoder_dims, config.obs_fourier_octaves
        )
        self.net = _build_network(config, self.obs_encoder.out_dim)
        m = config.clip_margin
        self.schedule = NoiseSchedule(config.num_train_steps, clip_range=(-m, 1 + m))
        self._generator = torch.Generator().manual_seed(0)
        self._obs_queue: deque[torch.Tensor] = deque(maxlen=config.obs_horizon)
        self._action_queue: deque[torch.Tensor] = deque()

    # -- statistics --------------------------------------------------------------
    def fit_normalizers(
        self, obs: np.ndarray, actions: np.ndarray, action_bounds: tuple[np.ndarray, np.ndarray] | None = None
    ) -> None:
        """obs: (..., obs_dim), actions: (..., action_dim) raw training data.

        action_bounds: (low, high) (action_dim,) fixed bounds for the action space (a task's
        ``ActionSpace.low`` / ``high``): the actions are normalized over them, not over the data, and
        every training action must lie inside. Without them the data's own min/max is used.

        In the object frame the network's observations and actions are normalized over the
        data's min/max in that frame (positions; the 6D rotation and the gripper over [-1, 1])."""
        obs_t = torch.as_tensor(np.asarray(obs), dtype=torch.float32)
        obs_t = obs_t.reshape(len(obs_t), -1, self.config.obs_dim)  # (N, H or 1, obs_dim)
        self.obs_normalizer.fit(self.frame_obs(obs_t))
        if self.frame is not None:  # actions (N, [C,] action_dim) pair with the N observations
            act = torch.as_tensor(np.asarray(actions), dtype=torch.float32)
            act = act.reshape(len(obs_t), -1, self.config.action_dim)
            framed = self.frame.actions_to(act, obs_t).reshape(-1, self.config.action_dim)
            low, high = framed.min(0).values.numpy(), framed.max(0).values.numpy()
            low[3:], high[3:] = -1.0, 1.0
            self.frame_action_normalizer.set_bounds(low, high)
        self._fit_action_bounds(actions, action_bounds)

    def _fit_action_bounds(self, actions: np.ndarray, action_bounds) -> None:
        if action_bounds is None:
            self.action_normalizer.fit(actions)
            return
        low, high = (np.asarray(b, dtype=np.float64) for b in action_bounds)
        flat = np.asarray(actions, dtype=np.float64).reshape(-1, self.config.action_dim)
        outside = (flat < low - 1e-6) | (flat > high + 1e-6)
        if outside.any():
            dims = sorted({int(i) for i in np.flatnonzero(outside.any(0))})
            raise ValueError(
                f"{int(outside.any(1).sum())} training actions lie outside the action bounds in dims {dims}"
            )
        self.action_normalizer.set_bounds(low, high)

    def normalize_action(self, action: torch.Tensor) -> torch.Tensor:
        return self.action_normalizer.normalize(action)

    def frame_obs(self, obs: torch.Tensor) -> torch.Tensor:
        """(B, H, obs_dim) raw world -> what the network is fed before normalization ((B, H, seen_dim) seen:
        the state turned, the image features as they are)."""
        if self.frame is None:
            return obs
        d = self.config.obs_dim
        return torch.cat([self.frame.observation(obs[..., :d]), obs[..., d:]], dim=-1)

    def normalize_obs(self, obs: torch.Tensor) -> torch.Tensor:
        """(B, H, obs_dim) raw -> the normalized observation the network sees (in its frame); for a policy
        that sees cameras, (B, H, seen_dim) seen (``encode_observation``): the state normalized, the image
        features as they are."""
        obs = torch.as_tensor(obs, dtype=torch.float32)
        d = self.config.obs_dim
        state = self.obs_normalizer.normalize(self.frame_obs(obs)[..., :d])
        return torch.cat([state, obs[..., d:]], dim=-1) if self.image_encoder is not None else state

    def encode_observation(
        self, obs: torch.Tensor, images: dict[str, torch.Tensor] | None, generator: torch.Generator | None = None
    ) -> torch.Tensor:
        """What the policy sees: obs (B, H, obs_dim) raw state and images {camera: (B, H, size, size, 3)
        uint8} -> (B, H, seen_dim), the state and then each camera's features (the input of every other
        method). A state-only policy returns ``obs``. ``generator``: random crops (training), else centred.
        Runs on the policy's device, answers on the device of ``obs``."""
        obs = torch.as_tensor(obs, dtype=torch.float32)
        if self.image_encoder is None:
            return obs
        if images is None:
            names = [c.name for c in self.config.cameras]
            raise ValueError(f"the policy sees cameras {names}: pass their frames (a task made with images=True)")
        features = self.image_encoder(images, generator).to(obs.device)
        if features.shape[:2] != obs.shape[:2]:
            raise ValueError(f"{tuple(features.shape[:2])} frames for {tuple(obs.shape[:2])} observation steps")
        return torch.cat([obs, features], dim=-1)

    def widen_obs_range(self, obs: np.ndarray | torch.Tensor) -> int:
        """Widens the observation normalizer to cover ``obs`` (M, H, obs_dim) raw, as the network
        sees it; returns the number of dimensions widened (MinMaxNormalizer.widen)."""
        obs_t = torch.as_tensor(np.asarray(obs), dtype=torch.float32)[..., : self.config.obs_dim]
        return self.obs_normalizer.widen(self.frame_obs(obs_t.reshape(len(obs_t), -1, obs_t.shape[-1])))

    def _to_net_actions(self, actions: torch.Tensor, obs: torch.Tensor) -> torch.Tensor:
        """(B, C, action_dim) raw world actions -> the network's normalized actions."""
        if self.frame is None:
            return self.action_normalizer.normalize(actions)
        return self.frame_action_normalizer.normalize(self.frame.actions_to(actions, obs))

    def _from_net_actions(self, x: torch.Tensor, obs: torch.Tensor) -> torch.Tensor:
        """The inverse of ``_to_net_actions``."""
        if self.frame is None:
            return self.action_normalizer.unnormalize(x)
        return self.frame.actions_from(self.frame_action_normalizer.unnormalize(x), obs)

    def unnormalize_action(self, action: torch.Tensor) -> torch.Tensor:
        return self.action_normalizer.unnormalize(action)

    @property
    def device(self) -> torch.device:
        """Where the weights live. ``noise_prediction`` and ``predict_action_chunk`` take inputs on any
        device, run here, and answer on the device of their input: callers keep CPU tensors while the
        network runs on an accelerator (``--device cuda``), or pass device tensors to stay there."""
        return self.action_normalizer.low.device

    def _obs_cond(self, obs: torch.Tensor) -> torch.Tensor:
        """obs: (B, H, seen_dim) raw (seen: ``encode_observation``) -> (B, cond_dim) encoded normalized
        history (on the policy's device)."""
        cfg = self.config
        if obs.dim() != 3 or obs.shape[1:] != (cfg.obs_horizon, self.seen_dim):
            seen = " seen (encode_observation: the state and the cameras' features)" if self.image_encoder else ""
            raise ValueError(
                f"obs must have shape (B, {cfg.obs_horizon}, {self.seen_dim}){seen}, got {tuple(obs.shape)}"
            )
        return self.obs_encoder(self.normalize_obs(obs.to(self.device, torch.float32)).flatten(1))

    # -- training ------------------------------------------------------------------
    def compute_loss(self, batch: dict[str, torch.Tensor], generator: torch.Generator | None = None) -> torch.Tensor:
        """batch: {OBS: (B, H, obs_dim), ACTION: (B, C, action_dim)} raw, and for a policy that sees
        cameras each one's frames (``keys.image_key``: (B, H, size, size, 3) uint8, cropped at random in
        training mode). Returns the ε-prediction MSE."""
        obs = batch[keys.OBS]
        if self.image_encoder is not None:
            images = {
                c.name: batch[keys.image_key(c.name)] for c in self.config.cameras if keys.image_key(c.name) in batch
            }
            crops = (generator or torch.default_generator) if self.training else None  # random in training only
            obs = self.encode_observation(obs, images, crops)
        cond = self._obs_cond(obs)
        x0 = self._to_net_actions(batch[keys.ACTION].float(), batch[keys.OBS])
        b = x0.shape[0]
        noise = torch.randn(x0.shape, generator=generator, device=x0.device)
        k = torch.randint(0, self.config.num_train_steps, (b,), generator=generator, device=x0.device)
        x_k = self.schedule.add_noise(x0, noise, k)
        pred = self.net(x_k[:, None], k, cond)[:, 0]
        return nn.functional.mse_loss(pred, noise)

    # -- the noise predictor ---------------------------------------------------------
    def noise_prediction(self, obs: torch.Tensor, actions: torch.Tensor, k: int | torch.Tensor) -> torch.Tensor:
        """ε_θ(o, a, k).

        obs: (B, H, obs_dim) raw; actions: (B, M, C, action_dim) or (B, C, action_dim) in the
        normalized action space; k: int or (B,). Returns noise of the same shape as ``actions``.

        In the object frame the actions are mapped into the network's normalized frame space and
        the noise back by the inverse of that map's linear part (span scaling and the turn), so
        the field is the same vector field expressed in the world's normalized action space. At
        k = 0 (the paper's metric) that is exact up to (1 - sqrt(ᾱ_0)) of the map's offset; at a
        larger k the clean estimates it implies are all shifted by one constant per observation,
        which leaves their spread (the ``spread`` signal) unchanged.
        """
        squeeze = actions.dim() == 3
        x = (actions[:, None] if squeeze else actions).to(self.device, torch.float32)
        cond = self._obs_cond(obs)
        if isinstance(k, int):
            k = torch.full((x.shape[0],), k, dtype=torch.long, device=self.device)
        if self.frame is not None:
            obs_d = obs.to(self.device, torch.float32)
            x = self._to_net_actions(self.action_normalizer.unnormalize(x), obs_d)
        eps = self._eps(x, k.to(self.device), cond)
        if self.frame is not None:
            turned = self.frame.actions_from(eps * self.frame_action_normalizer.span, obs_d, translate=False)
            eps = turned / self.action_normalizer.span
        eps = eps.to(actions.device)
        return eps[:, 0] if squeeze else eps

    # -- serving: a traced copy of the noise network ---------------------------------------
    def freeze_for_inference(self) -> None:
        """Traces the noise network with TorchScript and freezes its weights, for no-grad calls in
        eval mode (DDIM and probes). Switching to training mode, loading weights or moving the
        policy drops the traced copy (it holds the weights it was traced with).

        On CPU the trace also gets TorchScript's inference passes (``optimize_for_inference``: here
        each linear layer becomes a matmul with a pre-transposed constant weight plus a bias add),
        which cut the fixed cost of a call, what counts at the fleet's small batches
        (docs/benchmarks/serving.md). Outputs agree with the eager module to within the differences
        the eager module already shows between batch sizes."""
        if self.training:
            raise RuntimeError("freeze_for_inference needs eval mode (call .eval() first)")
        cfg = self.config
        x = torch.zeros((2, 1, cfg.action_horizon, cfg.action_dim), device=self.device)
        k = torch.zeros(2, dtype=torch.long, device=self.device)
        cond = torch.zeros((2, self.obs_encoder.out_dim), device=self.device)
        with warnings.catch_warnings(), torch.no_grad():
            warnings.simplefilter("ignore", torch.jit.TracerWarning)  # shape checks become constants
            # TorchScript is deprecated in favour of torch.compile, which compiles for tens of seconds per
            # policy on a small CPU and again for new batch shapes; tracing is instant
            warnings.simplefilter("ignore", DeprecationWarning)
            traced = torch.jit.trace(self.net, (x, k, cond), check_trace=False)
            traced = torch.jit.optimize_for_inference(traced) if self.device.type == "cpu" else torch.jit.freeze(traced)
        self.__dict__["_traced"] = traced  # not a submodule: never in the state dict

    def _eps(self, x: torch.Tensor, k: torch.Tensor, cond: torch.Tensor) -> torch.Tensor:
        traced = self.__dict__.get("_traced")
        if traced is not None and not self.training and not torch.is_grad_enabled():
            return traced(x, k, cond)
        return self.net(x, k, cond)

    def _drop_traced(self) -> None:
        self.__dict__.pop("_traced", None)

    def train(self, mode: bool = True) -> DiffusionPolicy:
        if mode:
            self._drop_traced()
        return super().train(mode)

    def load_state_dict(self, *args, **kwargs):
        self._drop_traced()
        return super().load_state_dict(*args, **kwargs)

    def _apply(self, fn, *args, **kwargs):
        self._drop_traced()
        return super()._apply(fn, *args, **kwargs)

    # -- inference ---------------------------------------------------------------------
    @torch.no_grad()
    def predict_action_chunk(
        self, obs: torch.Tensor, generator: torch.Generator | None = None, noise: torch.Tensor | None = None
    ) -> torch.Tensor:
        """obs: (B, H, obs_dim) raw -> (B, C, action_dim) raw actions, by DDIM from Gaussian noise.

        noise: (B, C, action_dim) the starting noise (e.g. drawn per robot); drawn from ``generator``
        (or the policy's own) when None.
        """
        cfg = self.config
        cond = self._obs_cond(obs)
        b = cond.shape[0]
        shape = (b, 1, cfg.action_horizon, cfg.action_dim)
        if noise is None:  # drawn on the CPU generator: the same actions on every device
            x = torch.randn(shape, generator=generator or self._generator)
        elif tuple(noise.shape) != (b, cfg.action_horizon, cfg.action_dim):
            raise ValueError(
                f"noise must have shape {(b, cfg.action_horizon, cfg.action_dim)}, got {tuple(noise.shape)}"
            )
        else:
            x = noise.reshape(shape).float()
        x = x.to(self.device)
        steps = self.schedule.ddim_timesteps(cfg.num_inference_steps)
        for i, k in enumerate(steps):
            eps = self._eps(x, torch.full((b,), k, dtype=torch.long, device=self.device), cond)
            x = self.schedule.ddim_step(x, eps, k, steps[i + 1] if i + 1 < len(steps) else -1)
        return self._from_net_actions(x[:, 0], obs.to(self.device, torch.float32)).to(obs.device)

    @torch.no_grad()
    def select_action(self, obs: torch.Tensor) -> torch.Tensor:
        """obs: (B, obs_dim) raw current observation -> (B, action_dim) raw action to execute now (B, seen_dim
        seen, ``encode_observation``, for a policy that sees cameras).

        Keeps the observation history and the queue of not yet executed actions of the chunk.
        """
        obs = torch.as_tensor(obs, dtype=torch.float32)
        if not self._obs_queue:
            self._obs_queue.extend([obs] * self.config.obs_horizon)  # pad the history with the first frame
        else:
            self._obs_queue.append(obs)
        if not self._action_queue:
            chunk = self.predict_action_chunk(self.observation_history())
            self._action_queue.extend(chunk[:, : self.config.n_action_steps].unbind(1))
        return self._action_queue.popleft()

    def observation_history(self) -> torch.Tensor:
        """(B, H, obs_dim) history held by ``select_action``."""
        if not self._obs_queue:
            raise RuntimeError("no observation yet: call select_action first")
        return torch.stack(list(self._obs_queue), dim=1)

    def reset(self, seed: int | None = None) -> None:
        """Clears the queues (call at every episode start); ``seed`` reseeds the sampling noise."""
        self._obs_queue.clear()
        self._action_queue.clear()
        if seed is not None:
            self._generator.manual_seed(seed)
