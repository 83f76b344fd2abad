"""Test-wide settings: headless MuJoCo and quiet TorchRL logging."""

import os

os.environ.setdefault("MUJOCO_GL", "disable")
os.environ.setdefault("RL_LOGGING_LEVEL", "WARNING")
