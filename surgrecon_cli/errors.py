"""One exception family. The CLI turns any `SurgReconError` into one line and exit code 2."""


class SurgReconError(Exception):
    """Base of every error surgrecon raises on purpose (bad input, bad config, ...)."""


class ConfigError(SurgReconError):
    """A config file or `--set` override is invalid (unknown key, wrong type, bad range)."""


class InputError(SurgReconError):
    """An input file is unreadable, corrupt, truncated or inconsistent."""


class TopicError(InputError):
    """A role of the `[topics]` config matches no channel, or a schema is unsupported."""


class RunFolderError(SurgReconError):
    """A run folder is missing a stage's outputs or belongs to another input/config."""


class GeometryError(SurgReconError):
    """Degenerate geometry: too few points, singular systems, invalid transforms."""


class ExecutorError(SurgReconError):
    """An executor could not start, lost its workers, or a task failed unexpectedly
    (raised by surgrecon_cli/executors, which re-exports it)."""
