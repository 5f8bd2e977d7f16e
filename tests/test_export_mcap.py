"""`cdpr export RUN --format mcap`: read back with the mcap reader, every sample value, the windows, the events
and the solution as written, each channel with its JSON Schema."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest
from mcap.reader import make_reader

from acquisition.cli import main
from acquisition.importers import import_irma
from acquisition.runlog import new_run, read_run, write_run, write_solution

SOLUTION = {"method": "tlse", "initial_pose": [0.3604, 0.3675, 1.158, 0.0847, -0.0717, 0.007],
            "sensor_offsets": {"length": [1.65, 1.10, 1.64, 2.04], "swivel": [1.28, -1.08, 1.05, -1.28], "yaw": 0.01},
            "windows": [[4, 7], [8, 11]], "chi2": 29.9}


def read_mcap(path):
    """{topic: [(log_time, message dict)]}, {topic: schema dict}, metadata {name: dict}."""
    messages, schemas = {}, {}
    with open(path, "rb") as fh:
        reader = make_reader(fh)
        for schema, channel, message in reader.iter_messages():
            assert schema.encoding == "jsonschema" and channel.message_encoding == "json"
            schemas[channel.topic] = json.loads(schema.data)
            messages.setdefault(channel.topic, []).append((message.log_time, json.loads(message.data)))
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
    out = tmp_path / "run.mcap"
    assert main(["export", str(small_run.path), "--format", "mcap", "-o", str(out)]) == 0
    assert "12 samples" in capsys.readouterr().out
    run = read_run(small_run.path)
    messages, schemas, meta = read_mcap(out)
    assert set(messages) == {"/samples", "/windows", "/events", "/solution"}
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
