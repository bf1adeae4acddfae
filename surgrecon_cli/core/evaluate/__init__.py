"""Scores against the simulator's ground truth: template, registration, labels, contact and
indentation."""
