"""Shared pytest fixtures.

`run8`, `run`: sc_8_final (parsed) imported and solved with the default options once per module, and a copy
of it for one test (the rough-edge tests, tests/test_rough_edges*.py, give it careless inputs).

`irma_data`: the folder of the authors' IRMA4U recordings (see /work/shared/data/irma4u/README.md).
It is taken from the environment variable CDPR_DATA, else from `<repo>/../shared/data/irma4u`;
tests that use it are skipped, with the reason, when the folder is absent, and FAIL instead when
CDPR_REQUIRE_DATA=1 (what .ci/run sets: a CI run never passes with the real-data tests silently off).
The data are never copied into the repository.
"""

from __future__ import annotations

import os
import shutil
from pathlib import Path

import pytest

REPO_ROOT = Path(__file__).resolve().parent.parent
DEFAULT_DATA = REPO_ROOT.parent / "shared" / "data" / "irma4u"


@pytest.fixture(scope="session")
def irma_data() -> Path:
    """Path to the IRMA4U data folder, or skip when it is not available."""
    env = os.environ.get("CDPR_DATA")
    folder = Path(env) if env else DEFAULT_DATA
    missing = None
    if not folder.is_dir():
        source = "CDPR_DATA" if env else "the default location"
        missing = f"IRMA4U data folder {folder} (from {source}) not found"
    elif not (folder / "sc_8_final_parsed.mat").is_file():
        missing = f"IRMA4U data folder {folder} has no sc_8_final_parsed.mat"
    if missing is not None:
        if os.environ.get("CDPR_REQUIRE_DATA") == "1":
            pytest.fail(f"{missing}, and CDPR_REQUIRE_DATA=1 requires the real-data tests to run", pytrace=False)
        pytest.skip(missing)
    return folder


@pytest.fixture(scope="module")
def run8(irma_data, tmp_path_factory) -> Path:
    """sc_8_final (parsed) imported, solved with the default options once: a run with its solution."""
    from acquisition.cli import main

    out = tmp_path_factory.mktemp("r30") / "R"
    assert main(["import", "irma", str(irma_data / "sc_8_final_parsed.mat"), "-o", str(out)]) == 0
    assert main(["solve", str(out), "--json"]) == 0
    return out


@pytest.fixture
def run(run8, tmp_path) -> Path:
    """A copy of ``run8`` that a test may change."""
    r = tmp_path / "R"
    shutil.copytree(run8, r)
    return r
