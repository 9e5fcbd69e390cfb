"""What a dataset that breaks the layout raises: the problem, named by file and key."""
from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

from dagr_lite.errors import UserError


@dataclass(frozen=True)
class Problem:
    """One thing wrong in a dataset: the file, the key or frame (may be empty) and what was expected."""

    path: Path
    key: str
    message: str

    def __str__(self) -> str:
        return f"{self.path}: {self.key}: {self.message}" if self.key else f"{self.path}: {self.message}"


class DatasetFormatError(UserError):
    """A dataset does not follow the layout; the message names the file, key and expectation.

    ``problems`` holds each :class:`Problem`; the message lists them one per line.
    """

    def __init__(self, *problems: Problem):
        self.problems = list(problems)
        super().__init__("\n".join(str(p) for p in problems))

    @classmethod
    def at(cls, path: Path | str, message: str, key: str = "") -> "DatasetFormatError":
        return cls(Problem(Path(path), key, message))
