"""One exception base (calib/errors.py): every error class of the project derives from CdprError, keeps its
builtin base, and the CLI maps it once by its exit status."""

from __future__ import annotations

import ast
import importlib
from pathlib import Path

from acquisition.cli import main
from acquisition.cli.errors import OperationError, UsageError
from calib.errors import CdprError

ROOT = Path(__file__).resolve().parents[1]


def error_classes() -> list[type]:
    """Every class of the packages that derives from BaseException, warnings left out."""
    found = []
    for pkg in ("acquisition", "calib", "drivers", "sim_backend"):
        for f in sorted((ROOT / pkg).rglob("*.py")):
            tree = ast.parse(f.read_text())
            names = [n.name for n in tree.body if isinstance(n, ast.ClassDef)]
            if not names:
                continue
            parts = list(f.relative_to(ROOT).with_suffix("").parts)
            module = importlib.import_module(".".join(parts[:-1] if parts[-1] == "__init__" else parts))
            for name in names:
                cls = getattr(module, name)
                if issubclass(cls, BaseException) and not issubclass(cls, Warning):
                    found.append(cls)
    return found


def test_every_error_of_the_project_derives_from_the_one_base_and_keeps_its_builtin_one():
    classes = error_classes()
    assert len(classes) >= 22
    assert [c.__name__ for c in classes if not issubclass(c, CdprError)] == ["Interrupted"]  # a KeyboardInterrupt
    bad_input = {c.__name__ for c in classes if issubclass(c, ValueError)}
    assert {"RunFormatError", "RobotDescriptionError", "DeviceConfigError", "SimConfigError",
            "OutputExistsError"} <= bad_input
    assert {"DeviceError", "SelfCalFailure", "StartupStopped", "SimulationError"} <= {
        c.__name__ for c in classes if issubclass(c, RuntimeError)}


def test_exit_status_follows_the_kind_of_error():
    from acquisition.runlog import RunFormatError
    from drivers.interfaces import DeviceError

    assert RunFormatError("x").exit_status == 2 and UsageError("x").exit_status == 2
    assert DeviceError("x").exit_status == 1 and OperationError("x").exit_status == 1


def test_the_cli_maps_an_error_of_the_project_to_one_sentence(tmp_path, capsys):
    (tmp_path / "run.yaml").write_text("format: [\n")
    assert main(["solve", str(tmp_path)]) == 2
    err = capsys.readouterr().err
    assert err.startswith(f"cdpr: {tmp_path}") and err.count("\n") == 1
