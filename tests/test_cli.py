"""What a new user meets on the command line: exit codes and messages."""
import os
import signal
import socket
import subprocess
import sys
import time
from pathlib import Path

import pytest

from service import cli
from service.cli_link import LinkWatcher
from service.cli_serve import check_port_free
from service.readout import LinkState

TACTILE = str(Path(sys.executable).with_name("tactile"))
ABSENT = "/dev/ttyUSB_tactile_absent"


def interruptible(*argv: str) -> subprocess.Popen:
    """``tactile`` in a subprocess that takes Ctrl-C as from a terminal (a shell's
    background job, as a test run may be, starts it with SIGINT ignored)."""
    return subprocess.Popen([TACTILE, *argv], stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                            preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL))


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


# 1. record and replay with nothing to read


def test_record_from_an_absent_device_says_so_once_and_exits_1_removing_the_empty_file(tmp_path, capsys):
    out = tmp_path / "run.mcap"
    assert cli.main(["record", "--source", ABSENT, "--out", str(out), "--seconds", "1.2"]) == 1
    captured = capsys.readouterr()
    assert "Ctrl-C" not in captured.out and "for 1.2 s" in captured.out
    assert captured.err.count(f"waiting for {ABSENT}: ") == 1
    assert f"nothing recorded: no byte from {ABSENT}" in captured.err
    assert f"removed the empty {out}" in captured.err and not out.exists()


def test_record_of_a_source_that_delivers_keeps_its_file_and_exits_0(tmp_path, capsys):
    out = tmp_path / "run.mcap"
    assert cli.main(["record", "--source", "sim://?scene=idle", "--out", str(out), "--seconds", "0.8"]) == 0
    assert out.stat().st_size > 0
    assert "nothing recorded" not in capsys.readouterr().err


def test_record_refuses_to_overwrite_a_recording_unless_told(tmp_path, capsys):
    """A repeated command lost the earlier recording without a word (POST /record/start refuses it: 409)."""
    out = tmp_path / "run.mcap"
    out.write_bytes(b"yesterday's run")
    assert cli.main(["record", "--source", "sim://?scene=idle", "--out", str(out), "--seconds", "0.5"]) == 2
    assert f"{out} (15 bytes) exists: name another file, or give --overwrite" in capsys.readouterr().err
    assert out.read_bytes() == b"yesterday's run"
    assert cli.main(["record", "--source", "sim://?scene=idle", "--out", str(out), "--seconds", "0.5",
                     "--overwrite"]) == 0
    assert out.read_bytes()[:8] == b"\x89MCAP0\r\n"


def test_record_refuses_one_file_for_the_recording_and_the_raw_bytes(tmp_path, capsys):
    out = tmp_path / "run.mcap"
    assert cli.main(["record", "--source", "sim://?scene=idle", "--out", str(out), "--raw",
                     str(tmp_path / "." / "run.mcap"), "--seconds", "0.5"]) == 2
    assert "--out and --raw name the same file" in capsys.readouterr().err and not out.exists()


@pytest.mark.parametrize("port", ["0", "65536", "99999", "-1", "http"])
def test_a_port_outside_the_tcp_range_is_refused_by_name(port, capsys):
    """--port 99999 printed a dashboard URL on 99999 and listened on 34463 (the value modulo 65536)."""
    with pytest.raises(SystemExit) as exit_:
        cli.main(["serve", "--port", port])
    assert exit_.value.code == 2
    assert f"argument --port: port {port if port.lstrip('-').isdigit() else repr(port)}" in capsys.readouterr().err


@pytest.mark.parametrize("text", ["1e-300", "5e-5"])
def test_a_replay_speed_too_slow_to_wait_for_is_refused_by_name_before_the_export_is_made(text, tmp_path, capsys):
    """--speed 1e-300 ended in an OverflowError traceback (a wait of 1e300 s) with an empty export left
    behind. A day-long recording at the slowest speed, 1e-4, waits 8.64e8 s: within time.sleep's 2**63 ns
    (9.2e9 s), as is any recording up to 10 days."""
    out = tmp_path / "x.jsonl"
    with pytest.raises(SystemExit) as exit_:
        cli.main(["replay", str(tmp_path / "run.bin"), "--export", str(out), "--speed", text])
    assert exit_.value.code == 2 and f"argument --speed: speed {text!r} must be at least 0.0001" in capsys.readouterr().err
    assert not out.exists()
    with pytest.raises(ValueError, match=f"replay:// speed '{text}' must be at least 0.0001"):
        from service.sources.protocol_replay import parse_replay_url

        parse_replay_url(f"replay://run.mcap?speed={text}")
    assert 10 * 86400 / 1e-4 < 2**63 * 1e-9  # the bound the docstring gives


@pytest.mark.parametrize("command", [["replay", "x.bin"], ["record", "--out", "x.mcap"], ["calibrations", "list"],
                                     ["calibrations", "show", "ab12"]])
def test_a_registry_named_for_reading_must_exist(command, tmp_path, capsys):
    """A mistyped --registry made a new empty registry: every sensor silently on its built-in calibration."""
    typo = tmp_path / "typo.sqlite3"
    with pytest.raises(SystemExit) as exit_:
        cli.main(command + ["--registry", str(typo)])
    assert exit_.value.code == 2 and f"no registry at {typo}" in capsys.readouterr().err
    assert not typo.exists()


def test_a_registry_stored_into_is_made_only_in_a_directory_that_exists(tmp_path, capsys):
    with pytest.raises(SystemExit):
        cli.main(["calibrations", "import", "c.json", "--registry", str(tmp_path / "no" / "dir" / "r.sqlite3")])
    assert f"no directory {tmp_path / 'no' / 'dir'} for the registry" in capsys.readouterr().err
    assert not (tmp_path / "no").exists()


def test_replay_of_a_file_without_a_valid_frame_exits_1_naming_it(tmp_path, capsys):
    text = tmp_path / "notes.txt"
    text.write_text("not a capture\n" * 100)
    export = tmp_path / "out.jsonl"
    assert cli.main(["replay", "--raw", str(text), "--export", str(export)]) == 1
    err = capsys.readouterr().err
    assert f"{text}: no valid frame" in err and not export.exists()


def test_replay_level_auto_says_which_level_it_took(tmp_path, capsys):
    raw = tmp_path / "run.bin"
    assert cli.main(["sim", "--capture", str(raw), "--seconds", "0.3", "--scene", "press"]) == 0
    assert cli.main(["replay", str(raw), "--level", "auto"]) == 0
    err = capsys.readouterr().err
    assert "level auto chose " in err and '"level_reason"' in err


# 2. serve tells the terminal what the link does


def test_link_watcher_says_each_change_once():
    link, said = LinkState("/dev/ttyX"), []
    watcher = LinkWatcher(lambda: link, out=None)
    watcher.say = said.append
    watcher.poll(100.0)  # not tried yet: nothing to say
    link.last_error = "no such device"
    for t in (100.5, 101.0, 101.5):  # every backoff attempt fails: said once
        watcher.poll(t)
    link.up, link.connects, link.connected_at, link.last_data_time = True, 1, 102.0, 102.0
    watcher.poll(102.1)
    watcher.poll(103.0)  # silent for 1 s: stale
    link.last_data_time = 103.4
    watcher.poll(103.5)
    # lost and back between two looks, within the stale threshold of the last byte (0.4 s)
    link.connects, link.connected_at, link.last_error = 2, 103.7, "read failed"
    watcher.poll(103.8)
    link.up = False
    watcher.poll(105.0)
    link.finished = True
    watcher.poll(106.0)
    assert said == [
        "waiting for /dev/ttyX: no such device",
        "connected to /dev/ttyX",
        "no bytes from /dev/ttyX for 1.0 s (link stale)",
        "bytes from /dev/ttyX again",
        "link to /dev/ttyX lost (read failed); connected again",
        "link to /dev/ttyX lost: read failed; waiting for it",
        "replay of /dev/ttyX finished (the service keeps serving; Ctrl-C to stop)",
    ]


def test_serve_from_an_absent_device_says_so_once_prints_the_url_and_ends_on_ctrl_c():
    port = free_port()
    process = interruptible("serve", "--source", ABSENT, "--port", str(port))
    try:
        deadline = time.monotonic() + 20
        while time.monotonic() < deadline:  # serving, and a few reopen attempts later
            try:
                socket.create_connection(("127.0.0.1", port), timeout=0.5).close()
                break
            except OSError:
                time.sleep(0.1)
        time.sleep(2.0)
        process.send_signal(signal.SIGINT)
        out, err = process.communicate(timeout=10)
    finally:
        process.kill()
        process.communicate()
    assert process.returncode == 130
    assert f"dashboard at http://127.0.0.1:{port}/" in out
    assert err.count(f"waiting for {ABSENT}: ") == 1, err
    assert "tactile serve: interrupted" in err and "Traceback" not in err


# 3. a port in use


def test_serve_on_a_port_in_use_exits_2_before_printing_a_url(capsys):
    with socket.socket() as other:
        other.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        other.bind(("127.0.0.1", 0))
        other.listen()
        port = other.getsockname()[1]
        assert cli.main(["serve", "--port", str(port)]) == 2
    captured = capsys.readouterr()
    assert f"port {port} on 127.0.0.1 is in use (another tactile serve?); choose --port" in captured.err
    assert "dashboard" not in captured.out


def test_a_free_port_passes_the_check():
    check_port_free("127.0.0.1", free_port())


# 5. Ctrl-C ends long commands at once, without a traceback


@pytest.mark.parametrize("argv", [["model", "convergence", "--out", "{tmp}"], ["bench", "--seconds", "5"],
                                  ["sim", "--tcp", "0"], ["sim", "--pty"]])
def test_ctrl_c_ends_a_long_command_within_a_second(argv, tmp_path):
    process = interruptible(*(a.format(tmp=tmp_path) for a in argv))
    try:
        time.sleep(1.5)  # past the imports, in the middle of the work
        assert process.poll() is None
        process.send_signal(signal.SIGINT)
        sent = time.monotonic()
        _, err = process.communicate(timeout=5)
        took = time.monotonic() - sent
    finally:
        process.kill()
        process.communicate()
    assert process.returncode == 130 and took < 2.0, (took, err)
    name = "model convergence" if argv[0] == "model" else argv[0]
    assert err.strip().endswith(f"tactile {name}: interrupted") and "Traceback" not in err


def test_progress_bars_stay_off_the_output_when_stderr_is_no_terminal(tmp_path):
    raw = tmp_path / "run.bin"
    subprocess.run([TACTILE, "sim", "--capture", str(raw), "--seconds", "0.3"], check=True, capture_output=True)
    result = subprocess.run([TACTILE, "replay", str(raw)], capture_output=True, text=True, timeout=60)
    assert result.returncode == 0 and "%|" not in result.stderr and "\r" not in result.stderr


# 6. help texts


def help_of(*argv: str) -> str:
    return subprocess.run([TACTILE, *argv, "--help"], capture_output=True, text=True, check=True).stdout


def test_sim_help_names_every_scene_and_the_seed():
    from firmware_sim.scenes import SCENES

    text = " ".join(help_of("sim").split())
    assert all(name in text for name in SCENES) and "--seed SEED seed of" in text


def test_every_option_has_help_and_defaults_are_shown():
    parser = cli.build_parser()
    missing = []

    def walk(p, path):
        for action in p._actions:
            if action.help is None:
                missing.append(f"{path} {action.option_strings or action.dest}")
            for name, sub in getattr(action, "choices", None).items() if isinstance(action.choices, dict) else ():
                walk(sub, f"{path} {name}")

    walk(parser, "tactile")
    assert [m for m in missing if "file" not in m and "command" not in m and "action" not in m] == []
    assert "(default: 10.0)" in " ".join(help_of("bench").split())


def test_an_unknown_scene_is_refused_naming_the_known_ones(capsys):
    with pytest.raises(SystemExit) as exit_:
        cli.main(["sim", "--capture", os.devnull, "--scene", "bogus"])
    assert exit_.value.code == 2
    assert "unknown scene 'bogus'; known scenes: idle, press, slow_press" in capsys.readouterr().err


@pytest.mark.parametrize("name", ["out.csv", "out.jsonl.gz", "out"])
def test_an_export_of_no_known_format_is_refused_by_name(name, tmp_path, capsys):
    """They got plain JSON lines without a word."""
    capture = tmp_path / "c.bin"
    capture.write_bytes(b"\x00" * 10)
    assert cli.main(["replay", "--raw", str(capture), "--export", str(tmp_path / name)]) == 2
    assert f"--export {tmp_path / name}: no format for" in capsys.readouterr().err
    assert not (tmp_path / name).exists()


def test_an_export_suffix_in_capitals_is_its_format(tmp_path):
    from firmware_sim.board import BoardConfig, SimGrid, capture

    raw = tmp_path / "c.bin"
    raw.write_bytes(capture(BoardConfig(scene="idle", sensors=[SimGrid(0)]), 1.5)[0])
    assert cli.main(["replay", "--raw", str(raw), "--export", str(tmp_path / "out.PARQUET")]) == 0
    assert (tmp_path / "out.PARQUET").read_bytes()[:4] == b"PAR1"


def test_a_capture_whose_every_data_frame_is_corrupt_exits_1_saying_so(tmp_path, capsys):
    """Its INFO counted as a valid frame: 0 rows exported and exit 0."""
    from firmware_sim.board import BoardConfig, SimGrid, capture
    from service.protocol_decoder import Decoder

    data = bytearray(capture(BoardConfig(scene="idle", sensors=[SimGrid(0)]), 0.5)[0])
    frames = Decoder().feed(bytes(data))
    assert frames[0].type.name == "INFO" and len(frames) > 400
    info_end = data.index(b"\xa5\x5a", 1)  # the INFO comes first: every frame after it gets a bad CRC
    for pos in range(info_end, len(data) - 1):
        if data[pos:pos + 2] == b"\xa5\x5a":
            data[pos + 14] ^= 0xFF
    raw = tmp_path / "bad.bin"
    raw.write_bytes(bytes(data))
    assert cli.main(["replay", "--raw", str(raw), "--export", str(tmp_path / "out.jsonl")]) == 1
    err = capsys.readouterr().err
    assert "no valid data frame (1 INFO/ERROR" in err and "removed the empty" in err


def test_link_messages_of_several_boards_name_their_board_one_whole_line_each():
    """Two boards' watchers printed 'connected to socket://…tactile: connected to /dev/pts/0' on one line,
    and two sim:// boards both said only 'connected to sim://'."""
    import io
    import threading

    out = io.StringIO()
    watchers = [LinkWatcher(lambda: None, out=out, board=lambda n=name: n) for name in ("left", "right")]

    def chatter(watcher):
        for _ in range(300):
            watcher.say("connected to sim://")

    threads = [threading.Thread(target=chatter, args=(w,)) for w in watchers]
    for thread in threads:
        thread.start()
    for thread in threads:
        thread.join()
    lines = out.getvalue().splitlines()
    assert len(lines) == 600
    assert set(lines) == {"tactile: board left: connected to sim://", "tactile: board right: connected to sim://"}


def test_a_simulated_board_on_tcp_stops_after_its_seconds():
    """--seconds was a capture's length only: a pty or TCP board ran until Ctrl-C whatever it said."""
    started = time.monotonic()
    result = subprocess.run([TACTILE, "sim", "--tcp", "0", "--seconds", "1"], capture_output=True, text=True, timeout=30)
    assert result.returncode == 0 and "simulated board on socket://127.0.0.1:" in result.stdout
    assert time.monotonic() - started < 10


def test_output_into_a_pipe_its_reader_closed_ends_quietly(tmp_path):
    """`tactile calibrations show ID | head` ended with 'error: [Errno 32] Broken pipe'."""
    process = subprocess.Popen([TACTILE, "calibrations", "show", "builtin-table1"], stdout=subprocess.PIPE,
                               stderr=subprocess.PIPE)
    process.stdout.close()  # before it writes: its first write meets a pipe without a reader
    with process.stderr:
        err = process.stderr.read().decode()
    assert process.wait(timeout=30) == 0 and err == ""


def test_bench_refuses_seconds_that_hold_no_loaded_frame(capsys):
    """--seconds 1 printed nan in every 'RMS loaded' cell: each scene begins with 1 s unloaded."""
    with pytest.raises(SystemExit) as exit_:
        cli.main(["bench", "--seconds", "1"])
    assert exit_.value.code == 2 and "1 s holds no loaded frame" in capsys.readouterr().err


def test_a_registry_named_by_the_environment_for_reading_must_exist_too(tmp_path, monkeypatch, capsys):
    """A typo in $TACTILE_REGISTRY made an empty registry as silently as one in --registry did."""
    typo = tmp_path / "typo.sqlite3"
    monkeypatch.setenv("TACTILE_REGISTRY", str(typo))
    assert cli.main(["calibrations", "list"]) == 2
    assert f"no registry at $TACTILE_REGISTRY={typo}" in capsys.readouterr().err and not typo.exists()
