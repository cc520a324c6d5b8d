"""Problems found in a sequence folder are collected as messages, each naming its file; a reader
raises the first."""

from __future__ import annotations

from meridian_torch.errors import SequenceFormatError

__all__ = ["raise_first"]


def raise_first(problems: list[str]) -> None:
    if problems:
        raise SequenceFormatError(problems[0])
