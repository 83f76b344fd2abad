"""Shared MJCF of the KUKA tasks: scene settings, the mesh-free iiwa arm with its gripper, actuators."""

from __future__ import annotations

import os

_ENVS_DIR = os.path.dirname(os.path.dirname(__file__))
_FILENAMES = ("./common/scene.xml", "./common/kuka_iiwa7.xml", "./common/actuators.xml")


def _read(filename: str) -> bytes:
    with open(os.path.join(_ENVS_DIR, filename), "rb") as f:
        return f.read()


ASSETS: dict[str, bytes] = {filename: _read(filename) for filename in _FILENAMES}


def read_model(model_filename: str) -> str:
    """The text of the task MJCF ``model_filename`` (a file in ``envs/``)."""
    return _read(model_filename).decode()
