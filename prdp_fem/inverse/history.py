"""What an optimisation run records per step, so error can be plotted against time and work.

One :class:`StepRecord` per optimiser step; a :class:`History` is an immutable sequence of them
with column access, JSON-lines output and "cost to reach an error" queries.
"""

from __future__ import annotations

import json
import math
import os
from collections.abc import Iterable, Iterator
from typing import NamedTuple

import numpy as np

from .._atomic import atomic_path
from ..errors import DataError

__all__ = ["History", "StepRecord"]


class StepRecord(NamedTuple):
    """The state after optimiser step ``step`` (1-based).

    ``loss`` and ``misfit`` are the objective's value and misfit part at the step's starting
    point (what the optimiser and the controller saw, with that step's solver);
    ``parameter_error`` (relative L2 against the truth, NaN when none is known) and
    ``state_error`` (relative nodal l2 of the truncated state against a pyamg solve, NaN when
    not asked for) belong to the parameters the step produced. ``time`` is cumulative run time
    without compilation, ``compile_time`` the cumulative compilation time; ``primal_iterations``
    and ``adjoint_iterations`` are cumulative CG iterations that actually ran, line-search trials
    included; ``validation_iterations`` those of converged validation solves. ``failed_steps``
    counts the steps so far whose optimiser reported a failure (a line search that ended
    without meeting its conditions: a sign that the solves are too truncated); ``rebuilds`` the
    preconditioner hierarchies built again so far, counted from the step that first uses each
    (:class:`~prdp_fem.linalg.amg.RebuiltAMG`).
    """

    step: int
    iterations: int
    adjoint_iterations: int
    rtol: float
    refinements: int
    primal_iterations: int
    adjoint_iterations_total: int
    validation_iterations: int
    evaluations: int
    time: float
    compile_time: float
    loss: float
    misfit: float
    parameter_error: float
    state_error: float
    failed_steps: int = 0  # defaulted: records written before it existed still load
    rebuilds: int = 0  # preconditioner rebuilds so far (prdp_fem.linalg.amg.RebuiltAMG)

    @property
    def total_iterations(self) -> int:
        """Cumulative primal + adjoint (+ validation) CG iterations."""
        return self.primal_iterations + self.adjoint_iterations_total + \
            self.validation_iterations


class History:
    """An immutable sequence of :class:`StepRecord` s."""

    def __init__(self, records: Iterable[StepRecord] = ()):
        self._records = tuple(records)

    def __len__(self) -> int:
        return len(self._records)

    def __iter__(self) -> Iterator[StepRecord]:
        return iter(self._records)

    def __getitem__(self, index):
        return self._records[index]

    def __repr__(self) -> str:
        last = f", last={self._records[-1]}" if self._records else ""
        return f"History({len(self)} steps{last})"

    def append(self, record: StepRecord) -> History:
        return History((*self._records, record))

    def column(self, name: str) -> np.ndarray:
        """One field over all steps (``total_iterations`` included)."""
        _check_field(name)
        return np.array([getattr(r, name) for r in self._records])

    def first_reaching(self, error: float, field: str = "parameter_error") -> StepRecord | None:
        """The first record whose ``field`` is ``<= error`` (None if never)."""
        _check_field(field)
        for record in self._records:
            if getattr(record, field) <= error:
                return record
        return None

    def to_jsonl(self, path: str | os.PathLike) -> None:
        """Write one JSON object per step (NaN as null), atomically (temp file + rename)."""
        with atomic_path(path) as tmp, open(tmp, "w") as stream:
            for record in self._records:
                row = {k: (None if isinstance(v, float) and not math.isfinite(v) else v)
                       for k, v in record._asdict().items()}
                stream.write(json.dumps(row) + "\n")

    @classmethod
    def from_jsonl(cls, path: str | os.PathLike) -> History:
        """Read what :meth:`to_jsonl` wrote; a line that is not a step record is a DataError."""
        records = []
        with open(path) as stream:
            for number, line in enumerate(stream, start=1):
                if not line.strip():
                    continue
                try:
                    row = json.loads(line)
                    records.append(StepRecord(**{k: (math.nan if v is None else v)
                                                 for k, v in row.items()}))
                except (ValueError, TypeError, AttributeError) as exc:
                    raise DataError(
                        f"{os.fspath(path)}: line {number} is not a step record ({exc}); "
                        "expected one JSON object of StepRecord fields per line, as "
                        "History.to_jsonl writes them") from None
        return cls(records)


def _check_field(name: str) -> None:
    if name not in StepRecord._fields and name != "total_iterations":
        raise KeyError(f"{name!r}: expected one of {StepRecord._fields}")
