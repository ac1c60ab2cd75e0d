"""``tactile serve`` (and ``replay --serve``): the port checked before anything
is said, the dashboard's URL announced once uvicorn listens, the link's
changes said on stderr by a LinkWatcher (``record`` uses one too), and
Ctrl-C, which uvicorn handles itself, ending the command as any other.
"""
from __future__ import annotations

import errno
import os
import secrets
import socket
import sys
import threading
import time
from pathlib import Path

from .cli_signals import noting_sigint
from .sources import check_source


_SAYING = threading.Lock()


class LinkWatcher:
    """Says on stderr what a readout's link does, once per change: waiting for
    a source that is not there (once per outage, with the error), connected,
    lost and back within one look, stale (connected, silent), finished (a
    replay's end). ``link`` returns the readout's LinkState (or None before
    there is one); ``poll`` looks once, ``start`` every ``period_s`` from a
    daemon thread. ``board`` returns the board's name, said on each line
    when a service reads several (two `connected to sim://` say nothing)."""

    def __init__(self, link, stale_after_s=lambda: 0.5, out=None, period_s: float = 0.5, board=None) -> None:
        self._link = link
        self._board = board
        self._stale_after_s = stale_after_s
        self._out = out
        self._period_s = period_s
        self._shown: str | None = None
        self._connects = 0
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name="tactile-link-watcher", daemon=True)

    def say(self, text: str) -> None:
        out = self._out or sys.stderr
        board = f"board {self._board()}: " if self._board is not None else ""
        with _SAYING:  # one line at a time: two boards' watchers ran their lines together
            out.write(f"tactile: {board}{text}\n")
            out.flush()

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


def cmd_serve(args) -> int:
    from .api.app import create_app
    from .calibration.book import book_from_options
    from .health import stale_after_s
    from .live_service import TactileService

    specs = board_specs(args)
    for spec in specs:
        check_source(spec.source)
    check_port_free(args.host, args.port)  # before anything is printed: not a URL that points at another instance
    token = _token(args)
    publisher = zenoh_publisher(args)
    if args.registry is not None and not Path(args.registry).exists():
        print(f"tactile: registry {args.registry} did not exist: made empty (every sensor on its built-in "
              "calibration until one is uploaded)", file=sys.stderr, flush=True)
    book = book_from_options(args.registry, args.calibration, args.mounting, getattr(args, "recording", None))
    service = TactileService(sched_slice_us=args.sched_slice_us or None, recordings_dir=args.recordings_dir,
                             silence_s=args.silence_s, calibrations=book, boards=specs, mounting=args.mounting,
                             grid_batch_s=_grid_batch_s(args.grid_batch_ms))
    service.zenoh = publisher
    app = create_app(service, token=token, bind_host=args.host, allow_hosts=tuple(args.allow_host),
                     allow_origins=tuple(args.allow_origin))
    reading = ", ".join(spec.source if spec.name is None else f"{spec.name}={spec.source}" for spec in specs)
    quiet_readout_transitions()
    several = len(service.all_boards) > 1
    watchers = [LinkWatcher(lambda b=board: b.readout.link if b.readout is not None else None,
                            lambda b=board: stale_after_s(b.pipeline.interpreter.board),
                            board=(lambda b=board: b.name) if several else None).start()
                for board in service.all_boards]
    try:
        return _run_http(app, args, token, f"reading {reading}")
    finally:
        for watcher in watchers:
            watcher.stop(final_look=False)


def _grid_batch_s(ms: float) -> float:
    if not 0 <= ms <= 100:
        raise ValueError(f"--grid-batch-ms {ms:g} must be in [0, 100]")
    return ms / 1000.0


def cmd_gateway(args) -> int:
    from .api.app import create_app
    from .gateway import GatewayService
    from .net.zenoh_config import open_session

    check_port_free(args.host, args.port)
    token = _token(args)
    config, note = gateway_zenoh_config(args)
    open_session(config).close()  # a listen port in use or a bad endpoint fails here, before anything is printed
    if note:
        print(f"tactile: {note}", file=sys.stderr)
    app = create_app(GatewayService(config), token=token, bind_host=args.host, allow_hosts=tuple(args.allow_host),
                     allow_origins=tuple(args.allow_origin))
    return _run_http(app, args, token, "gateway for every board on Zenoh")


def gateway_zenoh_config(args):
    """(zenoh.Config, what to tell the user) of the gateway's options: by
    default it connects to a service's default endpoint on this host."""
    from .net.zenoh_config import DEFAULT_PORT, session_config

    connect, note = args.zenoh_endpoint, None
    if not args.zenoh and not connect and not args.zenoh_listen:
        connect = [f"tcp/127.0.0.1:{DEFAULT_PORT}"]
        note = (f"gateway connects to tcp/127.0.0.1:{DEFAULT_PORT} only; "
                "--zenoh-endpoint (repeatable) or a CONFIG for services on other hosts")
    return session_config(args.zenoh or None, connect, args.zenoh_listen, args.zenoh_mode, multicast(args)), note


def multicast(args) -> bool | None:
    """Multicast scouting: as --multicast / --no-multicast say, else off
    without a CONFIG (explicit endpoints must not also join whatever Zenoh
    network shares the LAN), else the CONFIG's."""
    if args.multicast or args.no_multicast:
        return bool(args.multicast)
    return False if not args.zenoh else None


def _token(args) -> str | None:
    """--token, else $TACTILE_TOKEN, else a random one when bound beyond localhost."""
    token = args.token or os.environ.get("TACTILE_TOKEN")
    if args.host not in ("127.0.0.1", "localhost", "::1") and not token:
        token = secrets.token_urlsafe(16)
    return token


def _run_http(app, args, token: str | None, what: str) -> int:
    """Serve ``app`` with uvicorn until Ctrl-C; say where once it listens."""
    import uvicorn

    from .api.server_options import SERVER_OPTIONS

    url = f"http://{args.host}:{args.port}/" + (f"?token={token}" if token else "")
    done = threading.Event()

    def announce() -> None:
        """Say where once uvicorn listens (the port was free: whoever answers on it now is us)."""
        if _wait_until_listening(args.host, args.port, done):
            print(f"tactile: {what}; dashboard at {url}", flush=True)
            if token:
                print(f"tactile: mutating endpoints need 'Authorization: Bearer {token}'", flush=True)

    threading.Thread(target=announce, name="tactile-announce", daemon=True).start()
    interrupted = []
    try:
        with noting_sigint(interrupted):
            # Connections get 1 s to close after Ctrl-C, so that the command ends promptly.
            uvicorn.run(app, host=args.host, port=args.port, log_level=args.log_level, timeout_graceful_shutdown=1,
                        **SERVER_OPTIONS)
    finally:
        done.set()
    if interrupted:
        raise KeyboardInterrupt  # uvicorn stopped on Ctrl-C and swallowed it: end as every command does (130)
    return 0


def board_specs(args) -> list:
    """The boards to read: --config's, else each --source (default: the
    built-in simulator); --board-name names a single bare source."""
    from .board import BoardSpec
    from .robot_config import load_robot, specs_from_sources
    from .sources import DEFAULT_SOURCE

    if getattr(args, "board_specs", None):  # made by the command itself (replay --serve: one per recorded board)
        return args.board_specs
    if getattr(args, "config", None):
        specs = load_robot(args.config, args.level, args.mounting)
    else:
        sources = args.source if isinstance(args.source, list) else [args.source or DEFAULT_SOURCE]
        specs = specs_from_sources(sources, args.level, args.mounting)
    name = getattr(args, "board_name", None)
    if name:
        if len(specs) != 1 or specs[0].name is not None:
            raise ValueError("--board-name names a single bare --source; name several as --source NAME=URL")
        specs = [BoardSpec(specs[0].source, name, specs[0].level, specs[0].mounting)]
    return specs


def zenoh_publisher(args):
    """The ``--zenoh`` options as a ZenohPublisher, its session open (a listen
    port in use fails here, before anything is printed); None without --zenoh."""
    if getattr(args, "zenoh", None) is None:
        given = [name for name in ("zenoh_endpoint", "zenoh_listen", "zenoh_mode", "multicast", "no_multicast")
                 if getattr(args, name, None)]
        if given:
            raise ValueError(f"--{given[0].replace('_', '-')} needs --zenoh")
        return None
    from .net.zenoh_publisher import ZenohPublisher

    config, note = zenoh_config(args)
    if note:
        print(f"tactile: {note}", file=sys.stderr)
    return ZenohPublisher(config)


def zenoh_config(args):
    """(zenoh.Config, what to tell the user) of the ``--zenoh`` options.
    Without a CONFIG file and without --zenoh-listen the service listens on
    loopback only: like the HTTP side's 127.0.0.1, nothing reachable from
    the LAN unless asked; and without a CONFIG, multicast scouting is off
    (``multicast``): nothing connecting out to the peers scouting finds."""
    from .net.zenoh_config import DEFAULT_PORT, session_config

    listen, note = args.zenoh_listen, None
    if not args.zenoh and not listen:
        listen = [f"tcp/127.0.0.1:{DEFAULT_PORT}"]
        note = (f"zenoh listens on tcp/127.0.0.1:{DEFAULT_PORT} only, multicast scouting off; "
                "--zenoh-listen tcp/0.0.0.0:7447 (or a CONFIG) to be reachable from other hosts")
    return (session_config(args.zenoh or None, args.zenoh_endpoint, listen, args.zenoh_mode, multicast(args)),
            note)


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
