"""Batches: folders of captures processed by local worker processes, surviving bad
captures, dead workers, killed runs and concurrent runs (docs/design.md, "Batches")."""

from .folder import BatchSummary, find_captures, process_folder
from .task import CaptureOutcome, CaptureTask, ProcessOptions

__all__ = [
    "BatchSummary",
    "CaptureOutcome",
    "CaptureTask",
    "ProcessOptions",
    "find_captures",
    "process_folder",
]
