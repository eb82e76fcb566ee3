"""The object frame: observations and actions expressed relative to the object's pose on the table.

A policy trained in the world frame must learn where to grasp as a function of the object's yaw
(the grasp point is the object's position plus its rotation applied to an offset); a few dozen
takeover samples of a new object cannot teach that rotation. In the object frame (origin at the
object's position, turned by its heading about the vertical) that grasp point is one constant per
object, which a handful of samples can move. The frame keeps gravity vertical: only the heading
(yaw) of the object is removed, so lifting stays "up" and a tilted object still looks tilted.

The heading is that of the object's x axis projected on the table, ``atan2(r10, r00)`` of its
rotation; it is undefined only when that axis points straight up or down (then the frame uses
heading 0). The object's own position stays a world-frame input, so the policy still knows where
in the workspace it is.

``ObjectFrame`` names, by start index in the observation, what it turns: points (positions, shifted
to the object and turned), vectors (differences of positions, turned) and 6D rotations (both
columns turned). Everything else (gripper, object extent, the object's world position) passes
unchanged. Actions are (..., 10): position, 6D rotation, gripper (sim/spaces.py).
"""

from __future__ import annotations

from dataclasses import asdict, dataclass

import torch

# observation features by name: which ones the object frame turns, and how
FRAME_POINTS = ("eef_pos",)
FRAME_VECTORS = ("object_to_eef_pos",)
FRAME_ROTATIONS = ("eef_rot6d", "object_rot6d")
_HEADING_EPS = 1e-6


@dataclass(frozen=True)
class ObjectFrame:
    """Start indices in the observation (obs_dim,) of the object's position (3) and 6D rotation (6),
    and of the points (3), vectors (3) and 6D rotations (6) to express in its frame."""

    object_pos: int
    object_rot6d: int
    points: tuple[int, ...] = ()
    vectors: tuple[int, ...] = ()
    rotations: tuple[int, ...] = ()

    def __post_init__(self) -> None:
        for name in ("points", "vectors", "rotations"):
            object.__setattr__(self, name, tuple(getattr(self, name)))
        starts = (self.object_pos, self.object_rot6d, *self.points, *self.vectors, *self.rotations)
        if any(not isinstance(i, int) or isinstance(i, bool) or i < 0 for i in starts):
            raise ValueError(f"object frame indices must be integers >= 0, got {self.to_dict()}")

    def check(self, obs_dim: int) -> None:
        """Raises ValueError when an index runs past the observation or two turned features overlap."""
        spans = [(self.object_pos, 3), (self.object_rot6d, 6)]
        spans += [(i, 3) for i in (*self.points, *self.vectors)] + [(i, 6) for i in self.rotations]
        if any(i + n > obs_dim for i, n in spans):
            raise ValueError(f"object frame {self.to_dict()} runs past the {obs_dim}-dim observation")
        cols = [c for i, n in spans[2:] for c in range(i, i + n)]  # what gets turned, once each
        if len(cols) != len(set(cols)):
            raise ValueError(f"object frame {self.to_dict()}: features overlap")

    @classmethod
    def from_obs_spec(cls, spec) -> ObjectFrame:
        """The frame for a task's ``ObsSpec``: needs ``object_pos`` and ``object_rot6d``; turns the
        known points, vectors and rotations it holds (FRAME_POINTS, FRAME_VECTORS, FRAME_ROTATIONS)."""
        sl = spec.slices()
        missing = [n for n in ("object_pos", "object_rot6d") if n not in sl]
        if missing:
            raise ValueError(f"the object frame needs {missing} in the observation; it has {list(sl)}")
        return cls(
            object_pos=sl["object_pos"].start,
            object_rot6d=sl["object_rot6d"].start,
            points=tuple(sl[n].start for n in FRAME_POINTS if n in sl),
            vectors=tuple(sl[n].start for n in FRAME_VECTORS if n in sl),
            rotations=tuple(sl[n].start for n in FRAME_ROTATIONS if n in sl),
        )

    def to_dict(self) -> dict:
        return {k: list(v) if isinstance(v, tuple) else v for k, v in asdict(self).items()}

    def shifted(self, obs: torch.Tensor, offset: torch.Tensor) -> torch.Tensor:
        """obs (B, H, obs_dim) with the object seen ``offset`` (B, 3) metres from where it is (world frame,
        the same offset at every history step): its position and the vectors from it move, the points do
        not. Training with random offsets (``TrainConfig.origin_jitter``) decouples where the policy acts
        from where it believes the object is: what it acts on near the object is then what it senses there
        (``finger_rays``), not the object's origin, which for an unseen object is not where it is grasped."""
        out = obs.clone()
        shift = offset[:, None, :].to(obs.dtype)
        out[..., self.object_pos : self.object_pos + 3] += shift
        for i in self.vectors:
            out[..., i : i + 3] += shift
        return out

    def raised(
        self, obs: torch.Tensor, actions: torch.Tensor, height: torch.Tensor
    ) -> tuple[torch.Tensor, torch.Tensor]:
        """obs (B, H, obs_dim) and actions (B, C, 10) with the end effector and its targets seen ``height``
        (B,) metres higher against the object than they are, at every step; the object's own observed
        height stays (it tells a lifted object from one at rest), and so does everything the robot senses
        (``finger_rays``). Training with random heights (``TrainConfig.height_jitter``) makes how high the
        policy holds the gripper near an object follow what it senses there, not the object's origin."""
        obs_out, act_out = obs.clone(), actions.clone()
        dz = height.to(obs.dtype)[:, None]
        for i in self.points:
            obs_out[..., i + 2] += dz
        for i in self.vectors:  # vectors from the object to a point
            obs_out[..., i + 2] -= dz
        act_out[..., 2] += height.to(actions.dtype)[:, None]
        return obs_out, act_out

    # -- the frame of one observation ------------------------------------------------------
    def pose(self, obs: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """obs: (..., obs_dim) -> origin (..., 3), cos and sin of the heading (..., 1)."""
        origin = obs[..., self.object_pos : self.object_pos + 3]
        x = obs[..., self.object_rot6d : self.object_rot6d + 2]
        norm = x.norm(dim=-1, keepdim=True)
        flat = norm < _HEADING_EPS
        cos = torch.where(flat, torch.ones_like(norm), x[..., 0:1] / norm.clamp_min(_HEADING_EPS))
        sin = torch.where(flat, torch.zeros_like(norm), x[..., 1:2] / norm.clamp_min(_HEADING_EPS))
        return origin, cos, sin

    def observation(self, obs: torch.Tensor) -> torch.Tensor:
        """obs: (B, H, obs_dim) world frame -> the same in the frame of the last observation's object."""
        origin, cos, sin = (t[:, -1:] for t in self.pose(obs))
        out = obs.clone()
        for i in self.points:
            out[..., i : i + 3] = _turn(obs[..., i : i + 3] - origin, cos, -sin)
        for i in self.vectors:
            out[..., i : i + 3] = _turn(obs[..., i : i + 3], cos, -sin)
        for i in self.rotations:
            out[..., i : i + 6] = _turn_rot6d(obs[..., i : i + 6], cos, -sin)
        return out

    def actions_to(self, actions: torch.Tensor, obs: torch.Tensor) -> torch.Tensor:
        """actions: (B, ..., 10) world frame -> object frame of obs (B, H, obs_dim)'s last step."""
        origin, cos, sin = self._broadcast(actions, obs)
        out = actions.clone()
        out[..., 0:3] = _turn(actions[..., 0:3] - origin, cos, -sin)
        out[..., 3:9] = _turn_rot6d(actions[..., 3:9], cos, -sin)
        return out

    def actions_from(self, actions: torch.Tensor, obs: torch.Tensor, translate: bool = True) -> torch.Tensor:
        """The inverse of ``actions_to``. translate=False applies only the turn: what maps a
        difference of actions (a noise vector) back to the world frame."""
        origin, cos, sin = self._broadcast(actions, obs)
        out = actions.clone()
        out[..., 0:3] = _turn(actions[..., 0:3], cos, sin) + (origin if translate else 0.0)
        out[..., 3:9] = _turn_rot6d(actions[..., 3:9], cos, sin)
        return out

    def _broadcast(self, actions: torch.Tensor, obs: torch.Tensor):
        origin, cos, sin = (t[:, -1].to(actions.dtype) for t in self.pose(obs.to(actions.device)))
        shape = (actions.shape[0],) + (1,) * (actions.dim() - 2)
        return (t.reshape(*shape, t.shape[-1]) for t in (origin, cos, sin))


def _turn(v: torch.Tensor, cos: torch.Tensor, sin: torch.Tensor) -> torch.Tensor:
    """(..., 3) vectors turned about the vertical by the angle with this cos and sin."""
    x, y = v[..., 0:1], v[..., 1:2]
    return torch.cat([cos * x - sin * y, sin * x + cos * y, v[..., 2:3]], dim=-1)


def _turn_rot6d(r: torch.Tensor, cos: torch.Tensor, sin: torch.Tensor) -> torch.Tensor:
    return torch.cat([_turn(r[..., 0:3], cos, sin), _turn(r[..., 3:6], cos, sin)], dim=-1)
