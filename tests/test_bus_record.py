"""The raw record beside a run (RUN/bus.blf or bus.asc, RUN/serial.rec) and `cdpr replay`: a simulated run's
record read back by python-can, replayed through the drivers into the same samples.csv, a run cut by SIGINT
replayed up to its cut."""

import signal
import subprocess
import sys
import time

import can
import numpy as np
import pytest

from acquisition.busrecord import SERIAL_FORMAT, RecordError, read_can_record, read_serial_record
from acquisition.cli import main
from acquisition.runlog import read_run

DRIVES = (1, 2, 3, 4)  # the simulated prototype's node ids (sim_backend.backend)
ENCODERS = (11, 12, 13, 14)


@pytest.fixture(scope="module")
def sim_run(tmp_path_factory):
    out = tmp_path_factory.mktemp("rec") / "run"
    code = main(["startup", "--backend", "sim", "--grid", "2", "--hold", "0.5", "--max-rate", "80", "--no-html",
                 "--out", str(out)])
    assert code == 0
    return out


def test_bus_blf_holds_every_frame_of_every_node_in_both_directions(sim_run):
    frames = list(can.LogReader(sim_run / "bus.blf"))  # python-can's own reader
    sent = [f for f in frames if not f.is_rx]
    received = [f for f in frames if f.is_rx]
    run = read_run(sim_run)
    syncs = [f for f in sent if f.arbitration_id == 0x80]
    # one SYNC per control tick: the logged ticks are among them, the counter byte runs 1..240
    assert len(syncs) > int(run.extra["tick"][-1])
    assert [f.data[0] for f in syncs[:3]] == [1, 2, 3] and syncs[239].data[0] == 240 and syncs[240].data[0] == 1
    for node in DRIVES:
        assert any(f.arbitration_id == 0x200 + node for f in sent), f"no RPDO to drive {node}"
        assert any(f.arbitration_id == 0x600 + node for f in sent), f"no SDO request to drive {node}"
        for cob in (0x180, 0x280, 0x580, 0x700):
            assert any(f.arbitration_id == cob + node for f in received), f"no 0x{cob + node:X} from drive {node}"
    for node in ENCODERS:
        for cob in (0x180, 0x580, 0x700):
            assert any(f.arbitration_id == cob + node for f in received), f"no 0x{cob + node:X} from encoder {node}"
    assert any(f.arbitration_id == 0 and f.data[0] == 0x01 for f in sent)  # NMT start
    stamps = [f.timestamp for f in frames]
    assert all(b >= a for a, b in zip(stamps, stamps[1:], strict=False))


def test_serial_record_holds_both_devices_placed_among_the_can_frames(sim_run):
    settings, chunks = read_serial_record(sim_run / "serial.rec")
    assert settings["rate"] == 200.0 and settings["lockstep"] is True
    assert [d["node_id"] for d in settings["devices"]["drives"]] == list(DRIVES)
    assert [c.data for c in chunks if c.sent and c.device == "loadcells"] == [b"$INFO*0E\r\n"]  # the request
    lc = b"".join(c.data for c in chunks if c.device == "loadcells" and not c.sent)
    ahrs = b"".join(c.data for c in chunks if c.device == "ahrs" and not c.sent)
    assert lc.startswith(b"$INFO,") and lc.count(b"$LC,") > 1000  # the handshake answer, then a line per tick
    assert ahrs.startswith(b"\xfa\xff") and ahrs.count(b"\xfa\xff\x36") > 50  # Xbus preamble, MTData2 messages
    places = [c.can_frames for c in chunks]
    assert places == sorted(places) and places[-1] <= len(read_can_record(sim_run / "bus.blf"))


def test_replay_rebuilds_the_samples_byte_for_byte(sim_run, tmp_path, capsys):
    out = tmp_path / "replayed"
    assert main(["replay", str(sim_run), "--out", str(out)]) == 0
    original = (sim_run / "samples.csv").read_bytes()
    assert (out / "samples.csv").read_bytes() == original and original.count(b"\n") > 400
    n = original.count(b"\n") - 1
    assert f"{n} of {n} samples rebuilt" in capsys.readouterr().out
    # NEW_RUN exists now: refused without --force, one sentence, nothing touched
    assert main(["replay", str(sim_run), "--out", str(out)]) == 2
    assert capsys.readouterr().err.startswith(f"cdpr: --out {out} already holds a run; give another name")
    assert (out / "samples.csv").read_bytes() == original
    # with --force the first replay is moved aside and kept, never deleted
    assert main(["replay", str(sim_run), "--out", str(out), "--force"]) == 0
    kept = list(tmp_path.glob("replayed.replaced-*"))
    assert len(kept) == 1 and (kept[0] / "samples.csv").read_bytes() == original


def test_a_record_cut_short_replays_to_its_cut(sim_run, tmp_path):
    # a run killed outright: bus.blf ends in the middle of a container, serial.rec at the same place
    cut = tmp_path / "killed"
    cut.mkdir()
    for name in ("run.yaml", "samples.csv"):
        (cut / name).write_bytes((sim_run / name).read_bytes())
    blf = (sim_run / "bus.blf").read_bytes()
    (cut / "bus.blf").write_bytes(blf[:len(blf) // 3])
    kept = len(read_can_record(cut / "bus.blf"))
    lines = (sim_run / "serial.rec").read_text().split("\n")
    head = lines[:2] + [ln for ln in lines[2:] if ln and int(ln.split(" ")[1]) <= kept]
    (cut / "serial.rec").write_text("\n".join(head) + "\n" + lines[len(head)][:20])  # and a line cut off
    assert main(["replay", str(cut), "--out", str(tmp_path / "replayed")]) == 0
    original = (sim_run / "samples.csv").read_text().split("\n")
    rebuilt = (tmp_path / "replayed" / "samples.csv").read_text().split("\n")
    assert 100 < len(rebuilt) < len(original) * 0.6 and rebuilt[:-1] == original[:len(rebuilt) - 1]


def test_a_run_cut_by_sigint_replays_to_its_cut_and_shows_a_decoder_change(tmp_path, monkeypatch):
    out = tmp_path / "cut"
    cmd = [sys.executable, "-c", "import sys; from acquisition.cli import main; sys.exit(main())",
           "startup", "--backend", "sim", "--grid", "2", "--no-html", "--bus-log", "asc", "--out", str(out)]
    proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    samples = out / "samples.csv"
    deadline = time.monotonic() + 120
    while time.monotonic() < deadline and proc.poll() is None:
        if samples.exists() and samples.read_text().count("\n") > 30:
            break
        time.sleep(0.05)
    proc.send_signal(signal.SIGINT)
    _, stderr = proc.communicate(timeout=120)
    assert proc.returncode == 1 and "stopped by the operator (SIGINT)" in stderr
    assert (out / "bus.asc").is_file() and not (out / "bus.blf").exists()
    cut = read_run(out)
    assert cut.phase[-1] == "safe_stop" and len(cut) > 30
    replayed = tmp_path / "replayed"
    assert main(["replay", str(out), "--out", str(replayed)]) == 0
    assert (replayed / "samples.csv").read_bytes() == samples.read_bytes()
    # the replay runs the drivers' own decoding: a swivel encoder decoder that doubled the counts changes dsigma
    # only, and doubles it
    from drivers.swivel_encoder import CanopenSwivelEncoder

    make = CanopenSwivelEncoder._make_reading

    def doubled(self, t, seq, sync_count, values):
        return make(self, t, seq, sync_count, {k: 2 * v for k, v in values.items()})

    monkeypatch.setattr(CanopenSwivelEncoder, "_make_reading", doubled)
    assert main(["replay", str(out), "--out", str(replayed), "--force"]) == 0
    changed = read_run(replayed)
    assert (changed.tau == cut.tau).all() and (changed.dl == cut.dl).all() and (changed.roll == cut.roll).all()
    moved = np.abs(cut.dsigma) > 1e-3
    assert moved.any() and np.allclose(changed.dsigma[moved], 2 * cut.dsigma[moved], rtol=1e-3)


def test_serial_record_drops_a_line_cut_off_and_names_a_bad_one(tmp_path):
    rec = tmp_path / "serial.rec"
    rec.write_text(f"{SERIAL_FORMAT}\n{{\"rate\": 200}}\n1.0 3 loadcells tx 2441\n1.5 3 loadcells rx 2442\n"
                   f"2.0 4 ahrs rx fa")
    settings, chunks = read_serial_record(rec)
    assert settings == {"rate": 200}
    assert [(c.can_frames, c.sent, c.data) for c in chunks] == [(3, True, b"$A"), (3, False, b"$B")]
    rec.write_text(f"{SERIAL_FORMAT}\n{{}}\n1.0 3 scale rx 2441\n")
    with pytest.raises(RecordError, match="line 3 is not"):
        read_serial_record(rec)


def test_replay_refuses_a_run_without_a_record(tmp_path, capsys):
    assert main(["replay", str(tmp_path), "--out", str(tmp_path / "new")]) == 2
    assert "bus.blf: no such file" in capsys.readouterr().err
