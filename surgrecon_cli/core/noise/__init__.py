"""The run's noise model, measured from the run itself, and the noise a frame's tracked
pixels carry."""
