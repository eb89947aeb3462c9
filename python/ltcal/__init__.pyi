"""Type stubs of the `ltcal` package (see __init__.py for the docs)."""

import os
from dataclasses import dataclass
from typing import Any, Dict, List, Literal, Mapping, Optional, Sequence, Union

import pandas

from ._errors import InputError as InputError
from ._errors import LtcalError as LtcalError
from ._errors import StageError as StageError

PathLike = Union[str, os.PathLike[str]]
Backend = Literal["pandas", "polars", "arrow"]

@dataclass(frozen=True)
class StageResult:
    stage: str
    kind: str
    status: Literal["cached", "ran", "failed", "skipped"]
    reason: str
    seconds: float
    tables: Dict[str, int]
    files: List[str]

class Run:
    report: Dict[str, Any]
    pipeline: str
    name: Optional[str]
    results: Optional[str]
    stages: List[StageResult]
    @property
    def statuses(self) -> Dict[str, str]: ...
    @property
    def timings(self) -> Dict[str, float]: ...
    def table(self, name: str, backend: Backend = "pandas") -> Any:
        """The table "stage.table" as a pandas (default), polars or Arrow table."""

def run(
    pipeline: PathLike,
    set: Union[None, Mapping[str, Any], Sequence[str]] = None,
    name: Optional[str] = None,
    jobs: Optional[int] = None,
    executor: Optional[Literal["local", "slurm"]] = None,
    progress: bool = False,
    *,
    results: PathLike = "results",
    keep_going: bool = False,
) -> Run:
    """Run a pipeline as `ltcal run`; raises InputError or StageError.
    `progress`: a tqdm bar of the sweep's points (else of the stages).
    Ctrl-C stops the run, keeping what finished in the cache, and raises
    KeyboardInterrupt."""

@dataclass
class Campaign:
    readings: pandas.DataFrame
    targets: pandas.DataFrame
    gauge: Optional[pandas.DataFrame] = None
    meta: Dict[str, Any] = ...

def read_campaign(folder: PathLike, backend: Backend = "pandas") -> Campaign:
    """Read a campaign folder (docs/campaign-format.md), held to its rules."""

def write_campaign(
    folder: PathLike,
    readings: Any = None,
    targets: Any = None,
    gauge: Any = None,
    meta: Optional[Mapping[str, Any]] = None,
    *,
    campaign: Optional[Campaign] = None,
    overwrite: bool = False,
) -> None:
    """Write DataFrames as a campaign folder; a bad one raises InputError(table, row, column)."""

@dataclass
class Diagnosis:
    verdict: str
    tables: Dict[str, Any]
    out: str
    files: List[str]
    @property
    def figures(self) -> List[str]: ...

def diagnose(
    campaign: Union[PathLike, Campaign, Mapping[str, Any]],
    out: Optional[PathLike] = None,
    *,
    effects: Optional[Sequence[str]] = None,
    folds: int = 5,
    mc_draws: int = 100,
    seed: int = 0,
    model: Optional[str] = None,
    hypotheses: Optional[PathLike] = None,
    backend: Backend = "pandas",
) -> Diagnosis:
    """Diagnose a campaign (a folder or DataFrames) as `ltcal diagnose`."""
