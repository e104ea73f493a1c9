"""Exceptions whose message is the one line a user sees (the CLI prints it and exits non-zero)."""


class RoomError(Exception):
    """Base class: a problem the user can fix, reported as one line without a traceback."""


class InputError(RoomError):
    """Bad input: missing path, unreadable file, wrong dimensionality, empty mask, ..."""


class ConfigError(RoomError):
    """A configuration value is invalid or inconsistent."""


class BackendUnavailable(RoomError):
    """An optional backend (e.g. TotalSegmentator weights) is not installed or not present."""
