"""What ``tactile sim``, ``tables``, ``model`` and ``bench`` do (cli.py parses
the command line; cli_serve.py serves, cli_recordings.py records and
replays), and the progress bars all commands share.

Every command that can run for more than a couple of seconds shows a tqdm
bar on stderr (none when stderr is no terminal).
"""
from __future__ import annotations

import json
import sys
import threading
from pathlib import Path


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


def _sim_config(args):
    from firmware_sim.board import BoardConfig
    from firmware_sim.urlhandler.protocol_sim import parse_sensors

    return BoardConfig(
        sensors=parse_sensors(args.sensors), rate_hz=args.rate, scene=args.scene, noise_fF=args.noise, seed=args.seed
    )


def cmd_sim(args) -> int:
    from firmware_sim import frontends
    from firmware_sim.board import Board, capture

    config = _sim_config(args)
    if args.capture:
        seconds = args.seconds or 10.0
        data, board = capture(config, seconds)
        with open(args.capture, "wb") as out:
            out.write(data)
        print(f"wrote {len(data)} bytes ({seconds:g} s of scene {config.scene!r}) to {args.capture}")
        return 0
    stop = threading.Event()
    timer = threading.Timer(args.seconds, stop.set) if args.seconds else None
    if timer is not None:
        timer.daemon = True
        timer.start()
    try:  # Ctrl-C goes on to the CLI (exit 130, as every command), the board stopped first
        if args.pty:
            master, slave, path = frontends.open_pty()
            print(f"simulated board on {path} (scene {config.scene!r}); Ctrl-C to stop", flush=True)
            frontends.serve_pty(config, master, stop)
        else:
            server = frontends.tcp_server(args.host, args.tcp)
            host, port = server.getsockname()[:2]
            print(f"simulated board on socket://{host}:{port} (scene {config.scene!r}); Ctrl-C to stop", flush=True)
            frontends.serve_tcp(Board(config), server, stop)
    finally:
        stop.set()
        if timer is not None:
            timer.cancel()
    return 0


def cmd_bench(args) -> int:
    from .reports import plotting
    from .reports.bench import run, write_docs

    if args.out:
        plotting.require("bench.png")  # before minutes of measuring, not after
    with progress_bar(desc="bench", unit="step") as bar:
        report = run(seconds=args.seconds, progress=_stepper(bar), process_seconds=args.process_seconds)
    print(json.dumps(report, indent=1) if args.json else report["text"])
    if args.out:
        for path in write_docs(report, Path(args.out)):
            print(f"wrote {path}", file=sys.stderr)
    return 0


def cmd_tables_build(args) -> int:
    from .physics import table_files, tables

    directory = Path(args.out) if args.out else None
    for shape in args.shape:
        spec = table_files.TableSpec(shape, pdms_nu=args.nu, p=args.p, pz=args.pz)
        try:
            table_files.load(spec, directory)
            print(f"{spec.filename}: up to date")
            continue
        except FileNotFoundError:
            pass
        with progress_bar(desc=shape, total=100, unit="%", bar_format="{desc:8s} {percentage:3.0f}%|{bar}| {elapsed}") as bar:
            table = tables.build(spec, lambda fraction: bar.update(round(100 * fraction) - bar.n))
        print(f"{table_files.save(table, directory)}: {len(table.force_N)} points to {table.max_force_N:.2f} N")
    return 0


def cmd_tables_list(args) -> int:
    from .physics import table_files

    for path in sorted(table_files.shipped_dir().glob("*.json")):
        table = table_files.ForceTable.from_json(path.read_bytes())
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
