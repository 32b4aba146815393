"""User-facing errors: one clear paragraph naming the file or key and the fix.

The command-line tools catch :class:`NrtError` and print its message instead of a
traceback; anything else is a bug in nrt and keeps its traceback.
"""


class NrtError(Exception):
    """A mistake in user input (config, scene, dataset) with an actionable message."""


class DatasetError(NrtError):
    """A dataset folder is missing files, holds corrupt data or disagrees with itself."""


class SceneError(NrtError):
    """A scene specification is inconsistent or out of range."""


class ConfigError(NrtError, ValueError):
    """A config key holds a value a component cannot take (a count below 1, an unknown
    name). Also a ``ValueError``, which components raised for these before."""


class WriteError(NrtError, OSError):
    """A file could not be written (a full disk, a read-only or vanished folder): the
    message names what was being written, where, and what is left behind. Also an
    ``OSError``, which it wraps."""
