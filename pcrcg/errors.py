"""Errors raised on bad input. Each names the file or setting at fault."""

from __future__ import annotations


class PcrcgError(Exception):
    """Base class of the project's own errors."""


class DataError(PcrcgError, ValueError):
    """A data file or folder is missing, corrupt or inconsistent.

    The message always starts with the offending path.
    """

    def __init__(self, path: object, problem: str):
        self.path = str(path)
        self.problem = problem
        super().__init__(f"{self.path}: {problem}")

    def __reduce__(self):  # crosses process pools intact (the default would call DataError(message))
        return (DataError, (self.path, self.problem))


class ConfigError(PcrcgError, ValueError):
    """A configuration value is invalid. The message names the setting and what is allowed."""

    def __init__(self, setting: str, value: object, allowed: str):
        self.setting = setting
        self.value = value
        self.allowed = allowed
        super().__init__(f"invalid config value {setting}={value!r}: allowed {allowed}")

    def __reduce__(self):
        return (ConfigError, (self.setting, self.value, self.allowed))


class Terminated(KeyboardInterrupt):
    """The process received SIGTERM (a scheduler or ``kill`` ended it): handled like Ctrl-C, so
    that runs are closed as KILLED and the command ends with one line."""


def one_line(exc: BaseException, limit: int = 400) -> str:
    """An exception's message on one line (whitespace folded), at most ``limit`` characters."""
    text = " ".join(str(exc).split()) or type(exc).__name__
    return text if len(text) <= limit else text[: limit - 3] + "..."
