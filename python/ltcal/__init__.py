"""ltcal from Python: run pipelines, read their tables, diagnose campaigns.

The Rust library is the one implementation; this package converts. Tables
cross as Arrow (the Parquet bytes ltcal holds them as, read by pyarrow in
memory: no temporary files), errors as exceptions (:class:`InputError`,
:class:`StageError`, :class:`LtcalError`), and the GIL is released while
Rust works.

    import ltcal
    run = ltcal.run("pipelines/synthetic-validation.toml")
    summary = run.table("evaluate_sphere.summary")        # a pandas DataFrame
    d = ltcal.diagnose("examples/campaigns/example-05-station-drift")
    print(d.verdict)
"""

from __future__ import annotations

import json
import os
import tempfile
import warnings
from dataclasses import dataclass, field
from typing import Any, Dict, List, Mapping, Optional, Sequence, Union

from . import _ltcal
from ._errors import InputError, LtcalError, StageError

__all__ = [
    "run",
    "Run",
    "StageResult",
    "diagnose",
    "Diagnosis",
    "read_campaign",
    "write_campaign",
    "Campaign",
    "InputError",
    "StageError",
    "LtcalError",
]

PathLike = Union[str, "os.PathLike[str]"]


def _frame(data: bytes, backend: str) -> Any:
    """A table's Parquet bytes as a DataFrame of `backend`."""
    # Imported here, not at the top: `import ltcal` then costs no pandas or
    # pyarrow import (~0.4 s) until a table is asked for.
    import pyarrow as pa
    import pyarrow.parquet as pq

    table = pq.read_table(pa.BufferReader(data))
    if backend == "pandas":
        return table.to_pandas()
    if backend == "polars":
        import polars

        return polars.from_arrow(table)
    if backend == "arrow":
        return table
    raise ValueError(f"backend {backend!r}: expected 'pandas', 'polars' or 'arrow'")


def _parquet(df: Any, what: str) -> bytes:
    """A pandas or polars DataFrame (or an Arrow table) as Parquet bytes."""
    import pyarrow as pa
    import pyarrow.parquet as pq

    if isinstance(df, pa.Table):
        table = df
    elif hasattr(df, "to_arrow") and not hasattr(df, "to_pandas"):
        table = df.to_arrow()
    elif type(df).__module__.startswith("polars"):
        table = df.to_arrow()
    else:
        try:
            table = pa.Table.from_pandas(df, preserve_index=False)
        except Exception as e:  # noqa: BLE001 - pyarrow raises many kinds
            raise InputError(f"table `{what}`: not a DataFrame ltcal can read: {e}", table=what) from e
    sink = pa.BufferOutputStream()
    pq.write_table(table, sink)
    return sink.getvalue().to_pybytes()


def _set_args(set: Union[None, Mapping[str, Any], Sequence[str]]) -> List[str]:
    """`--set` arguments: a mapping's values as TOML values (JSON's
    strings, numbers, booleans and lists are TOML's too), or the
    `path=value` strings as the command line takes them."""
    if set is None:
        return []
    if isinstance(set, Mapping):
        return [f"{k}={json.dumps(v)}" for k, v in set.items()]
    if isinstance(set, str):
        return [set]
    return [str(s) for s in set]


@dataclass(frozen=True)
class StageResult:
    """One stage of a run: its status (``cached``, ``ran``, ``failed``,
    ``skipped``), why, its time in seconds and its tables (name → rows)."""

    stage: str
    kind: str
    status: str
    reason: str
    seconds: float
    tables: Dict[str, int]
    files: List[str]


class Run:
    """What :func:`run` returns: the run's stages, statuses and timings,
    and its tables through :meth:`table`."""

    def __init__(self, report: Dict[str, Any], pipeline: str, set: List[str], name: Optional[str], results: str):
        self.report = report
        self.pipeline = pipeline
        self.name = name
        self.results = report.get("results")
        self._args = (pipeline, set, name, results)
        self.stages: List[StageResult] = [
            StageResult(
                stage=s["stage"],
                kind=s["kind"],
                status=s["status"],
                reason=s["reason"],
                seconds=s["seconds"],
                tables=dict(s["tables"]),
                files=list(s["files"]),
            )
            for s in report["stages"]
        ]
        experiment = report.get("experiment")
        if experiment is not None and self.name is None:
            # The experiment a `set` run became: its tables are read by name.
            self.name = experiment.get("name")
            self._args = (pipeline, set, self.name, results)

    @property
    def statuses(self) -> Dict[str, str]:
        """Stage → status."""
        return {s.stage: s.status for s in self.stages}

    @property
    def timings(self) -> Dict[str, float]:
        """Stage → seconds it took (0 when cached)."""
        return {s.stage: s.seconds for s in self.stages}

    def table(self, name: str, backend: str = "pandas") -> Any:
        """The table ``"stage.table"`` (or ``"stage"``: its first table) as a
        pandas DataFrame, a polars one (``backend="polars"``) or an Arrow
        table (``"arrow"``). The published table is checked against the
        cache entry it came from, as ``ltcal show`` does; a table from an
        earlier run is returned with a warning."""
        pipeline, set, run_name, results = self._args
        data, stale = _ltcal.table(pipeline, set, run_name, results, name)
        if stale is not None:
            warnings.warn(f"{name} is from an earlier run: {stale}", stacklevel=2)
        return _frame(data, backend)

    def __repr__(self) -> str:
        counts: Dict[str, int] = {}
        for s in self.stages:
            counts[s.status] = counts.get(s.status, 0) + 1
        said = ", ".join(f"{n} {k}" for k, n in sorted(counts.items()))
        return f"<ltcal.Run {self.report['pipeline']}: {said}>"


def run(
    pipeline: PathLike,
    set: Union[None, Mapping[str, Any], Sequence[str]] = None,
    name: Optional[str] = None,
    jobs: Optional[int] = None,
    executor: Optional[str] = None,
    progress: bool = False,
    *,
    results: PathLike = "results",
    keep_going: bool = False,
) -> Run:
    """Run a pipeline, as ``ltcal run``: every stage whose result is not
    cached.

    ``set`` overrides settings (``{"stages.identify.noise": 0.1}`` or
    ``["stages.identify.noise=0.1"]``) and makes the run an experiment,
    published to ``results/<pipeline>/runs/<name>/``; ``name`` names it.
    ``jobs``: worker threads (default: all cores). ``executor``: ``"local"``
    (default) or ``"slurm"``. ``progress``: a tqdm bar of the sweep's
    points done, or of the stages done for a pipeline without a sweep
    (cached counts as done).
    Raises :class:`InputError` for a wrong pipeline or setting and
    :class:`StageError` when a stage failed (its ``run`` holds the rest).
    Ctrl-C stops the run: nothing starts after it, the stages and sweep
    points under way finish and are cached (a rerun takes them and goes
    on), nothing of the unfinished run is published, and KeyboardInterrupt
    is raised once they have finished; a second Ctrl-C raises it at once,
    leaving what is under way to finish in the background (what lands in
    the cache is whole).
    """
    set_args = _set_args(set)
    if jobs is not None and not 1 <= jobs <= 1024:
        raise InputError(f"jobs = {jobs}: expected 1 to 1024 worker threads")
    bar = None
    callback = None
    if progress:
        try:
            from tqdm.auto import tqdm
        except ImportError as e:
            raise ImportError("progress=True needs tqdm: pip install tqdm") from e
        bar = tqdm(desc=os.path.basename(os.fspath(pipeline)), unit="stage")

        def callback(done: int, total: int, unit: str) -> None:
            bar.unit = unit
            bar.total = total
            bar.n = done
            bar.refresh()

    try:
        report = _ltcal.run(
            os.fspath(pipeline),
            set_args,
            name,
            os.fspath(results),
            jobs,
            executor or "local",
            keep_going,
            callback,
        )
    finally:
        if bar is not None:
            bar.close()
    r = Run(json.loads(report), os.fspath(pipeline), set_args, name, os.fspath(results))
    failed = [s for s in r.stages if s.status == "failed"]
    if failed:
        f = failed[0]
        raise StageError(
            f"stage `{f.stage}` ({f.kind}) failed:\n  {f.reason}",
            stage=f.stage,
            kind=f.kind,
            reason=f.reason,
            run=r,
        )
    return r


@dataclass
class Campaign:
    """A campaign (docs/campaign-format.md) as DataFrames: ``readings``,
    ``targets``, ``gauge`` (optional) and ``meta`` (campaign.toml as a
    dict)."""

    readings: Any
    targets: Any
    gauge: Any = None
    meta: Dict[str, Any] = field(default_factory=dict)


def read_campaign(folder: PathLike, backend: str = "pandas") -> Campaign:
    """Read a campaign folder, held to the format's rules; a broken file
    raises :class:`InputError` at its file, line and column."""
    tables, meta = _ltcal.read_campaign(os.fspath(folder))
    frames = {name: _frame(data, backend) for name, data in tables}
    return Campaign(
        readings=frames["readings"],
        targets=frames["targets"],
        gauge=frames.get("gauge"),
        meta=json.loads(meta),
    )


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
    """Write a campaign given as DataFrames as the folder ``folder``, held
    to the format's rules exactly as a folder is read: a bad DataFrame
    raises :class:`InputError` naming its ``table``, ``row`` (0-based) and
    ``column``, and nothing is written. ``campaign`` gives all four at
    once. ``overwrite`` replaces a campaign folder already there."""
    if campaign is not None:
        readings, targets, gauge, meta = campaign.readings, campaign.targets, campaign.gauge, campaign.meta
    if readings is None or targets is None or meta is None:
        raise InputError("a campaign needs readings, targets and meta")
    tables = [("readings", _parquet(readings, "readings")), ("targets", _parquet(targets, "targets"))]
    if gauge is not None and len(gauge) > 0:
        tables.append(("gauge", _parquet(gauge, "gauge")))
    _ltcal.write_campaign(os.fspath(folder), tables, json.dumps(dict(meta)), overwrite)


@dataclass
class Diagnosis:
    """What :func:`diagnose` returns: the verdict (as ``ltcal diagnose``
    prints it), every table as a DataFrame, the folder the files were
    written to and the figures' paths."""

    verdict: str
    tables: Dict[str, Any]
    out: str
    files: List[str]

    @property
    def figures(self) -> List[str]:
        """Paths of the figures (SVG) in :attr:`out`."""
        return [os.path.join(self.out, f) for f in self.files if f.endswith(".svg")]


def _as_campaign(c: Any) -> Optional[Campaign]:
    if isinstance(c, Campaign):
        return c
    if isinstance(c, Mapping):
        return Campaign(
            readings=c.get("readings"),
            targets=c.get("targets"),
            gauge=c.get("gauge"),
            meta=c.get("meta") or {},
        )
    return None


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
    backend: str = "pandas",
) -> Diagnosis:
    """Diagnose a campaign, as ``ltcal diagnose``: where its residual lies,
    which unmodelled effect causes it, how far the gap shrinks.

    ``campaign``: a folder, or DataFrames (a :class:`Campaign`, or a dict
    with ``readings``, ``targets``, ``gauge``, ``meta``), checked as
    :func:`write_campaign` does. ``out``: where diagnosis.csv, report.md
    and the figures go (default: a new temporary folder, kept).
    """
    folder = out if out is not None else tempfile.mkdtemp(prefix="ltcal-diagnosis-")
    as_tables = _as_campaign(campaign)
    args = (
        os.fspath(folder),
        list(effects or []),
        folds,
        mc_draws,
        seed,
        model,
        None if hypotheses is None else os.fspath(hypotheses),
    )
    if as_tables is None:
        verdict, tables, files = _ltcal.diagnose(os.fspath(campaign), *args, False)
    else:
        with tempfile.TemporaryDirectory(prefix="ltcal-campaign-") as scratch:
            where = os.path.join(scratch, "campaign")
            write_campaign(where, campaign=as_tables)
            verdict, tables, files = _ltcal.diagnose(where, *args, True)
    return Diagnosis(
        verdict=verdict,
        tables={name: _frame(data, backend) for name, data in tables},
        out=os.fspath(folder),
        files=list(files),
    )
