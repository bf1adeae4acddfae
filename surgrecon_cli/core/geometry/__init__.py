"""Cameras, lens distortion, poses, triangulation and the tool's shaft: the geometry every
later step uses."""
