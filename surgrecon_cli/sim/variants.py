"""Named simulator presets that look like real rigs (`surgrecon simulate --variant NAME`).

A preset sets several `SimConfig` fields at once; anything given explicitly overrides it.
`default` is today's scene (6 tracked cameras on a ring, breathing, a tool indenting).
"""

from __future__ import annotations

from dataclasses import dataclass, field, fields
from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:  # imported lazily: the CLI lists the presets without loading numpy
    from .scene import SimConfig

STEREO_BASELINE = 0.005  # m: a 10 mm stereo laparoscope's two lenses sit ~5 mm apart
# What a clinical endoscope's video adds to a clean rendering (sim/degrade.py): the
# localisation error is the order of the real recordings' across-epipolar residuals.
REAL_IMAGES: dict[str, Any] = {"warp_px": 0.25, "blur_px": 0.8, "vignetting": 0.35,
                               "interlace_px": 0.3, "jpeg_quality": 80}


@dataclass(frozen=True)
class Variant:
    """A preset: a one-line description and the `SimConfig` fields it sets."""

    name: str
    description: str
    settings: dict[str, Any] = field(default_factory=dict)


VARIANTS: dict[str, Variant] = {
    v.name: v
    for v in (
        Variant("default", "6 tracked cameras on a ring, breathing, a tool indenting"),
        Variant(
            "stereo",
            "one tracked stereo endoscope alone (5 mm baseline, 30-80 mm away)",
            {"cameras": 2, "stereo_baseline": STEREO_BASELINE},
        ),
        Variant(
            "stereo-real",
            "the stereo endoscope alone with real-image difficulty: 0.25 px localisation "
            "error, blur, vignetting, interlacing, JPEG quality 80",
            {"cameras": 2, "stereo_baseline": STEREO_BASELINE, **REAL_IMAGES},
        ),
        Variant(
            "stereo-sweep",
            "stereo-real while the endoscope pans 30 deg (2-4 deg per frame over 12 frames)",
            {"cameras": 2, "stereo_baseline": STEREO_BASELINE, "sweep_deg": 30.0,
             **REAL_IMAGES},
        ),
        Variant(
            "breathing",
            "stereo-real over breathing tissue: all of it rises 4 mm at 0.25 Hz (the tool "
            "held away) with a local swelling of 0.8 mm",
            {"cameras": 2, "stereo_baseline": STEREO_BASELINE, **REAL_IMAGES,
             "breath_edge": -1.0, "breath_amplitude": 0.004, "breath_period": 4.0,
             "swell_amplitude": 0.0025, "swell_sigma": 0.0025, "indent_depth": 0.0,
             "tool_clearance": 0.015},
        ),
        Variant(
            "stereo-plus",
            "the stereo endoscope plus 3 tracked ring cameras",
            {"cameras": 5, "stereo_baseline": STEREO_BASELINE},
        ),
        Variant(
            "rigid",
            "the tissue moves as one rigid body (a few deg and mm); nothing deforms",
            {"rigid_scene": True},
        ),
        Variant(
            "sweep",
            "every camera pans up to 35 deg: ~40 % of the frame-0 tissue leaves all views",
            {"sweep_deg": 35.0},
        ),
        Variant(
            "rig-sweep",
            "an untracked stereo endoscope sweeping 2-4 deg a frame over still tissue: the "
            "logged rig pose is fixed, the scene moves rigidly in its frame",
            {"cameras": 2, "stereo_baseline": STEREO_BASELINE, "rigid_scene": True,
             "rig_sweep_deg": 3.0, "tracker_noise_pos": 0.0, "tracker_noise_deg": 0.0},
        ),
        Variant(
            "press-release",
            "the tool presses, releases the dent fully and lifts off before the end",
            {"release": 1.0},
        ),
        Variant(
            "hover",
            "breathing alone: the tool hovers 1 mm above a breathing part of the tissue",
            {"indent_depth": 0.0, "tool_clearance": 0.0017, "contact_xy": (0.015, -0.005)},
        ),
        Variant(
            "noisy",
            "tracker noise 0.25 mm / 0.1 deg (default 0.1 mm / 0.05 deg)",
            {"tracker_noise_pos": 0.25e-3, "tracker_noise_deg": 0.1},
        ),
    )
}


def variant_config(name: str = "default", **overrides: Any) -> SimConfig:
    """The `SimConfig` of a preset, with `overrides` (SimConfig field names) on top."""
    from .scene import SimConfig

    if name not in VARIANTS:
        raise ValueError(f"unknown simulator variant {name!r}; choose from {', '.join(VARIANTS)}")
    known = {f.name for f in fields(SimConfig)}
    unknown = sorted(set(overrides) - known)
    if unknown:
        raise ValueError(f"not SimConfig fields: {', '.join(unknown)}")
    return SimConfig(**{**VARIANTS[name].settings, **overrides})
