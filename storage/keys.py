"""Names shared by ``sim/``, ``storage/``, ``policy/``, ``server/`` and ``web/``.

Batch and array keys, MCAP topics, schema names and frame ids live here and
nowhere else.
"""

from __future__ import annotations

# -- batch / array keys -------------------------------------------------------
OBS = "obs"  # (..., obs_horizon, obs_dim)
ACTION = "action"  # (..., action_horizon, 10) absolute end-effector pose + gripper
IMAGE_PREFIX = (
    "observation.images."  # + camera name: (..., obs_horizon, size, size, 3) uint8 RGB, as LeRobot names them
)


def image_key(camera: str) -> str:
    """The batch key of one policy camera's frames (LeRobot's ``observation.images.<camera>``)."""
    return IMAGE_PREFIX + camera


# -- step messages: the fields one control step has in every MCAP file (/step, /takeover/step) --
STEP_T = "t"  # step index within the episode / takeover
STEP_OBSERVATION = "observation"  # (obs_dim,) the observation before the action
STEP_ACTION = "action"  # (10,) the absolute action sent
STEP_EE_POSE = "ee_pose"  # {position: {x, y, z}, orientation: {x, y, z, w}} before the action
STEP_GRIPPER = "gripper"  # finger gap in metres
STEP_SUCCESS = "success"  # task success after the step
STEP_SOURCE = "source"  # who produced the action: see SOURCES
# optional, in episodes the fleet records (absent in scripted demonstrations):
STEP_SCORE = "score"  # the asking signal's score at this step (absent when the robot was not scored)
STEP_THRESHOLD = "threshold"  # the asking signal's threshold then
STEP_PAPER_U = "paper_u"  # the paper's denoising U at this step (absent when it was not computed)
STEP_POLICY_VERSION = "policy_version"  # the registry id of the version that drove the robot
STEP_COMMAND = "command"  # the operator's command, on an operator step: delta_pos, delta_rot, gripper
STEP_TAKEOVER = "takeover"  # the takeover segment's id, on an operator step
STEP_EXTRAS = (STEP_SCORE, STEP_THRESHOLD, STEP_PAPER_U, STEP_POLICY_VERSION, STEP_COMMAND, STEP_TAKEOVER)

SOURCE_EXPERT = "expert"  # scripted demonstrator
SOURCE_POLICY = "policy"  # autonomous diffusion policy
SOURCE_OPERATOR = "operator"  # human (or simulated human) takeover
SOURCE_HOLD = "hold"  # the service holding the pose (waiting for an operator, paused)
SOURCES = (SOURCE_EXPERT, SOURCE_POLICY, SOURCE_OPERATOR, SOURCE_HOLD)

# the observation's channel names, in order (``sim.env.ObsSpec.labels``; ``storage.obs_layout``): in the
# metadata of episodes and takeover segments, and in a policy's config.json (the layout it was trained on)
OBS_LABELS = "obs_labels"

# -- MCAP ------------------------------------------------------------------------
MCAP_PROFILE = "hitl"
TOPIC_EPISODE = "/episode"  # once, first: task, seed, expert, object, specs
TOPIC_STEP = "/step"  # every control step: observation, action, ee pose, gripper, success
TOPIC_OUTCOME = "/outcome"  # once, last: success, steps, reason
TOPIC_TF = "/tf"  # foxglove.FrameTransform, world -> ee and world -> each object
TOPIC_EE_POSE = "/poses/ee"  # foxglove.PoseInFrame
TOPIC_OBJECT_POSE = "/poses/objects/{name}"  # foxglove.PoseInFrame per object
# every control step, per policy camera: foxglove.CompressedImage (PNG, lossless) of what the policy saw
TOPIC_POLICY_IMAGE = "/observation/images/{name}"
CAMERAS = "cameras"  # in episode and segment metadata and a policy's config.json: [CameraSpec.to_json(), ...]

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
TOPIC_TAKEOVER = "/takeover"  # once, first: robot, episode, policy version, operator, task, reason, request
TOPIC_TAKEOVER_STEP = "/takeover/step"  # per step: obs, command, fine-tune label, U, shadow scores, pose
TOPIC_TAKEOVER_END = "/takeover/end"  # once, last: status, steps
TOPIC_FIELD = "/denoising/field"  # foxglove.SceneUpdate: the vector field as arrows coloured by mode
SCHEMA_TAKEOVER = "hitl.Takeover"
SCHEMA_TAKEOVER_STEP = "hitl.TakeoverStep"
SCHEMA_TAKEOVER_END = "hitl.TakeoverEnd"
SCHEMA_SCENE_UPDATE = "foxglove.SceneUpdate"
TOPIC_CAMERA = "/camera/{name}/image/compressed"  # foxglove.CompressedImage: each camera view the operator saw
SCHEMA_COMPRESSED_IMAGE = "foxglove.CompressedImage"
