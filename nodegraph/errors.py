"""Errors a user can act on: each one names where the problem is (file:line, node, port)."""
from __future__ import annotations


class VolcapError(Exception):
    """Base class: the message is meant for the user, printed without a traceback."""


class GraphError(VolcapError):
    """One or more problems in a graph file, each already formatted as 'file:line: message'."""

    def __init__(self, problems: list[str]):
        self.problems = list(problems)
        super().__init__("\n".join(self.problems))


class NodeError(VolcapError):
    """A node rejected its inputs or parameters (bad data, camera/image mismatch, ...)."""


class DataError(VolcapError):
    """A file could not be read or written as the expected data type."""
