"""What the tests share: the repository (pipelines, example campaigns, the
built `ltcal` binary) and a results folder of their own."""

import os
import pathlib

import pytest

# The tests run against the installed package from any folder; the
# repository is found beside them (or named by LTCAL_REPO).
REPO = pathlib.Path(os.environ.get("LTCAL_REPO", pathlib.Path(__file__).resolve().parents[2]))
BINARY = REPO / "target" / "release" / "ltcal"
CAMPAIGN = REPO / "examples" / "campaigns" / "example-05-station-drift"


@pytest.fixture
def repo(monkeypatch):
    """The repository as the current folder (pipeline paths are relative)."""
    monkeypatch.chdir(REPO)
    return REPO


@pytest.fixture(scope="session")
def results(tmp_path_factory):
    """A results folder shared by the tests, apart from the committed one."""
    return tmp_path_factory.mktemp("results")
