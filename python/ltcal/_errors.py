"""ltcal's exceptions, raised by the extension module (python/src/lib.rs)."""

from __future__ import annotations

from typing import Any, Dict, List, Optional, Union


class LtcalError(Exception):
    """The work did not succeed (the command line's exit 1)."""


class InputError(LtcalError, ValueError):
    """The input is wrong (the command line's exit 2), located.

    ``file``, ``line``, ``column``: where in a file (``column`` is the
    column's name in a campaign's CSV file, else a character column);
    ``table``, ``row``, ``column``: where in a campaign given as
    DataFrames (``row`` is the 0-based DataFrame row). ``problems`` holds
    every problem found (each a dict of these keys); the attributes are
    the first one's.
    """

    def __init__(
        self,
        message: str,
        *,
        file: Optional[str] = None,
        line: Optional[int] = None,
        column: Union[str, int, None] = None,
        table: Optional[str] = None,
        row: Optional[int] = None,
        problems: Optional[List[Dict[str, Any]]] = None,
    ) -> None:
        super().__init__(message)
        self.message = message
        self.file = file
        self.line = line
        self.column = column
        self.table = table
        self.row = row
        self.problems = problems or []

    @classmethod
    def _of(cls, problems: List[Dict[str, Any]]) -> "InputError":
        first = problems[0] if problems else {}
        message = "\n\n".join(p["message"] for p in problems) or "invalid input"
        return cls(
            message,
            file=first.get("file"),
            line=first.get("line"),
            column=first.get("column"),
            table=first.get("table"),
            row=first.get("row"),
            problems=problems,
        )


class StageError(LtcalError):
    """A stage of a run failed; ``stage``, ``kind``, ``reason`` say which
    and why, ``run`` is the whole run (its other stages' statuses)."""

    def __init__(self, message: str, *, stage: str, kind: str, reason: str, run: Any) -> None:
        super().__init__(message)
        self.stage = stage
        self.kind = kind
        self.reason = reason
        self.run = run
