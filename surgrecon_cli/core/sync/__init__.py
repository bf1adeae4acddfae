"""Time: frames from image stamps, pose streams at image times, the TF tree and world
poses."""
