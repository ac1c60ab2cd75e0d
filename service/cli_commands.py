"""What each `tactile` command does (cli.py parses the command line)."""
from __future__ import annotations

import json
import os
import secrets
import sys
import threading

from .sources import check_source


def _sim_config(args):
    from firmware_sim.board import BoardConfig
    from firmware_sim.urlhandler.protocol_sim import parse_sensors

    return BoardConfig(
        sensors=parse_sensors(args.sensors), rate_hz=args.rate, scene=args.scene, noise_fF=args.noise, seed=args.seed
    )


def cmd_serve(args) -> int:
    import uvicorn

    from .api.app import create_app
    from .live_service import TactileService

    check_source(args.source)
    token = args.token or os.environ.get("TACTILE_TOKEN")
    if args.host not in ("127.0.0.1", "localhost", "::1") and not token:
        token = secrets.token_urlsafe(16)
    service = TactileService(args.source, level=args.level, mounting=args.mounting,
                             sched_slice_us=args.sched_slice_us or None, recordings_dir=args.recordings_dir,
                             silence_s=args.silence_s)
    app = create_app(service, token=token, bind_host=args.host, allow_hosts=tuple(args.allow_host),
                     allow_origins=tuple(args.allow_origin))
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


def cmd_record(args) -> int:
    import time

    from .handover import ThreadSink
    from .pipeline import Pipeline
    from .readout import Readout
    from .reconstruct import Reconstructor
    from .record.recorder import Recorder

    check_source(args.source)
    pipeline = Pipeline(Reconstructor(level=args.level, mounting=args.mounting))
    recorder = Recorder(args.out, args.raw)
    recorder.attach(pipeline)
    readout = Readout(args.source, ThreadSink(pipeline.feed, pipeline.link_lost))
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

    from .reports import plotting
    from .reports.bench import run, write_docs

    if args.out:
        plotting.require("bench.png")  # before minutes of measuring, not after
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
