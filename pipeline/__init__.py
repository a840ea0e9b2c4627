"""Fluid pipeline engine: config, registry, graph, cache, executors and CLI. Imports no stage.

Public API for stage authors: Stage, Params, Artifact, Context, StageError (pipeline.stage);
for callers: run (pipeline.runner), status, clean (pipeline.status), Registry; InputFile (pipeline.scene) types
a stage parameter naming a file whose content belongs in the key.
"""
from .errors import CacheMissError, ConfigError, PipelineError, RegistryError, StageFailed
from .registry import Registry
from .runner import RunReport, run
from .scene import InputFile, OptionalInputFile
from .status import clean, status
from .stage import Artifact, Context, Params, Progress, Stage, StageError

__all__ = ["Artifact", "CacheMissError", "ConfigError", "Context", "Params", "PipelineError", "Progress",
           "Registry", "RegistryError", "RunReport", "Stage", "StageError", "StageFailed", "clean", "run", "status"]
