"""Error types. Every error a user can cause derives from MeridianError; the CLI turns it
into a one-line message and exit code 1."""

from __future__ import annotations

__all__ = ["MeridianError", "ConfigError", "SequenceFormatError", "OrthophotoError", "SimulationError", "ModelWeightsError", "ExportError",
           "OutputExistsError", "CheckpointError"]


class MeridianError(Exception):
    """Root of all errors caused by input, configuration or environment."""


class ConfigError(MeridianError):
    """A configuration file or override is invalid; the message names the key."""


class SequenceFormatError(MeridianError):
    """A sequence folder violates its format (README, Formats); the message names the file and the problem."""


class OrthophotoError(SequenceFormatError):
    """An orthophoto or its georeference is unreadable or unsupported."""


class SimulationError(MeridianError):
    """The simulator cannot build the requested world, trajectory or sequence."""


class ModelWeightsError(MeridianError):
    """A model weights file is missing, unreadable or does not fit the architecture; the message names the path."""


class ExportError(MeridianError):
    """An ONNX export failed or its onnxruntime output differs from eager torch; nothing was written."""


class OutputExistsError(MeridianError):
    """An output location holds files the command would replace; nothing was written."""


class CheckpointError(MeridianError):
    """A run checkpoint is missing, damaged or belongs to another run; the message names the folder."""
