"""The two refusals every layer raises: bad input and a bad experiment config.

Both are `ValueError`s whose one-line message names the culprit (a file, a flag or a key);
the CLI turns them into exit code 2 and the widgets into a message beside the field.
"""

__all__ = ["InputError", "ConfigError"]


class InputError(ValueError):
    """Input that cannot be used; the message names the culprit in one line."""


class ConfigError(ValueError):
    """An experiment config that cannot describe a real setup; the message names the key."""
