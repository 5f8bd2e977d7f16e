"""Shared pytest fixtures.

`irma_data`: the folder of the authors' IRMA4U recordings (see /work/shared/data/irma4u/README.md).
It is taken from the environment variable CDPR_DATA, else from `<repo>/../shared/data/irma4u`;
tests that use it are skipped, with the reason, when the folder is absent. The data are never
copied into the repository.
"""

from __future__ import annotations

import os
from pathlib import Path

import pytest

REPO_ROOT = Path(__file__).resolve().parent.parent
DEFAULT_DATA = REPO_ROOT.parent / "shared" / "data" / "irma4u"


@pytest.fixture(scope="session")
def irma_data() -> Path:
    """Path to the IRMA4U data folder, or skip when it is not available."""
    env = os.environ.get("CDPR_DATA")
    folder = Path(env) if env else DEFAULT_DATA
    if not folder.is_dir():
        source = "CDPR_DATA" if env else "the default location"
        pytest.skip(f"IRMA4U data folder {folder} (from {source}) not found")
    if not (folder / "sc_8_final_parsed.mat").is_file():
        pytest.skip(f"IRMA4U data folder {folder} has no sc_8_final_parsed.mat")
    return folder
