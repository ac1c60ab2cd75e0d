"""What each `tactile` command does (cli.py parses the command line).

Every command that can run for more than a couple of seconds shows a tqdm
bar on stderr (none when stderr is no terminal); what the link does while
``serve`` or ``record`` reads a source is said on stderr by a LinkWatcher.
"""
from __future__ import annotations

import contextlib
import errno
import json
import os
import secrets
import socket
import sys
import threading
import time
from pathlib import Path

from .sources import check_source


def scene_names() -> list[str]:
    """The simulator's scenes (imported on demand: the simulator pulls in scipy)."""
    from firmware_sim.scenes import SCENES

    return list(SCENES)


def progress_bar(**options):
    """A tqdm bar on stderr, off when stderr is no terminal, shown only after 0.5 s."""
    from tqdm import tqdm

    return tqdm(disable=None, delay=0.5, file=sys.stderr, dynamic_ncols=True, leave=False, **options)


def _stepper(bar):
    """A reports-style ``progress(done, total, what)`` callback driving ``bar``."""
    def progress(done: int, total: int, what: str) -> None:
        bar.total = total
        bar.set_postfix_str(what, refresh=False)
        bar.update(done - bar.n)
    return progress


class LinkWatcher:
    """Says on stderr what a readout's link does, once per change: waiting for
    a source that is not there (once per outage, with the error), connected,
    lost and back within one look, stale (connected, silent), finished (a
    replay's end). ``link`` returns the readout's LinkState (or None before
    there is one); ``poll`` looks once, ``start`` every ``period_s`` from a
    daemon thread."""

    def __init__(self, link, stale_after_s=lambda: 0.5, out=None, period_s: float = 0.5) -> None:
        self._link = link
        self._stale_after_s = stale_after_s
        self._out = out
        self._period_s = period_s
        self._shown: str | None = None
        self._connects = 0
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name="tactile-link-watcher", daemon=True)

    def say(self, text: str) -> None:
        print(f"tactile: {text}", file=self._out or sys.stderr, flush=True)

    def poll(self, now: float | None = None) -> None:
        link = self._link()
        if link is None:
            return
        now = time.time() if now is None else now
        state = link.state(now, self._stale_after_s())
        connects, url = link.connects, link.url
        if connects > self._connects:
            if self._connects and self._shown in ("up", "stale"):  # lost and back between two looks
                self.say(f"link to {url} lost ({link.last_error}); connected again")
            else:
                self.say(f"connected to {url}")
            self._connects = connects
            self._shown = "up"
        if state == "down" and self._shown != "down":
            if link.last_error is None:  # not tried yet
                return
            if self._connects:
                self.say(f"link to {url} lost: {link.last_error}; waiting for it")
            else:
                self.say(f"waiting for {url}: {link.last_error}")
            self._shown = "down"
        elif state == "stale" and self._shown == "up":
            silent = link.silent_s(now)
            self.say(f"no bytes from {url} for {silent:.1f} s (link stale)")
            self._shown = "stale"
        elif state == "up" and self._shown == "stale":
            self.say(f"bytes from {url} again")
            self._shown = "up"
        elif state == "finished" and self._shown != "finished":
            self.say(f"replay of {url} finished (the service keeps serving; Ctrl-C to stop)")
            self._shown = "finished"

    def start(self) -> "LinkWatcher":
        self._thread.start()
        return self

    def stop(self, final_look: bool = True) -> None:
        self._stop.set()
        if self._thread.is_alive():
            self._thread.join(2)
        if final_look:  # what happened since the last look
            self.poll()

    def _run(self) -> None:
        while not self._stop.wait(self._period_s):
            try:
                self.poll()
            except Exception as exc:  # a watcher must never take the command down
                self.say(f"link watcher failed: {exc!r}")
                return


def quiet_readout_transitions() -> None:
    """The LinkWatcher says when the link comes up or is lost; drop the readout's
    own log lines for those two events, keep its others (asking INFO?, …)."""
    import logging

    logger = logging.getLogger("service.readout")
    if _drop_transitions not in logger.filters:
        logger.addFilter(_drop_transitions)


def _drop_transitions(record) -> bool:
    return not str(record.msg).startswith(("connected to ", "link to "))


def check_port_free(host: str, port: int) -> None:
    """Bind ``host:port`` as uvicorn will (SO_REUSEADDR) and let go; OSError
    naming the port and what to do when another process holds it."""
    try:
        infos = socket.getaddrinfo(host, port, type=socket.SOCK_STREAM, flags=socket.AI_PASSIVE)
    except socket.gaierror as exc:
        raise OSError(f"cannot bind {host}: {exc.strerror}") from None
    for family, kind, proto, _, address in infos:
        with socket.socket(family, kind, proto) as sock:
            sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
            try:
                sock.bind(address)
            except OSError as exc:
                if exc.errno == errno.EADDRINUSE:
                    raise OSError(f"port {port} on {host} is in use (another tactile serve?); choose --port") from None
                if exc.errno == errno.EADDRNOTAVAIL and family == socket.AF_INET6 and len(infos) > 1:
                    continue  # 'localhost' without IPv6: uvicorn binds what it can
                raise OSError(f"cannot bind {host}:{port}: {exc.strerror}") from None


def _sim_config(args):
    from firmware_sim.board import BoardConfig
    from firmware_sim.urlhandler.protocol_sim import parse_sensors

    return BoardConfig(
        sensors=parse_sensors(args.sensors), rate_hz=args.rate, scene=args.scene, noise_fF=args.noise, seed=args.seed
    )


def cmd_serve(args) -> int:
    import uvicorn

    from .api.app import create_app
    from .health import stale_after_s
    from .live_service import TactileService

    check_source(args.source)
    check_port_free(args.host, args.port)  # before anything is printed: not a URL that points at another instance
    token = args.token or os.environ.get("TACTILE_TOKEN")
    if args.host not in ("127.0.0.1", "localhost", "::1") and not token:
        token = secrets.token_urlsafe(16)
    service = TactileService(args.source, level=args.level, mounting=args.mounting,
                             sched_slice_us=args.sched_slice_us or None, recordings_dir=args.recordings_dir,
                             silence_s=args.silence_s)
    app = create_app(service, token=token, bind_host=args.host, allow_hosts=tuple(args.allow_host),
                     allow_origins=tuple(args.allow_origin))
    url = f"http://{args.host}:{args.port}/" + (f"?token={token}" if token else "")
    listening = threading.Event()
    done = threading.Event()

    def announce() -> None:
        """Say where once uvicorn listens (the port was free: whoever answers on it now is us)."""
        if _wait_until_listening(args.host, args.port, done):
            listening.set()
            print(f"tactile: reading {args.source}; dashboard at {url}", flush=True)
            if token:
                print(f"tactile: mutating endpoints need 'Authorization: Bearer {token}'", flush=True)

    quiet_readout_transitions()
    watcher = LinkWatcher(lambda: service.readout.link if service.readout is not None else None,
                          lambda: stale_after_s(service.pipeline.interpreter.board)).start()
    threading.Thread(target=announce, name="tactile-announce", daemon=True).start()
    interrupted = []
    try:
        with _noting_sigint(interrupted):
            # No per-message deflate: compressing every 1 kHz message costs more CPU than loopback or a LAN saves.
            # Connections get 1 s to close after Ctrl-C, so that the command ends promptly.
            uvicorn.run(app, host=args.host, port=args.port, log_level=args.log_level, ws_per_message_deflate=False,
                        timeout_graceful_shutdown=1)
    finally:
        done.set()
        watcher.stop(final_look=False)
    if interrupted:
        raise KeyboardInterrupt  # uvicorn stopped on Ctrl-C and swallowed it: end as every command does (130)
    return 0


@contextlib.contextmanager
def _noting_sigint(noted: list):
    """uvicorn catches Ctrl-C, shuts down, re-raises it to the handler it found and
    then swallows the KeyboardInterrupt: a handler of ours notes that it came.
    (A SIGINT that is ignored, as in a background job, stays ignored.)"""
    import signal

    if threading.current_thread() is not threading.main_thread() or \
            signal.getsignal(signal.SIGINT) is not signal.default_int_handler:
        yield
        return

    def note(signum, frame):
        noted.append(signum)
        raise KeyboardInterrupt

    signal.signal(signal.SIGINT, note)
    try:
        yield
    finally:
        signal.signal(signal.SIGINT, signal.default_int_handler)


def _wait_until_listening(host: str, port: int, done: threading.Event, poll_s: float = 0.05) -> bool:
    """True once something accepts TCP connections on host:port, False if ``done`` is set first."""
    target = {"0.0.0.0": "127.0.0.1", "::": "::1", "": "127.0.0.1"}.get(host, host)
    while not done.is_set():
        try:
            with socket.create_connection((target, port), timeout=0.5):
                return True
        except OSError:
            done.wait(poll_s)
    return False


def cmd_sim(args) -> int:
    from firmware_sim import frontends
    from firmware_sim.board import Board, capture

    config = _sim_config(args)
    if args.capture:
        data, board = capture(config, args.seconds)
        with open(args.capture, "wb") as out:
            out.write(data)
        print(f"wrote {len(data)} bytes ({args.seconds} s of scene {config.scene!r}) to {args.capture}")
        return 0
    stop = threading.Event()
    try:
        if args.pty:
            master, slave, path = frontends.open_pty()
            print(f"simulated board on {path} (scene {config.scene!r}); Ctrl-C to stop", flush=True)
            frontends.serve_pty(config, master, stop)
        else:
            server = frontends.tcp_server(args.host, args.tcp)
            host, port = server.getsockname()[:2]
            print(f"simulated board on socket://{host}:{port} (scene {config.scene!r}); Ctrl-C to stop", flush=True)
            frontends.serve_tcp(Board(config), server, stop)
    except KeyboardInterrupt:
        stop.set()
    return 0


def cmd_record(args) -> int:
    from .handover import ThreadSink
    from .pipeline import Pipeline
    from .readout import Readout
    from .reconstruct import Reconstructor
    from .record.recorder import Recorder

    check_source(args.source)
    pipeline = Pipeline(Reconstructor(level=args.level, mounting=args.mounting))
    outputs = [Path(p) for p in (args.out, args.raw) if p]
    new = [p for p in outputs if not p.exists()]
    recorder = Recorder(args.out, args.raw)
    recorder.attach(pipeline)
    readout = Readout(args.source, ThreadSink(pipeline.feed, pipeline.link_lost))
    quiet_readout_transitions()
    watcher = LinkWatcher(lambda: readout.link)
    readout.start()
    watcher.start()
    until = f"for {args.seconds:g} s" if args.seconds else "Ctrl-C to stop"
    print(f"recording {args.source} to {args.out}" + (f" and {args.raw}" if args.raw else "") + f"; {until}",
          flush=True)
    started = time.monotonic()
    try:
        deadline = started + args.seconds if args.seconds else None
        while recorder.active and (deadline is None or time.monotonic() < deadline):
            time.sleep(0.05)
    except KeyboardInterrupt:
        pass
    finally:
        readout.stop()
        watcher.stop(final_look=False)
        status = recorder.stop()
    print(json.dumps(status, indent=1))
    if status["error"]:
        return 1
    if readout.link.last_data_time is None:  # not one byte came
        removed = [p for p in new if p.exists() and _unlink(p)]  # only files this command created
        kept = [p for p in outputs if p not in new]
        why = f" ({readout.link.last_error})" if readout.link.last_error else ""
        note = f"; removed the empty {' and '.join(map(str, removed))}" if removed else ""
        note += f"; {' and '.join(map(str, kept))} existed before and now hold an empty recording" if kept else ""
        print(f"tactile record: nothing recorded: no byte from {args.source} in {time.monotonic() - started:.1f} s"
              f"{why}{note}", file=sys.stderr)
        return 1
    return 0


def _unlink(path: Path) -> bool:
    try:
        path.unlink()
        return True
    except OSError:
        return False


class _ProgressPacer:
    """A Pacer that also moves a bar by bytes of the file: a raw capture is read
    in CHUNK_BYTES chunks, one wait each; an MCAP recording's progress is its
    recorded time against the span its summary gives, scaled to the file's size."""

    def __init__(self, pacer, bar, path: Path) -> None:
        from .record.readers import CHUNK_BYTES, is_timed_by_host

        self._pacer, self._bar = pacer, bar
        self._size = path.stat().st_size
        self._chunk = CHUNK_BYTES
        self._span = _mcap_span(path) if is_timed_by_host(path) else None
        self._timed = is_timed_by_host(path)

    def wait(self, t_recorded: float) -> None:
        self._pacer.wait(t_recorded)
        if not self._timed:
            done = self._bar.n + self._chunk
        elif self._span is not None:
            t0, t1 = self._span
            done = self._size * min(max((t_recorded - t0) / (t1 - t0), 0.0), 1.0) if t1 > t0 else self._bar.n
        else:
            return
        self._bar.update(min(done, self._size) - self._bar.n)


def _mcap_span(path: Path) -> tuple[float, float] | None:
    """(first, last) message time in s from an MCAP's summary; None without one (a file cut short)."""
    try:
        from mcap.reader import make_reader

        with open(path, "rb") as stream:
            summary = make_reader(stream).get_summary()
        if summary is None or summary.statistics is None:
            return None
        return summary.statistics.message_start_time * 1e-9, summary.statistics.message_end_time * 1e-9
    except Exception:  # no summary is no reason to refuse the replay
        return None


def cmd_replay(args) -> int:
    from .record.pacing import Pacer
    from .replay import replay

    path = args.file or args.raw
    if path is None:
        raise ValueError("name a recording: tactile replay FILE (or --raw FILE)")
    if args.serve:
        import math
        import urllib.parse

        speed = 1.0 if args.speed is None else args.speed
        args.source = f"replay://{urllib.parse.quote(str(path))}?speed={'max' if math.isinf(speed) else speed}"
        return cmd_serve(args)
    if not Path(path).is_file():
        raise FileNotFoundError(f"no such recording: {path}")
    speed = args.speed if args.speed is not None else float("inf")
    to_stdout = args.export == "-"
    export_is_new = bool(args.export) and not to_stdout and not Path(args.export).exists()
    out = sys.stdout.buffer if to_stdout else open(args.export, "wb") if args.export else None
    bar = progress_bar(total=Path(path).stat().st_size, unit="B", unit_scale=True, desc=Path(path).name)
    try:
        pipeline = replay(path, out, level=args.level, mounting=args.mounting,
                          pacer=_ProgressPacer(Pacer(speed), bar, Path(path)))
    except BrokenPipeError:
        if not to_stdout:
            raise
        # The reader stopped (`| head`): end quietly, as a pipeline's tools do.
        os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())
        return 0
    except (ValueError, OSError):  # not a recording after all: leave no empty export behind
        if export_is_new:
            out.close()
            _unlink(Path(args.export))
        raise
    finally:
        bar.close()
        if out is not None and not to_stdout:
            out.close()
    counters = pipeline.decoder.counters.as_dict()
    reconstructor = pipeline.reconstructor
    summary = {"stream": {k: v for k, v in counters.items() if k != "sensors"}, "sensors": counters["sensors"],
               "rejected": pipeline.interpreter.rejected,
               "level": reconstructor.level, "level_reason": reconstructor.level_reason}
    print(json.dumps(summary, indent=1), file=sys.stderr)
    if args.level == "auto":
        print(f"tactile replay: level auto chose {reconstructor.level}: {reconstructor.level_reason}", file=sys.stderr)
    if counters["frames"] == 0:
        removed = export_is_new and _unlink(Path(args.export))
        print(f"tactile replay: {path}: no valid frame in {counters['bytes_in']} bytes (is it a capture of the "
              f"board?)" + (f"; removed the empty {args.export}" if removed else ""), file=sys.stderr)
        return 1
    return 0


def cmd_bench(args) -> int:
    from .reports import plotting
    from .reports.bench import run, write_docs

    if args.out:
        plotting.require("bench.png")  # before minutes of measuring, not after
    with progress_bar(desc="bench", unit="step") as bar:
        report = run(seconds=args.seconds, progress=_stepper(bar))
    print(json.dumps(report, indent=1) if args.json else report["text"])
    if args.out:
        for path in write_docs(report, Path(args.out)):
            print(f"wrote {path}", file=sys.stderr)
    return 0


def cmd_tables_build(args) -> int:
    from .physics import tables

    directory = Path(args.out) if args.out else None
    for shape in args.shape:
        spec = tables.TableSpec(shape, pdms_nu=args.nu, p=args.p, pz=args.pz)
        try:
            tables.load(spec, directory)
            print(f"{spec.filename}: up to date")
            continue
        except FileNotFoundError:
            pass
        with progress_bar(desc=shape, total=100, unit="%", bar_format="{desc:8s} {percentage:3.0f}%|{bar}| {elapsed}") as bar:
            table = tables.build(spec, lambda fraction: bar.update(round(100 * fraction) - bar.n))
        print(f"{tables.save(table, directory)}: {len(table.force_N)} points to {table.max_force_N:.2f} N")
    return 0


def cmd_tables_list(args) -> int:
    from .physics import tables

    for path in sorted(tables.shipped_dir().glob("*.json")):
        table = tables.ForceTable.from_json(path.read_bytes())
        print(f"{path.name}: shape {table.spec.shape}, ν {table.spec.pdms_nu}, p {table.spec.p}/{table.spec.pz}, "
              f"0–{table.max_force_N:.2f} N")
    return 0


def cmd_model_check(args) -> int:
    from .reports import model_check as check

    with progress_bar(desc="model check", unit="model") as bar:
        step = _stepper(bar)
        checks = check.run(progress=lambda done, total, what: step(done, total + 3, what))
        poisson = check.poisson_study(progress=lambda done, total, what: step(check.RUN_STEPS + done,
                                                                               check.RUN_STEPS + total, what))
    if args.json:
        print(json.dumps({"passed": all(c.passed for c in checks), "checks": [c.as_dict() for c in checks],
                          "poisson": poisson}, indent=1))
    else:
        print(check.report_text(checks))
        for row in poisson:
            print(f"info  ν = {row['nu']}: sensitivity {100 * row['sensitivity_per_N']:.4f} %/N, "
                  f"ΔC/C0 at 100 kPa {100 * row['dC_C0_100kPa']:.4f} %, max deflection {row['max_deflection_um']:.4f} µm")
    return 0 if all(c.passed for c in checks) else 1


def cmd_model_convergence(args) -> int:
    from .reports import convergence as study
    from .reports import plotting

    plotting.require("convergence.png")  # before minutes of solving, not after
    with progress_bar(desc="convergence", unit="model") as bar:
        result = study.run(progress=_stepper(bar))
    for path in study.write_docs(result, Path(args.out)):
        print(f"wrote {path}")
    return 0
