"""User-facing errors. The CLIs print these as one clear line and exit non-zero."""


class RainyScapeError(Exception):
    """Base class: an error the user can fix (bad input, bad config, unknown name)."""

    exit_code = 2


class ConfigError(RainyScapeError):
    """A bad key, value or component name in the configuration."""


class DataError(RainyScapeError):
    """Input data that cannot be read; the message names the file and the problem."""


class PluginError(RainyScapeError):
    """A plugin that cannot be found or imported."""


class RunBusyError(RainyScapeError):
    """A run folder another process is working in (it holds the folder's lock)."""


def warn(message: str) -> None:
    """A warning the user should see (input accepted, but probably not what they meant)."""
    import sys

    print(f"rainyscape: warning: {message}", file=sys.stderr)
