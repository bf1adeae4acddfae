"""Exports of a run: an MCAP file Foxglove opens, TUM trajectories."""
