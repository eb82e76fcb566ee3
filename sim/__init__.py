"""Simulated robots: task suite, action space, teleoperation command, scripted experts.

MuJoCo chooses its OpenGL back end when it is first imported, so the choice is made here, before any module
of this package imports it: software OpenGL (OSMesa, package ``libosmesa6``), which renders the policy's
cameras (``sim.vision``) on any machine, unless ``MUJOCO_GL`` already names another (``egl`` on a GPU).
"""

import os

os.environ.setdefault("MUJOCO_GL", "osmesa")
os.environ.setdefault("PYOPENGL_PLATFORM", os.environ["MUJOCO_GL"])
