"""`cdpr export RUN --format mcap`: read back with the mcap reader, every sample value, the windows, the events
and the solution as written, each JSON channel with its JSON Schema; the 3D scene, the transforms and the log
decoded with the Foxglove schemas the file carries (protobuf), the scene's cables checked against the model."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest
import yaml
from google.protobuf import descriptor_pb2, descriptor_pool, message_factory
from mcap.reader import make_reader

from acquisition.cli import main
from acquisition.importers import import_irma
from acquisition.runlog import read_run
from acquisition.runwriter import new_run, write_run, write_solution

SOLUTION = {"method": "tlse", "initial_pose": [0.3604, 0.3675, 1.158, 0.0847, -0.0717, 0.007],
            "sensor_offsets": {"length": [1.65, 1.10, 1.64, 2.04], "swivel": [1.28, -1.08, 1.05, -1.28], "yaw": 0.01},
            "windows": [[4, 7], [8, 11]], "chi2": 29.9}


FOXGLOVE = {"/scene": "foxglove.SceneUpdate", "/tf": "foxglove.FrameTransform", "/log": "foxglove.Log"}


def protobuf_class(name: str, file_descriptor_set: bytes):
    """The message class of ``name`` from a schema's FileDescriptorSet (what a Foxglove viewer decodes with)."""
    pool = descriptor_pool.DescriptorPool()
    fds = descriptor_pb2.FileDescriptorSet.FromString(file_descriptor_set)
    for f in fds.file:
        pool.Add(f)
    return message_factory.GetMessageClass(pool.FindMessageTypeByName(name))


def read_mcap(path):
    """{topic: [(log_time, message dict or decoded protobuf)]}, {topic: JSON schema dict or schema name},
    metadata {name: dict}."""
    messages, schemas, classes = {}, {}, {}
    with open(path, "rb") as fh:
        reader = make_reader(fh)
        for schema, channel, message in reader.iter_messages():
            if channel.topic in FOXGLOVE:
                assert (schema.name, schema.encoding, channel.message_encoding) == (
                    FOXGLOVE[channel.topic], "protobuf", "protobuf")
                if schema.name not in classes:
                    classes[schema.name] = protobuf_class(schema.name, schema.data)
                schemas[channel.topic] = schema.name
                msg = classes[schema.name].FromString(message.data)
            else:
                assert schema.encoding == "jsonschema" and channel.message_encoding == "json"
                schemas[channel.topic] = json.loads(schema.data)
                msg = json.loads(message.data)
            messages.setdefault(channel.topic, []).append((message.log_time, msg))
        meta = {m.name: dict(m.metadata) for m in reader.iter_metadata()}
    return messages, schemas, meta


def assert_samples_round_trip(run, got):
    cols = run.columns()
    assert len(got) == len(run)
    for j, (_, msg) in enumerate(got):
        assert list(msg) == list(cols)
        for name, col in cols.items():
            v = col[j]
            if col.dtype.kind == "f":
                assert (msg[name] is None and math.isnan(v)) or msg[name] == float(v), (j, name)
            else:
                assert msg[name] == v.item(), (j, name)


@pytest.fixture()
def small_run(tmp_path):
    rng = np.random.default_rng(3)
    N = 12
    temperature = 20 + rng.normal(0, 1, N)
    temperature[5] = np.nan  # an extra column may miss a value
    run = new_run("irma4u", "equilibrium", 0.1, "sim", t=np.arange(N) * 0.1, tau=100 + rng.normal(0, 5, (N, 4)),
                  tau_ref=np.full((N, 4), 100.0), dl=rng.normal(0, 0.2, (N, 4)), dsigma=rng.normal(0, 0.1, (N, 4)),
                  roll=rng.normal(0, 0.05, N), pitch=rng.normal(0, 0.05, N), dyaw=rng.normal(0, 0.01, N),
                  phase=["pretension"] * 4 + ["hold"] * 4 + ["settle"] * 4, setpoint=[-1] * 4 + [0] * 4 + [1] * 4,
                  extra={"tick": np.arange(N, dtype=np.int64) * 20, "temperature": temperature})
    run.meta["events"].append({"t": 1.05, "kind": "operator", "message": "stopped by the operator (SIGINT)."})
    return write_run(tmp_path / "run", run)


def test_every_sample_value_the_windows_events_and_solution_round_trip(small_run, tmp_path, capsys):
    write_solution(small_run.path, SOLUTION)
    meta = yaml.safe_load((small_run.path / "run.yaml").read_text())
    meta["sequential"] = {"tolerance_m": 0.003, "stop": "tolerance", "windows": [  # a sequential startup's
        {"pose": 0, "position_sigma_m": None, "initial_pose": [0.1, 0.2, 0.9, 0, 0, 0], "iterations": 0},
        {"pose": 1, "position_sigma_m": 0.002, "initial_pose": [0.11, 0.21, 0.91, 0, 0, 0], "iterations": 3}]}
    (small_run.path / "run.yaml").write_text(yaml.safe_dump(meta))
    out = tmp_path / "run.mcap"
    assert main(["export", str(small_run.path), "--format", "mcap", "-o", str(out)]) == 0
    assert "12 samples" in capsys.readouterr().out
    run = read_run(small_run.path)
    messages, schemas, meta = read_mcap(out)
    assert {"/samples", "/windows", "/events", "/solution", "/supervisor", "/log", "/scene"} <= set(messages)
    assert_samples_round_trip(run, messages["/samples"])
    assert messages["/samples"][5][1]["temperature"] is None
    assert schemas["/samples"]["properties"]["tau_3"] == {"type": ["number", "null"]}
    assert schemas["/samples"]["properties"]["setpoint"] == {"type": "integer"}
    times = [t for t, _ in messages["/samples"]]
    assert np.allclose(np.diff(times), 100_000_000) and times[0] > 1.7e18  # ns, from run.yaml's creation time
    assert [m for _, m in messages["/windows"]] == [
        {"first": 4, "last": 7, "t_first": run.t[4], "t_last": run.t[7], "setpoint": 0, "source": "solution"},
        {"first": 8, "last": 11, "t_first": run.t[8], "t_last": run.t[11], "setpoint": 1, "source": "solution"}]
    assert [m for _, m in messages["/events"]] == run.events
    assert messages["/events"][0][0] - times[0] == 1_050_000_000
    assert [m for _, m in messages["/solution"]] == [SOLUTION]
    # the online estimates, each at the end of its pose's window; the supervisor watched, then stopped
    assert [(t, m["pose"], m["position_sigma_m"], m["initial_pose"][0]) for t, m in messages["/estimate"]] == [
        (times[7], 0, None, 0.1), (times[11], 1, 0.002, 0.11)]
    assert [m["state"] for _, m in messages["/supervisor"]][-1] == "stopped"
    assert messages["/supervisor"][-1][1]["stop"] == "stopped by the operator (SIGINT)."
    assert sum("online estimate" in m.message for _, m in messages["/log"]) == 2
    assert json.loads(meta["run.yaml"]["json"])["procedure"]["method"] == "equilibrium"


def test_an_unsolved_real_run_exports_every_value_and_the_windows_found_in_its_signals(irma_data, tmp_path):
    run = import_irma(irma_data / "sc_8_final_parsed.mat", tmp_path / "irma")
    out = tmp_path / "irma.mcap"
    assert main(["export", str(run.path), "--format", "mcap", "-o", str(out)]) == 0
    run = read_run(run.path)
    messages, _, _ = read_mcap(out)
    assert "/solution" not in messages
    assert_samples_round_trip(run, messages["/samples"])
    wins = [m for _, m in messages["/windows"]]
    assert len(wins) >= 8 and {w["source"] for w in wins} == {"signals"}  # the authors held 8 setpoints


def entity(update, name):
    return next(e for e in update.entities if e.id == name)


def segment_points(line):
    """A LineList's points as (n, 2, 3): (pulley exit, anchor) per cable."""
    return np.array([[p.x, p.y, p.z] for p in line.points]).reshape(-1, 2, 3)


def test_the_scene_of_a_solved_real_run_is_the_model_at_the_solved_poses(irma_data, tmp_path):
    from calib.equilibrium import direct_statics
    from calib.kinematics import inverse_kinematics
    from calib.selfcal import solve

    run = import_irma(irma_data / "sc_8_final_parsed.mat", tmp_path / "irma")
    run = read_run(run.path)
    sol = solve(run.robot, run).to_json()
    write_solution(run.path, sol)
    out = tmp_path / "irma.mcap"
    assert main(["export", str(run.path), "--format", "mcap", "-o", str(out)]) == 0
    messages, schemas, _ = read_mcap(out)
    robot = run.robot
    scenes = [m for _, m in messages["/scene"]]
    assert len(scenes) == len(run) and schemas["/scene"] == "foxglove.SceneUpdate"

    def model_segments(poses):
        kin = inverse_kinematics(robot, poses)
        anchors = kin.poses[:, None, :3] + kin.a_rel  # A_i = p + R a_i'
        return np.stack([anchors - kin.rho, anchors], 2)  # (k, n, 2, 3): B_i on the pulley, A_i

    # the solve's initial pose, drawn from the reference sample on
    ref = sol["reference_sample"]
    assert all(e.id != "solution" for e in scenes[ref - 1].entities)
    want = model_segments(np.array(sol["initial_pose"]))[0]
    for update in (scenes[ref], scenes[-1]):
        np.testing.assert_allclose(segment_points(entity(update, "solution").lines[0]), want, rtol=0, atol=1e-9)
    # every sample: the platform at the direct statics of its measured tensions, its cables the model's there
    pick = np.linspace(0, len(run) - 1, 40).astype(int)
    statics = direct_statics(robot, run.tau[pick])
    assert statics.converged.all()
    want = model_segments(statics.poses)
    for k, j in enumerate(pick):
        got = segment_points(entity(scenes[j], "cables").lines[0])
        np.testing.assert_allclose(got, want[k], rtol=0, atol=1e-9)
        cube = entity(scenes[j], "platform").cubes[0].pose.position
        np.testing.assert_allclose([cube.x, cube.y, cube.z], statics.poses[k, :3], rtol=0, atol=1e-9)
        tf = messages["/tf"][j][1]
        assert tf.child_frame_id == "platform" and abs(tf.translation.z - statics.poses[k, 2]) < 1e-9
    # the ghosts are the planned poses (an imported run has none: the statics of its setpoints), one per setpoint
    ghosts = entity(scenes[0], "ghosts").cubes
    planned = direct_statics(robot, run.setpoints).poses
    assert len(ghosts) == len(run.setpoints) == 8
    np.testing.assert_allclose([[g.pose.position.x, g.pose.position.y, g.pose.position.z] for g in ghosts],
                               planned[:, :3], rtol=0, atol=1e-9)
    logs = [m.message for _, m in messages["/log"]]
    assert sum("equilibrium window" in m for m in logs) == len(sol["windows"])
