"""``tactile serve`` (and ``replay --serve``): the port checked before anything
is said, the dashboard's URL announced once uvicorn listens, the link's
changes said on stderr by a LinkWatcher (cli_link.py), the Zenoh options
read by cli_zenoh.py, and Ctrl-C, which uvicorn handles itself, ending the
command as any other.
"""
from __future__ import annotations

import errno
import os
import secrets
import socket
import sys
import threading
from pathlib import Path

from .cli_link import LinkWatcher, quiet_readout_transitions
from .cli_signals import noting_sigint
from .cli_zenoh import gateway_zenoh_config, zenoh_publisher
from .sources import check_source


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
