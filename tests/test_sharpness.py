"""core/template/sharpness: a blurred template frame is told apart from its sharp neighbours."""

from __future__ import annotations

import cv2
import numpy as np

from surgrecon_cli.core.template.sharpness import (
    blurred_cameras,
    decode_reduction,
    first_sharp,
    sharpness,
)


def test_blur_lowers_sharpness_whatever_the_size_and_exposure():
    rng = np.random.default_rng(0)
    texture = cv2.GaussianBlur(rng.integers(0, 255, (480, 640), np.uint8), (0, 0), 1.5)
    sharp = sharpness(texture)
    assert sharpness(cv2.GaussianBlur(texture, (0, 0), 6)) < 0.2 * sharp
    larger = cv2.resize(texture, (1280, 960), interpolation=cv2.INTER_CUBIC)
    assert abs(sharpness(larger) / sharp - 1) < 0.3  # measured at one width
    darker = (texture * 0.5).astype(np.uint8)
    assert abs(sharpness(darker) / sharp - 1) < 0.1  # over the intensity variance
    assert np.isnan(sharpness(np.full((100, 100), 7, np.uint8)))


def test_blurred_cameras_are_judged_against_their_own_later_frames():
    first = np.array([0.01, 0.5, 0.01, 0.3])
    later = np.array([[0.5, 0.5, np.nan, 0.02], [0.6, 0.4, 0.5, 0.03], [0.5, 0.5, np.nan, 0.02]])
    # camera 0 blurred; 1 sharp; 2 has one later image (not judged); 3's later frames are
    # duller than its first (a different scene, not blur in frame 0)
    np.testing.assert_array_equal(blurred_cameras(first, later), [0])
    assert first_sharp(later, np.array([0])) == 0
    blurred_start = np.array([[0.01, 0.02], [0.01, 0.5], [0.5, 0.5], [0.6, 0.5], [0.5, 0.5]])
    assert first_sharp(blurred_start, np.array([0, 1])) == 2  # both sharp again
    taking_turns = np.array([[1.0, 0.1], [0.1, 1.0], [1.0, 0.1], [0.1, 1.0]])
    assert first_sharp(taking_turns, np.array([0, 1])) is None  # never both at once


def test_images_are_decoded_no_smaller_than_the_measure_needs():
    assert [decode_reduction(w) for w in (160, 320, 640, 1279, 1280, 1920, 3840)] == [
        1, 1, 2, 2, 4, 4, 8]
