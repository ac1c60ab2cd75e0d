"""`tactile` command line: serve | sim | replay | bench."""
from __future__ import annotations

import argparse
import json
import logging
import os
import secrets
import sys
import threading

from .sources import DEFAULT_SOURCE, check_source


def _sim_config(args):
    from firmware_sim.board import BoardConfig
    from firmware_sim.urlhandler.protocol_sim import parse_sensors

    return BoardConfig(
        sensors=parse_sensors(args.sensors), rate_hz=args.rate, scene=args.scene, noise_fF=args.noise, seed=args.seed
    )


def cmd_serve(args) -> int:
    import uvicorn

    from .api.app import create_app
    from .runtime import TactileService

    check_source(args.source)
    token = args.token or os.environ.get("TACTILE_TOKEN")
    if args.host not in ("127.0.0.1", "localhost", "::1") and not token:
        token = secrets.token_urlsafe(16)
    app = create_app(TactileService(args.source, level=args.level, mounting=args.mounting,
                                    sched_slice_us=args.sched_slice_us or None), token=token)
    url = f"http://{args.host}:{args.port}/" + (f"?token={token}" if token else "")
    print(f"tactile: reading {args.source}; dashboard at {url}", flush=True)
    if token:
        print(f"tactile: mutating endpoints need 'Authorization: Bearer {token}'", flush=True)
    # No per-message deflate: compressing every 1 kHz message costs more CPU than loopback or a LAN saves.
    uvicorn.run(app, host=args.host, port=args.port, log_level=args.log_level, ws_per_message_deflate=False)
    return 0


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


def _speed(text: str) -> float:
    import math

    if text == "max":
        return math.inf
    try:
        speed = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"speed {text!r} must be a number or 'max'") from None
    if not speed > 0:
        raise argparse.ArgumentTypeError(f"speed {text!r} must be > 0")
    return speed


def cmd_record(args) -> int:
    import time

    from .pipeline import Pipeline
    from .readout import Readout
    from .reconstruct import Reconstructor
    from .record.recorder import Recorder

    check_source(args.source)
    pipeline = Pipeline(Reconstructor(level=args.level, mounting=args.mounting))
    recorder = Recorder(args.out, args.raw, diagnostics=pipeline.decoder.counters.as_dict)
    pipeline.byte_listeners.append(recorder.on_bytes)
    pipeline.listeners.append(recorder.on_frames)
    readout = Readout(args.source, pipeline.feed, pipeline.link_lost)
    readout.start()
    print(f"recording {args.source} to {args.out}" + (f" and {args.raw}" if args.raw else "") + "; Ctrl-C to stop", flush=True)
    try:
        deadline = time.monotonic() + args.seconds if args.seconds else None
        while recorder.active and (deadline is None or time.monotonic() < deadline):
            time.sleep(0.05)
    except KeyboardInterrupt:
        pass
    finally:
        readout.stop()
        status = recorder.stop()
    print(json.dumps(status, indent=1))
    return 1 if status["error"] else 0


def cmd_replay(args) -> int:
    from .replay import Pacer, replay

    path = args.file or args.raw
    if path is None:
        raise ValueError("name a recording: tactile replay FILE (or --raw FILE)")
    if args.serve:
        import urllib.parse

        speed = 1.0 if args.speed is None else args.speed
        args.source = f"replay://{urllib.parse.quote(str(path))}?speed={'max' if speed == float('inf') else speed}"
        return cmd_serve(args)
    speed = args.speed if args.speed is not None else float("inf")
    to_stdout = args.export == "-"
    out = sys.stdout.buffer if to_stdout else open(args.export, "wb") if args.export else None
    try:
        pipeline = replay(path, out, level=args.level, mounting=args.mounting, pacer=Pacer(speed))
    except BrokenPipeError:
        if not to_stdout:
            raise
        # The reader stopped (`| head`): end quietly, as a pipeline's tools do.
        os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())
        return 0
    finally:
        if out is not None and not to_stdout:
            out.close()
    counters = pipeline.decoder.counters.as_dict()
    summary = {"stream": {k: v for k, v in counters.items() if k != "sensors"}, "sensors": counters["sensors"],
               "rejected": pipeline.interpreter.rejected}
    print(json.dumps(summary, indent=1), file=sys.stderr)
    return 0


def cmd_bench(args) -> int:
    from pathlib import Path

    from .reports.bench import run, write_docs

    report = run(seconds=args.seconds)
    print(json.dumps(report, indent=1) if args.json else report["text"])
    if args.out:
        for path in write_docs(report, Path(args.out)):
            print(f"wrote {path}", file=sys.stderr)
    return 0


def cmd_tables_build(args) -> int:
    from pathlib import Path

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

        last = [-1]

        def bar(fraction, label=shape):
            done = int(30 * fraction)
            if done == last[0]:
                return
            last[0] = done
            print(f"\r{label:8s} [{'#' * done}{'.' * (30 - done)}] {100 * fraction:3.0f}%", end="", file=sys.stderr, flush=True)

        table = tables.build(spec, bar)
        print(file=sys.stderr)
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

    checks = check.run()
    if args.json:
        print(json.dumps({"passed": all(c.passed for c in checks), "checks": [c.as_dict() for c in checks],
                          "poisson": check.poisson_study()}, indent=1))
    else:
        print(check.report_text(checks))
        for row in check.poisson_study():
            print(f"info  ν = {row['nu']}: sensitivity {100 * row['sensitivity_per_N']:.4f} %/N, "
                  f"ΔC/C0 at 100 kPa {100 * row['dC_C0_100kPa']:.4f} %, max deflection {row['max_deflection_um']:.4f} µm")
    return 0 if all(c.passed for c in checks) else 1


def cmd_model_convergence(args) -> int:
    from pathlib import Path

    from .reports import convergence as study

    for path in study.write_docs(study.run(), Path(args.out)):
        print(f"wrote {path}")
    return 0


def _slice_us(text: str) -> int:
    from .sched import MAX_SLICE_US, MIN_SLICE_US

    try:
        value = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"slice {text!r} must be a whole number of microseconds") from None
    if value and not MIN_SLICE_US <= value <= MAX_SLICE_US:
        raise argparse.ArgumentTypeError(f"slice {value} us is outside {MIN_SLICE_US}..{MAX_SLICE_US} (or 0 for the default)")
    return value


def _add_reconstruction_options(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--level", default="full", choices=["level0", "table", "full", "auto"], help="fidelity level (default: %(default)s)")
    parser.add_argument("--mounting", default="flat", choices=["flat", "curved"], help="grid mounting: picks the load-shape table")


def _add_serving_options(parser: argparse.ArgumentParser) -> None:
    """What ``serve`` and ``replay --serve`` share: both end in cmd_serve."""
    parser.add_argument("--host", default="127.0.0.1")
    parser.add_argument("--port", type=int, default=8000)
    parser.add_argument("--log-level", default="warning")
    parser.add_argument("--token", help="require this bearer token on mutating endpoints (default: none on localhost, "
                                        "a random one printed at start when binding beyond it; env TACTILE_TOKEN)")
    _add_reconstruction_options(parser)
    parser.add_argument("--sched-slice-us", type=_slice_us, default=0, metavar="US",
                        help="ask Linux >= 6.12 for this scheduler time slice (100-100000 us) so the service is "
                             "woken promptly on a busy host; 0 keeps the kernel's default (default: %(default)s)")


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="tactile", description="Capacitive tactile sensor service")
    sub = parser.add_subparsers(dest="command", required=True)

    serve = sub.add_parser("serve", help="read a board and serve the API and dashboard")
    serve.add_argument("--source", default=DEFAULT_SOURCE,
                       help="pyserial URL or device path (default: %(default)s, the built-in simulator)")
    _add_serving_options(serve)
    serve.set_defaults(func=cmd_serve)

    sim = sub.add_parser("sim", help="run the board simulator on a pty, TCP, or into a capture file")
    where = sim.add_mutually_exclusive_group(required=True)
    where.add_argument("--pty", action="store_true", help="serve on a new pseudo-terminal and print its path")
    where.add_argument("--tcp", type=int, metavar="PORT", help="serve on TCP (0 picks a free port)")
    where.add_argument("--capture", metavar="FILE", help="write the simulator's exact bytes to FILE")
    sim.add_argument("--host", default="127.0.0.1", help="TCP bind address")
    sim.add_argument("--seconds", type=float, default=10.0, help="capture length")
    sim.add_argument("--scene", default="demo", help="idle | press | slide | shear | demo")
    sim.add_argument("--rate", type=float, default=1000.0, help="scans per second per sensor")
    sim.add_argument("--noise", type=float, default=1.0, help="white capacitance noise, fF rms")
    sim.add_argument("--seed", type=int, default=0)
    sim.add_argument("--sensors", default="grid,quad", help="e.g. grid,quad or grid8x8,grid4x4,quad")
    sim.set_defaults(func=cmd_sim)

    record = sub.add_parser("record", help="record a source to MCAP (raw bytes, frames, forces, diagnostics)")
    record.add_argument("--source", default=DEFAULT_SOURCE, help="pyserial URL or device path (default: %(default)s)")
    record.add_argument("--out", required=True, metavar="RUN.mcap")
    record.add_argument("--raw", metavar="RUN.bin", help="also write the raw bytes, exactly as received")
    record.add_argument("--seconds", type=float, help="stop after this long (default: until Ctrl-C)")
    _add_reconstruction_options(record)
    record.set_defaults(func=cmd_record)

    replay = sub.add_parser("replay", help="replay a recording (.mcap) or raw capture through the pipeline")
    replay.add_argument("file", nargs="?", help="recording (.mcap) or raw capture (any other suffix)")
    replay.add_argument("--raw", metavar="FILE", help="a raw capture (same as giving FILE)")
    replay.add_argument("--speed", type=_speed, default=None,
                        help="1 (real time), 2, … or max (default: max for --export, 1 for --serve)")
    replay.add_argument("--serve", action="store_true", help="publish through the live API and dashboard")
    replay.add_argument("--export", metavar="OUT.jsonl", help="write one JSON line per data frame ('-': to stdout)")
    _add_serving_options(replay)
    replay.set_defaults(func=cmd_replay)

    tables_cmd = sub.add_parser("tables", help="force tables of the taxel model").add_subparsers(dest="action", required=True)
    build = tables_cmd.add_parser("build", help="build the tables a configuration needs (skips up-to-date ones)")
    build.add_argument("--shape", nargs="+", default=["uniform", "uneven", "shear"], choices=["uniform", "uneven", "shear"])
    build.add_argument("--nu", type=float, default=0.49, help="PDMS Poisson ratio")
    build.add_argument("--p", type=int, default=4, help="in-plane polynomial degree")
    build.add_argument("--pz", type=int, default=3, help="polynomial degree across each layer")
    build.add_argument("--out", help="directory (default: the service's shipped tables)")
    build.set_defaults(func=cmd_tables_build)
    tables_cmd.add_parser("list", help="list the shipped tables").set_defaults(func=cmd_tables_list)

    model = sub.add_parser("model", help="validate the forward models").add_subparsers(dest="action", required=True)
    check_cmd = model.add_parser("check", help="validation figures; exit 1 if any is out of tolerance")
    check_cmd.add_argument("--json", action="store_true")
    check_cmd.set_defaults(func=cmd_model_check)
    conv = model.add_parser("convergence", help="error against order study (minutes); writes docs")
    conv.add_argument("--out", default="docs")
    conv.set_defaults(func=cmd_model_convergence)

    bench = sub.add_parser("bench", help="speed against error of every fidelity level on the simulator's scenes")
    bench.add_argument("--seconds", type=float, default=10.0, help="simulated seconds per scenario")
    bench.add_argument("--json", action="store_true")
    bench.add_argument("--out", help="also write bench.md and bench.png to this directory")
    bench.set_defaults(func=cmd_bench)
    return parser


def main(argv: list[str] | None = None) -> int:
    logging.basicConfig(level=logging.INFO, format="%(levelname)s %(name)s: %(message)s")
    args = build_parser().parse_args(argv)
    try:
        return args.func(args)
    except (ValueError, OSError) as exc:
        print(f"tactile {args.command}: error: {exc}", file=sys.stderr)
        return 2


if __name__ == "__main__":
    sys.exit(main())
