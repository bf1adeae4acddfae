"""The colours every output uses for the classes and reprojection statuses (report figures,
Foxglove export), so that a class looks the same wherever a person looks at it."""

from __future__ import annotations

CLASS_COLOURS = {"static": "#4C78A8", "shifting": "#F2A541", "deforming": "#D1495B",
                 "unknown": "#BAB0AC"}
STATUS_COLOURS = {"intra": "#4C78A8", "inter": "#59A14F", "outlier": "#D1495B",
                  "unobserved": "#BAB0AC"}


def rgba255(hex_colour: str, alpha: int = 255) -> tuple[int, int, int, int]:
    """"#RRGGBB" -> (r, g, b, a), each 0..255."""
    value = hex_colour.lstrip("#")
    return int(value[0:2], 16), int(value[2:4], 16), int(value[4:6], 16), alpha
