"""The `ltcal` package against the `ltcal` command line: the same tables,
verdicts and located errors; no panic crosses into Python."""

import io
import json
import math
import os
import pathlib
import signal
import subprocess
import sys
import threading
import time

import pandas as pd
import pytest

import ltcal
from conftest import BINARY, CAMPAIGN, REPO

PIPELINE = "pipelines/synthetic-validation.toml"


def cli(*args, cwd=REPO):
    return subprocess.run([str(BINARY), *map(str, args)], cwd=cwd, capture_output=True, text=True, check=True)


def test_the_package_under_test_is_the_installed_one():
    if os.environ.get("LTCAL_INSTALLED"):
        assert not pathlib.Path(ltcal.__file__).resolve().is_relative_to(REPO / "python")


def test_run_table_equals_ltcal_show_csv(repo, results):
    run = ltcal.run(PIPELINE, results=results)
    assert run.statuses["evaluate_sphere"] in ("ran", "cached")
    assert set(run.timings) == set(run.statuses)
    table = run.table("evaluate_sphere.summary")
    shown = cli("show", PIPELINE, "evaluate_sphere.summary", "--format", "csv", "--results", results)
    expected = pd.read_csv(io.StringIO(shown.stdout))
    pd.testing.assert_frame_equal(table, expected, check_exact=True)
    assert list(table["statistic"]) == ["mean", "rms", "max"]
    assert 190 < table.loc[0, "before_um"] < 200


def test_a_cached_second_run_runs_nothing(repo, results):
    ltcal.run(PIPELINE, results=results)
    again = ltcal.run(PIPELINE, results=results)
    assert set(again.statuses.values()) == {"cached"}


def test_run_table_as_polars_and_arrow(repo, results):
    run = ltcal.run(PIPELINE, results=results)
    arrow = run.table("evaluate_sphere.points", backend="arrow")
    assert arrow.num_rows == 480
    polars = pytest.importorskip("polars")
    assert isinstance(run.table("evaluate_sphere.points", backend="polars"), polars.DataFrame)


def test_run_with_progress_shows_a_bar(repo, results, capsys):
    pytest.importorskip("tqdm")
    run = ltcal.run(PIPELINE, results=results, progress=True)
    assert len(run.stages) == 25
    assert "25/25" in capsys.readouterr().err


SWEEP = """
[pipeline]
name = "little-sweep"

[stages.truth]
kind = "inject"

[stages.corner]
kind = "simulate_campaign"
inputs = { errors = "truth" }
layout = { kind = "corner", stations = 4 }

[stages.calibration]
kind = "calibrate"
inputs = { campaign = "corner" }
objective = "bundle"

[[sweep.axis]]
path = "stages.corner.seed"
range = { from = 1, to = 12, step = 1 }

[sweep]
gather = ["calibration.params"]
"""


def test_progress_of_a_sweep_counts_its_points(tmp_path, capsys):
    # It counted stages: a sweep's bar stood at 0 until the whole sweep ended.
    pytest.importorskip("tqdm")
    pipeline = tmp_path / "little-sweep.toml"
    pipeline.write_text(SWEEP)
    seen = []
    report = ltcal._ltcal.run(
        str(pipeline), [], None, str(tmp_path / "results"), None, "local", False,
        lambda done, total, unit: seen.append((done, total, unit)),
    )
    assert json.loads(report)["sweep"]["points"] == 12
    assert seen[-1] == (12, 12, "point")
    assert all(total == 12 and unit == "point" for _, total, unit in seen)
    assert [d for d, _, _ in seen] == sorted(d for d, _, _ in seen)
    ltcal.run(pipeline, results=tmp_path / "results", progress=True)
    assert "12/12" in capsys.readouterr().err


def test_a_wrong_override_raises_input_error(repo, results):
    with pytest.raises(ltcal.InputError) as e:
        ltcal.run(PIPELINE, set={"stages.no_such_stage.seed": 1}, results=results)
    assert "no_such_stage" in str(e.value)


def test_an_unknown_table_raises_input_error(repo, results):
    run = ltcal.run(PIPELINE, results=results)
    with pytest.raises(ltcal.InputError):
        run.table("evaluate_sphere.no_such_table")


def test_diagnose_dataframes_equals_ltcal_diagnose_on_the_folder(tmp_path):
    shown = cli("diagnose", CAMPAIGN, "--out", tmp_path / "cli")
    campaign = ltcal.read_campaign(CAMPAIGN)
    assert isinstance(campaign.readings, pd.DataFrame)
    d = ltcal.diagnose(campaign, out=tmp_path / "py")
    assert d.verdict == shown.stdout.strip()
    assert d.verdict.startswith("station-drift at S4")
    parquet = sorted(p.stem for p in (tmp_path / "cli").glob("*.parquet"))
    assert sorted(d.tables) == parquet
    for name in parquet:
        pd.testing.assert_frame_equal(d.tables[name], pd.read_parquet(tmp_path / "cli" / f"{name}.parquet"))
    assert d.figures and all(os.path.exists(f) for f in d.figures)


def test_diagnose_a_folder(tmp_path):
    d = ltcal.diagnose(CAMPAIGN, out=tmp_path / "out")
    assert d.verdict.startswith("station-drift at S4")


def test_write_and_read_campaign_round_trip(tmp_path):
    c = ltcal.read_campaign(CAMPAIGN)
    ltcal.write_campaign(tmp_path / "c", campaign=c)
    back = ltcal.read_campaign(tmp_path / "c")
    pd.testing.assert_frame_equal(back.readings, c.readings)
    pd.testing.assert_frame_equal(back.targets, c.targets)
    assert back.meta == c.meta


def bad(edit):
    c = ltcal.read_campaign(CAMPAIGN)
    edit(c)
    return c


def test_a_missing_column_raises_input_error_naming_table_and_column(tmp_path):
    c = bad(lambda c: setattr(c, "readings", c.readings.drop(columns=["d_mm"])))
    with pytest.raises(ltcal.InputError) as e:
        ltcal.write_campaign(tmp_path / "c", campaign=c)
    assert (e.value.table, e.value.column) == ("readings", "d_mm")
    assert not (tmp_path / "c").exists()


def test_a_nan_distance_raises_input_error_naming_table_row_and_column(tmp_path):
    def nan(c):
        c.readings.loc[7, "d_mm"] = math.nan

    with pytest.raises(ltcal.InputError) as e:
        ltcal.diagnose(bad(nan), out=tmp_path / "out")
    assert (e.value.table, e.value.row, e.value.column) == ("readings", 7, "d_mm")
    assert e.value.file is None
    assert str(e.value).startswith("table `readings`, row 7, column `d_mm`: ")


def test_an_unknown_reflector_raises_input_error_naming_table_row_and_column(tmp_path):
    def unknown(c):
        c.readings.loc[3, "target"] = "NO-SUCH-SMR"

    with pytest.raises(ltcal.InputError) as e:
        ltcal.write_campaign(tmp_path / "c", campaign=bad(unknown))
    assert (e.value.table, e.value.row, e.value.column) == ("readings", 3, "target")
    assert "NO-SUCH-SMR" in str(e.value)


def test_a_bad_file_raises_input_error_at_its_file_line_and_column(tmp_path):
    folder = tmp_path / "c"
    ltcal.write_campaign(folder, campaign=ltcal.read_campaign(CAMPAIGN))
    lines = (folder / "readings.csv").read_text().splitlines()
    header = lines[0].split(",")
    cells = lines[5].split(",")
    cells[header.index("az_deg")] = "east"
    lines[5] = ",".join(cells)
    (folder / "readings.csv").write_text("\n".join(lines) + "\n")
    with pytest.raises(ltcal.InputError) as e:
        ltcal.read_campaign(folder)
    assert e.value.file.endswith("readings.csv")
    assert (e.value.line, e.value.row, e.value.column) == (6, 4, "az_deg")


def test_a_panic_in_rust_raises_an_exception_not_a_crash():
    with pytest.raises(ltcal.LtcalError, match="internal error.*provoked"):
        ltcal._ltcal._panic()
    # The interpreter goes on.
    assert ltcal.read_campaign(CAMPAIGN).readings.shape[0] > 0


def test_quickstart_runs(tmp_path):
    # From a folder that sees the repository's pipelines and examples, so
    # that its results/ is its own and the committed one stays untouched.
    here = tmp_path / "repo"
    here.mkdir()
    for name in ("pipelines", "examples"):
        (here / name).symlink_to(REPO / name)
    env = dict(os.environ, MPLBACKEND="Agg")
    done = subprocess.run(
        [sys.executable, "examples/quickstart.py", str(tmp_path)],
        cwd=here,
        env=env,
        capture_output=True,
        text=True,
    )
    assert done.returncode == 0, done.stderr
    assert (tmp_path / "figure8.png").stat().st_size > 10_000
    assert "station-drift at S4" in done.stdout


def test_ctrl_c_raises_keyboard_interrupt_while_rust_runs(tmp_path):
    # A sweep of minutes, interrupted two seconds in: Python gets its
    # KeyboardInterrupt within the polling interval, not at the run's end.
    script = (
        "import ltcal, sys, time\n"
        "print('started', flush=True)\n"
        "t = time.time()\n"
        "try:\n"
        f"    ltcal.run('pipelines/noise-sweep.toml', results={str(tmp_path)!r})\n"
        "    print('finished')\n"
        "except KeyboardInterrupt:\n"
        "    print('interrupted after', round(time.time() - t, 1), flush=True)\n"
    )
    p = subprocess.Popen([sys.executable, "-c", script], cwd=REPO, stdout=subprocess.PIPE, text=True)
    assert p.stdout.readline() == "started\n"
    time.sleep(2)
    p.send_signal(signal.SIGINT)
    out, _ = p.communicate(timeout=60)
    assert out.startswith("interrupted after"), out
    assert float(out.split()[-1]) < 10
    # The points under way finished and were cached before the exception
    # (they went on in a background thread, past it, and were lost when
    # the interpreter ended); nothing of the unfinished run was published.
    folder = tmp_path / "noise-sweep"
    assert list((folder / ".ltcal" / "packs").glob("*.pack"))
    assert not (folder / "run.json").exists()
    assert not (folder / "sweep").exists()
    status = cli("status", "pipelines/noise-sweep.toml", "--results", tmp_path)
    assert " of 2000 sweep points done" in status.stdout


def test_the_gil_is_released_while_rust_works(tmp_path):
    ticks = 0
    done = threading.Event()

    def diagnose():
        ltcal.diagnose(CAMPAIGN, out=tmp_path / "out")
        done.set()

    worker = threading.Thread(target=diagnose)
    worker.start()
    while not done.is_set():
        ticks += 1
        time.sleep(0.001)
    worker.join()
    # The diagnosis takes a fraction of a second; a held GIL would leave
    # this thread one tick.
    assert ticks > 20


def test_a_run_with_set_is_an_experiment_with_its_own_tables(repo, results):
    plain = ltcal.run(PIPELINE, results=results).table("evaluate_sphere_noisy.summary")
    run = ltcal.run(PIPELINE, set={"stages.measure_sphere_noisy.seed": 2}, results=results)
    assert run.name.startswith("set-")
    assert "/runs/" in run.results
    changed = run.table("evaluate_sphere_noisy.summary")
    assert list(changed["statistic"]) == list(plain["statistic"])
    assert changed.loc[0, "after_um"] != plain.loc[0, "after_um"]
    # The pipeline's own results are still the plain run's.
    again = ltcal.run(PIPELINE, results=results).table("evaluate_sphere_noisy.summary")
    pd.testing.assert_frame_equal(again, plain)


FAILING = """
[stages.a]
kind = "mesh"
shape = "plane"

[stages.bad]
kind = "plot"
plot = "mesh-errors"
inputs = { table = "a" }
"""


def test_a_failed_stage_raises_stage_error_with_the_run(tmp_path):
    # A figure of a table that lacks its columns fails at run time.
    (tmp_path / "p.toml").write_text(FAILING)
    with pytest.raises(ltcal.StageError) as e:
        ltcal.run(tmp_path / "p.toml", results=tmp_path / "results")
    assert (e.value.stage, e.value.kind) == ("bad", "plot")
    assert "has no column `x_ref_mm`" in e.value.reason
    assert e.value.run.statuses == {"a": "ran", "bad": "failed"}
