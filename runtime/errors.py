"""User-facing errors: one line, naming the file, key or device, and exit code 2.

Anything raised as a `UserError` is a mistake the user can fix (bad config, missing model,
unusable device); the CLI prints its message without a traceback and exits 2. Everything else
is a bug or a fault and keeps its traceback.
"""


class UserError(Exception):
    """A mistake in what the user gave us; printed as one line, exit code 2."""

    exit_code = 2


class ConfigError(UserError):
    """A config or calibration file, or a --set override, is wrong."""


class DeviceError(UserError):
    """A device cannot be used at start (missing, busy, silent)."""
