"""Shared test set-up."""

import os

# Headless rendering: MuJoCo's offscreen renderer needs a GL backend before mujoco is first imported
# (the CLIs do the same; .ci/run exports it too).
os.environ.setdefault("MUJOCO_GL", "egl")
