"""Re-association of a camera's lost tracks by descriptor (issue 24, item 2): when a frame's
chained tracks are too few to say how the image moved since the template (the tracking
was lost: a fast sweep, the view covered by smoke or the tool, the tissue out of view and
back), ORB features of the template's image are matched to those of the current image and
the image motion is fitted to the matches; the template's points are then re-tracked from
that guess (core/track_points). Pure OpenCV/numpy on arrays."""

from __future__ import annotations

import cv2
import numpy as np

from .tracking import MIN_MOTION_FIT, TrackingView, image_motion

ORB_FEATURES = 1500  # ours: features per image (a 640x512 endoscope image: ~1-2 k corners)
ORB_RATIO = 0.8  # Lowe's ratio test on the two nearest Hamming distances
MATCH_FIT_PX = 3.0  # RANSAC inlier bound of the motion fitted to the matches (px)
MIN_MATCH_INLIERS = 3 * MIN_MOTION_FIT  # matches agreeing on one motion to believe it


def orb_features(view: TrackingView) -> tuple[np.ndarray, np.ndarray]:
    """ORB corners (K, 2) px and descriptors (K, 32) uint8 of a view's grey image, highlights
    (`view.specular`) excluded."""
    orb = cv2.ORB.create(nfeatures=ORB_FEATURES)
    mask = np.where(view.specular, 0, 255).astype(np.uint8)
    keypoints, descriptors = orb.detectAndCompute(view.grey, mask)
    if descriptors is None or len(keypoints) == 0:
        return np.zeros((0, 2)), np.zeros((0, 32), np.uint8)
    return np.array([k.pt for k in keypoints], float), descriptors


def descriptor_motion(anchor: TrackingView, cur: TrackingView) -> np.ndarray | None:
    """The image motion (2, 3) (a 2D similarity, core/target/tracking.image_motion) from the
    anchor image to the current one, fitted robustly to ORB matches that pass the ratio
    test; None with fewer than MIN_MATCH_INLIERS matches agreeing on it."""
    pts_a, des_a = orb_features(anchor)
    pts_c, des_c = orb_features(cur)
    if len(pts_a) < MIN_MATCH_INLIERS or len(pts_c) < 2:
        return None
    pairs = cv2.BFMatcher(cv2.NORM_HAMMING).knnMatch(des_a, des_c, k=2)
    good = [p[0] for p in pairs if len(p) == 2 and p[0].distance < ORB_RATIO * p[1].distance]
    return image_motion(pts_a[[m.queryIdx for m in good]], pts_c[[m.trainIdx for m in good]],
                        MATCH_FIT_PX, MIN_MATCH_INLIERS)
