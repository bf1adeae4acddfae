"""dVRK (da Vinci Research Kit) arm topics: which pose topic is which arm.

The dVRK publishes each arm's Cartesian pose under the arm's name: `/PSM1/measured_cp`
(dVRK 2), `/dvrk/PSM1/position_cartesian_current` (dVRK 1.x), with a namespace such as
`/jhu_daVinci/` or `/dvrk/` in some setups, and `local/` variants in the arm's base frame.
PSMs hold the instruments (tools); the ECM holds the endoscope (its pose is the camera's
up to the hand-eye transform).
"""

from __future__ import annotations

import re
from collections.abc import Iterable

ARM = re.compile(r"(?:^|/)(?P<arm>PSM\d|ECM)/(?P<local>local/)?"
                 r"(?P<kind>measured_cp|position_cartesian_current|setpoint_cp|"
                 r"position_cartesian_desired)\Z")
_PREFERENCE = ("measured_cp", "position_cartesian_current", "setpoint_cp",
               "position_cartesian_desired")


def dvrk_arms(pose_topics: Iterable[str]) -> dict[str, str]:
    """{arm: topic} of the dVRK arm pose topics among `pose_topics`, one per arm (measured
    before desired, the world-frame topic before `local/`), arms in name order (ECM, PSM1,
    PSM2, ...)."""
    best: dict[str, tuple[tuple[int, int], str]] = {}
    for topic in pose_topics:
        m = ARM.search(topic)
        if m is None:
            continue
        key = (_PREFERENCE.index(m["kind"]), int(bool(m["local"])))
        if m["arm"] not in best or key < best[m["arm"]][0]:
            best[m["arm"]] = (key, topic)
    return {arm: best[arm][1] for arm in sorted(best)}


def psm_topics(pose_topics: Iterable[str]) -> list[str]:
    """The PSMs' (instrument arms') pose topics, PSM1 first."""
    return [t for arm, t in dvrk_arms(pose_topics).items() if arm.startswith("PSM")]
