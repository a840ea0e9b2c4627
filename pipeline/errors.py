"""Errors the engine shows to users as one line, with the exit code the CLI maps them to."""
from __future__ import annotations


class PipelineError(Exception):
    """Base of errors shown as one line without a traceback."""

    exit_code = 2


class ConfigError(PipelineError):
    """The config (or a --set override) is malformed: the message names the file, line and field."""


class RegistryError(PipelineError):
    """A stage implementation is unknown, fails to import or breaks the stage contract."""


class CacheMissError(PipelineError):
    """A partial run (--only/--from) needs an upstream artifact that is not in the cache."""


class StageFailed(PipelineError):
    """A stage raised; the message names the stage, its key and the config."""

    def __init__(self, message: str, *, user_error: bool) -> None:
        super().__init__(message)
        self.exit_code = 2 if user_error else 1


class InputChanged(PipelineError):
    """An input file changed while a stage used it: its key names the former content, so nothing the
    stage made from it is kept (exit 1: run again)."""

    exit_code = 1


class CodeChanged(PipelineError):
    """A stage's source changed on disk after this process imported it: the key would name the new code
    while the old one ran (exit 1: run again in a new process)."""

    exit_code = 1


class FrameError(Exception):
    """A per-frame job failed (raised in the worker, picklable): the frame, a one-line cause, the
    worker's traceback, and whether it was the input's fault."""

    def __init__(self, frame: int, cause: str, traceback: str, user_error: bool) -> None:
        super().__init__(frame, cause, traceback, user_error)
        self.frame, self.cause, self.traceback, self.user_error = frame, cause, traceback, user_error

    def __str__(self) -> str:
        return f"frame {self.frame}: {self.cause}"
