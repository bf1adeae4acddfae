"""One exception family. The CLI turns any `SurgReconError` into one line (and its
`details`, one item per indented line after it) and exit code 2.

Names taken from an input (topics, frame ids, keys) are echoed through `cut` / `quoted`: a
50 MB frame id must not become a 50 MB error line.
"""

import errno
from typing import Any

# errno values of an output the system refuses to hold: the user's to fix, not a bug.
WRITE_ERRNOS = frozenset({errno.ENOSPC, errno.EDQUOT, errno.EROFS, errno.EACCES, errno.EPERM,
                          errno.EFBIG, errno.ENOTDIR, errno.EISDIR, errno.ELOOP,
                          errno.ENAMETOOLONG})
NAME_LIMIT = 120  # characters of an input-controlled string echoed in a message


def cut(text: str, limit: int = NAME_LIMIT) -> str:
    """`text` cut to `limit` characters, the cut marked with an ellipsis and the length."""
    if len(text) <= limit:
        return text
    return f"{text[:limit]}… ({len(text)} characters)"


def quoted(value: Any, limit: int = NAME_LIMIT) -> str:
    """An input-controlled name for a message: plain quoted text (numpy strings and bytes as
    their text, not `np.str_('world')`), cut to `limit` characters."""
    if isinstance(value, bytes):
        value = value.decode("utf-8", "replace")
    text = str(value) if isinstance(value, str) else repr(value)
    return repr(cut(text, limit)) if isinstance(value, str) else cut(text, limit)


def counted(count: int, noun: str) -> str:
    """`count` and the noun, singular for one: counted(1, "frame") -> "1 frame"."""
    return f"{count} {noun}" + ("" if count == 1 else "s")


class SurgReconError(Exception):
    """Base of every error surgrecon raises on purpose (bad input, bad config, ...).
    `details`: items a person reads as a list (e.g. the topics of a log), printed one per
    line below the message."""

    def __init__(self, message: str = "", details: tuple[str, ...] = ()) -> None:
        super().__init__(message)
        self.details = tuple(details)


class ConfigError(SurgReconError):
    """A config file or `--set` override is invalid (unknown key, wrong type, bad range)."""


class InputError(SurgReconError):
    """An input file is unreadable, corrupt, truncated or inconsistent."""


class TopicError(InputError):
    """A role of the `[topics]` config matches no channel, or a schema is unsupported."""


class OutputError(SurgReconError):
    """An output could not be written: no space left, read-only or not writable."""


class RunFolderError(SurgReconError):
    """A run folder is missing a stage's outputs or belongs to another input/config."""


class GeometryError(SurgReconError):
    """Degenerate geometry: too few points, singular systems, invalid transforms."""


class ExecutorError(SurgReconError):
    """An executor could not start, lost its workers, or a task failed unexpectedly
    (raised by surgrecon_cli/executors, which re-exports it)."""
