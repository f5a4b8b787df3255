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


class ConfigError(PcrcgError, ValueError):
    """A configuration value is invalid. The message names the setting and what is allowed."""

    def __init__(self, setting: str, value: object, allowed: str):
        self.setting = setting
        self.value = value
        self.allowed = allowed
        super().__init__(f"invalid config value {setting}={value!r}: allowed {allowed}")
