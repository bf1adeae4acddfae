"""The simulator: scenes, motion, rendering and the logs it writes with their ground truth.

The names its options choose from live here, importable without numpy (the CLI lists them
in `--help` and click's choices without loading the simulator)."""

from __future__ import annotations

LENSES = ("plumb_bob", "rational_polynomial", "equidistant")
# Keys of `sim.conventions.CONVENTIONS`, in its order (tests/test_sim.py checks both agree).
POSE_CONVENTIONS = ("topics", "tf", "tf-tree", "tracker-frame", "robot-base")
