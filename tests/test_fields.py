"""One YAML reader for the robot, simulator and device files (calib/fields.py)."""

from __future__ import annotations

import pytest

from calib.errors import CdprError
from calib.robot import RobotDescriptionError, load_robot
from drivers.config import DeviceConfigError, load_device_config
from sim_backend.config import SimConfigError, load_sim_config

LOADERS = [(load_robot, RobotDescriptionError, "."), (load_sim_config, SimConfigError, "."),
           (load_device_config, DeviceConfigError, "")]


@pytest.mark.parametrize("load, error, end", LOADERS)
def test_bad_yaml_is_one_sentence_naming_the_file(tmp_path, load, error, end):
    bad = tmp_path / "bad.yaml"
    bad.write_text("a: [1, 2\nb: 3\n")
    with pytest.raises(error) as info:
        load(bad)
    text = str(info.value)
    assert text.startswith(f"{bad}: not valid YAML (") and text.endswith(")" + end) and "\n" not in text
    assert isinstance(info.value, CdprError) and info.value.exit_status == 2


@pytest.mark.parametrize("load, error, end", LOADERS)
def test_an_unreadable_file_is_one_sentence(tmp_path, load, error, end):
    folder = tmp_path / "folder.yaml"
    folder.mkdir()
    (folder / "x").write_text("")
    with pytest.raises(error, match=r"folder\.yaml: (cannot read the \w+ \w+ \(|simulation configuration file)"):
        load(folder)


def test_field_errors_keep_each_file_kinds_wording(tmp_path):
    robot = tmp_path / "r.yaml"
    robot.write_text("name: x\nplatform: {mass: .nan}\n")
    with pytest.raises(RobotDescriptionError, match=r"r\.yaml: required field '\w+' is missing\.$"):
        load_robot(robot)
    sim = tmp_path / "s.yaml"
    sim.write_text("seed_noise: 1\n")
    with pytest.raises(SimConfigError, match=r"s\.yaml: field 'seed_noise' = 1 is not one of .*\.$"):
        load_sim_config(sim)
