"""Hysteresis of the labels over time (core/classify/rules.py): a label change counts only once
it persists, in two passes of O(N) per frame so that a stage can stream them over the
frames of a long log (the backward pass first, then the forward pass)."""

from __future__ import annotations

import numpy as np

from .labels import UNKNOWN


def apply_hysteresis(labels: np.ndarray, frames: int) -> np.ndarray:
    """Labels (T, N) with every run shorter than `frames` frames replaced by the label before
    it (frame 0 is the reference and never changes; a run that reaches the last frame is kept:
    the future that would confirm it is not recorded). UNKNOWN entries stay unknown and do
    not break runs. frames <= 1 returns a copy.

    Two passes of O(N) per frame (`HysteresisAhead` backwards, `hysteresis_step`
    forwards), so a stage can run them streaming over the frames of a long log."""
    out = np.array(labels, np.uint8, copy=True)
    if frames <= 1 or out.shape[0] < 2:
        return out
    ahead = HysteresisAhead(out.shape[1], frames)
    persists = np.zeros(out.shape, bool)
    for k in range(out.shape[0] - 1, 0, -1):
        persists[k] = ahead.step(out[k])
    current = out[0].copy()
    for k in range(1, out.shape[0]):
        out[k] = hysteresis_step(current, out[k], persists[k])
    return out


class HysteresisAhead:
    """The backward pass of `apply_hysteresis`, fed frames T-1, T-2, ..., 1 (raw labels
    (N,) each): per point, the latest known label seen, how many known frames in a row
    carry it (capped at `frames`) and whether no other known label follows."""

    def __init__(self, n_points: int, frames: int) -> None:
        self.frames = frames
        self.label = np.full(n_points, UNKNOWN, np.uint8)
        self.run = np.zeros(n_points, np.int64)
        self.to_end = np.ones(n_points, bool)

    def step(self, raw: np.ndarray) -> np.ndarray:
        """Whether each point's label at this frame persists: its next `frames` known
        frames from this one (or all of them, to the end of the log) carry it (N,) bool."""
        known = raw != UNKNOWN
        same = known & (raw == self.label)
        other = known & ~same
        self.to_end &= ~(other & (self.label != UNKNOWN))
        self.run = np.where(same, np.minimum(self.run + 1, self.frames),
                            np.where(other, 1, self.run))
        self.label = np.where(known, raw, self.label)
        return (self.run >= self.frames) | self.to_end


def hysteresis_step(current: np.ndarray, raw: np.ndarray, persists: np.ndarray) -> np.ndarray:
    """The forward pass of `apply_hysteresis` at one frame: a point takes its raw label where
    it differs from `current` (N,), is known and persists (`HysteresisAhead.step` of this
    frame); `current` is updated in place. Returns the frame's labels (UNKNOWN stays)."""
    accept = (raw != current) & (raw != UNKNOWN) & persists
    current[accept] = raw[accept]
    return np.where(raw == UNKNOWN, UNKNOWN, current).astype(np.uint8)
