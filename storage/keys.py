"""Names shared by ``sim/``, ``storage/``, ``policy/``, ``server/`` and ``web/``.

Batch and array keys, MCAP topics, schema names and frame ids live here and
nowhere else.
"""

from __future__ import annotations

# -- batch / array keys -------------------------------------------------------
OBS = "obs"  # (..., obs_horizon, obs_dim)
ACTION = "action"  # (..., action_horizon, 10) absolute end-effector pose + gripper
EE_POSE = "ee_pose"  # (..., 7) position + quaternion xyzw
GRIPPER = "gripper"  # (...,) finger gap in metres
SUCCESS = "success"  # (...,) task success after the step
SOURCE = "source"  # who produced the action: see SOURCES

SOURCE_EXPERT = "expert"  # scripted demonstrator
SOURCE_POLICY = "policy"  # autonomous diffusion policy
SOURCE_OPERATOR = "operator"  # human (or simulated human) takeover
SOURCE_HOLD = "hold"  # the service holding the pose (waiting for an operator, paused)
SOURCES = (SOURCE_EXPERT, SOURCE_POLICY, SOURCE_OPERATOR, SOURCE_HOLD)

# -- MCAP ------------------------------------------------------------------------
MCAP_PROFILE = "hitl"
TOPIC_EPISODE = "/episode"  # once, first: task, seed, expert, object, specs
TOPIC_STEP = "/step"  # every control step: observation, action, ee pose, gripper, success
TOPIC_OUTCOME = "/outcome"  # once, last: success, steps, reason
TOPIC_TF = "/tf"  # foxglove.FrameTransform, world -> ee and world -> each object
TOPIC_EE_POSE = "/poses/ee"  # foxglove.PoseInFrame
TOPIC_OBJECT_POSE = "/poses/objects/{name}"  # foxglove.PoseInFrame per object

SCHEMA_EPISODE = "hitl.Episode"
SCHEMA_STEP = "hitl.Step"
SCHEMA_OUTCOME = "hitl.Outcome"
SCHEMA_FRAME_TRANSFORM = "foxglove.FrameTransform"
SCHEMA_POSE_IN_FRAME = "foxglove.PoseInFrame"

WORLD_FRAME = "world"
EE_FRAME = "ee"

EPISODE_GLOB = "*.mcap"
CACHE_DIR = ".cache"

# -- takeover segments (one MCAP file per operator takeover) --------------------------------------
TOPIC_TAKEOVER = "/takeover"  # once, first: robot, episode, policy version, operator, task, reason
TOPIC_TAKEOVER_STEP = "/takeover/step"  # per step: obs, command, fine-tune label, U, shadow scores, pose
TOPIC_TAKEOVER_END = "/takeover/end"  # once, last: status, steps
TOPIC_FIELD = "/denoising/field"  # foxglove.SceneUpdate: the vector field as arrows coloured by mode
SCHEMA_TAKEOVER = "hitl.Takeover"
SCHEMA_TAKEOVER_STEP = "hitl.TakeoverStep"
SCHEMA_TAKEOVER_END = "hitl.TakeoverEnd"
SCHEMA_SCENE_UPDATE = "foxglove.SceneUpdate"
