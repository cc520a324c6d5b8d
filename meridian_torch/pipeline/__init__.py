"""Orchestration: `live` takes a robot's frames one at a time and returns its pose; `run` is a
sequence folder fed through `live`; `outputs` writes a run's output folder; `checkpoint` lets an
interrupted run resume."""

from meridian_torch.pipeline.live import LiveEstimate, LiveLocalizer
from meridian_torch.pipeline.run import SequenceRun, localize_sequence

__all__ = ["LiveEstimate", "LiveLocalizer", "SequenceRun", "localize_sequence"]
