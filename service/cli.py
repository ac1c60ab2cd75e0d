"""`tactile` command line: serve | sim | record | replay | tables | model | bench.

This module only parses (cli_options.py: the value types and option groups
several commands share); cli_serve.py (serve), cli_recordings.py (record,
replay) and cli_commands.py (the others) do the work, cli_signals.py
handles Ctrl-C.
"""
from __future__ import annotations

import argparse
import logging
import os
import sys

from . import cli_commands as commands
from .calibration.cli import add_parsers as add_calibration_parsers
from .calibration.cli import check_registry_env
from .cli_options import (SceneHelp, add_http_options, add_multicast_options, add_reconstruction_options,
                          add_serving_options, add_zenoh_options, bench_seconds, port_or_free, positive, scene, speed)
from .cli_recordings import cmd_record, cmd_replay
from .cli_serve import cmd_gateway, cmd_serve
from .cli_signals import interrupted, watchdog_for
from .sources import DEFAULT_SOURCE


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="tactile", description="Capacitive tactile sensor service")
    sub = parser.add_subparsers(dest="command", required=True)
    for add in (_add_serve, _add_gateway, _add_sim, _add_record, _add_replay, _add_tables, _add_model, _add_bench,
                add_calibration_parsers):
        add(sub)
    return parser


def _add_serve(sub) -> None:
    serve = sub.add_parser("serve", help="read one or several boards and serve the API and dashboard")
    boards = serve.add_mutually_exclusive_group()
    boards.add_argument("--source", action="append", metavar="[NAME=]URL",
                        help=f"pyserial URL or device path, optionally named (left=/dev/ttyACM0); repeat for several "
                             f"boards; a bare URL is named from its INFO (default: {DEFAULT_SOURCE}, the built-in "
                             f"simulator)")
    boards.add_argument("--config", metavar="ROBOT.toml",
                        help="the boards from a robot description file: name, source, level, mounting, calibration "
                             "per board (docs/scale.md)")
    serve.add_argument("--board-name", metavar="NAME",
                       help="name a single bare --source (as NAME=URL does): its address in the API and its key in "
                            "tactile/<board>/… (default: the serial, else the board name, from INFO)")
    add_serving_options(serve, stores=True)
    add_zenoh_options(serve)
    serve.set_defaults(func=cmd_serve)


def _add_gateway(sub) -> None:
    gateway = sub.add_parser("gateway", help="serve the API and dashboard for every board that services publish on "
                                             "Zenoh (tactile serve --zenoh on this or other hosts)")
    add_http_options(gateway)
    zenoh = gateway.add_argument_group("zenoh", "where the services are (docs/scale.md)")
    zenoh.add_argument("--zenoh", metavar="CONFIG", help="a Zenoh JSON5 configuration file")
    zenoh.add_argument("--zenoh-endpoint", action="append", default=[], metavar="ENDPOINT",
                       help="connect to this Zenoh endpoint (repeatable; default without CONFIG: tcp/127.0.0.1:7447, "
                            "a service's default)")
    zenoh.add_argument("--zenoh-listen", action="append", default=[], metavar="ENDPOINT",
                       help="listen on this Zenoh endpoint for services that connect to the gateway (repeatable)")
    zenoh.add_argument("--zenoh-mode", choices=["peer", "client", "router"], help="Zenoh mode (default: peer)")
    add_multicast_options(zenoh)
    gateway.set_defaults(func=cmd_gateway)


def _add_sim(sub) -> None:
    sim = sub.add_parser("sim", help="run the board simulator on a pty, TCP, or into a capture file")
    where = sim.add_mutually_exclusive_group(required=True)
    where.add_argument("--pty", action="store_true", help="serve on a new pseudo-terminal and print its path")
    where.add_argument("--tcp", type=port_or_free, metavar="PORT", help="serve on TCP (0 picks a free port)")
    where.add_argument("--capture", metavar="FILE", help="write the simulator's exact bytes to FILE")
    sim.add_argument("--host", default="127.0.0.1", help="TCP bind address (default: %(default)s)")
    sim.add_argument("--seconds", type=positive,
                     help="a capture's length, s (default: 10); on a pty or TCP, stop after this long (default: "
                          "at Ctrl-C)")
    sim.add_argument("--scene", type=scene, default="demo", help=SceneHelp("scene"))
    sim.add_argument("--rate", type=positive, default=1000.0, help="scans per second per sensor (default: %(default)s)")
    sim.add_argument("--noise", type=float, default=1.0, help="white capacitance noise, fF rms (default: %(default)s)")
    sim.add_argument("--seed", type=int, default=0,
                     help="seed of the simulator's noise: the same seed gives the same bytes (default: %(default)s)")
    sim.add_argument("--sensors", default="grid,quad",
                     help="sensors in id order, e.g. grid,quad or grid8x8,grid4x4,quad (default: %(default)s)")
    sim.set_defaults(func=commands.cmd_sim)


def _add_record(sub) -> None:
    record = sub.add_parser("record", help="record a source to MCAP (raw bytes, frames, forces, diagnostics)")
    record.add_argument("--source", default=DEFAULT_SOURCE, help="pyserial URL or device path (default: %(default)s)")
    record.add_argument("--out", required=True, metavar="RUN.mcap", help="the MCAP file to write")
    record.add_argument("--raw", metavar="RUN.bin", help="also write the raw bytes, exactly as received")
    record.add_argument("--overwrite", action="store_true", help="replace files that exist (default: refuse them)")
    record.add_argument("--seconds", type=positive, help="stop after this long (default: until Ctrl-C); "
                                                           "exit 1 if not one byte came")
    add_reconstruction_options(record)
    record.set_defaults(func=cmd_record)


def _add_replay(sub) -> None:
    replay = sub.add_parser("replay", help="replay a recording (.mcap) or raw capture through the pipeline")
    replay.add_argument("file", nargs="?", help="recording (.mcap) or raw capture (any other suffix)")
    replay.add_argument("--raw", metavar="FILE", help="a raw capture (same as giving FILE)")
    replay.add_argument("--speed", type=speed, default=None,
                        help="1 (real time), 2, … (at least 0.0001) or max (default: max for --export, 1 for --serve)")
    replay.add_argument("--serve", action="store_true", help="publish through the live API and dashboard")
    replay.add_argument("--export", metavar="OUT.jsonl", help="write one JSON line per data frame ('-': to stdout); "
                                                              "OUT.parquet: one row per data frame, a Parquet table")
    add_serving_options(replay)
    # None: as the recording was made (its /settings), else the defaults (cli_recordings.replay_settings)
    replay.set_defaults(func=cmd_replay, level=None, mounting=None)


def _add_tables(sub) -> None:
    tables_cmd = sub.add_parser("tables", help="force tables of the taxel model").add_subparsers(dest="action", required=True)
    build = tables_cmd.add_parser("build", help="build the tables a configuration needs (skips up-to-date ones)")
    build.add_argument("--shape", nargs="+", default=["uniform", "uneven", "shear"], choices=["uniform", "uneven", "shear"],
                       help="load shapes to build (default: all)")
    build.add_argument("--nu", type=float, default=0.49, help="PDMS Poisson ratio (default: %(default)s)")
    build.add_argument("--p", type=int, default=4, help="in-plane polynomial degree (default: %(default)s)")
    build.add_argument("--pz", type=int, default=3, help="polynomial degree across each layer (default: %(default)s)")
    build.add_argument("--out", help="directory (default: the service's shipped tables)")
    build.set_defaults(func=commands.cmd_tables_build)
    tables_cmd.add_parser("list", help="list the shipped tables").set_defaults(func=commands.cmd_tables_list)


def _add_model(sub) -> None:
    model = sub.add_parser("model", help="validate the forward models").add_subparsers(dest="action", required=True)
    check_cmd = model.add_parser("check", help="validation figures; exit 1 if any is out of tolerance")
    check_cmd.add_argument("--json", action="store_true", help="print the checks and the Poisson study as JSON")
    check_cmd.set_defaults(func=commands.cmd_model_check)
    conv = model.add_parser("convergence", help="error against order study (minutes); writes docs")
    conv.add_argument("--out", default="docs", metavar="DIR",
                      help="directory for convergence.md and convergence.png (default: %(default)s; "
                           "needs matplotlib: pip install -e \".[docs]\")")
    conv.set_defaults(func=commands.cmd_model_convergence)


def _add_bench(sub) -> None:
    bench = sub.add_parser("bench", help="speed against error of every fidelity level on the simulator's scenes")
    bench.add_argument("--seconds", type=bench_seconds, default=10.0,
                       help="simulated seconds per scenario, at least 2 (default: %(default)s)")
    bench.add_argument("--process-seconds", type=float, default=60.0,
                       help="simulated seconds of the capture the whole-process figures replay "
                            "(default: %(default)s; 0 skips them)")
    bench.add_argument("--json", action="store_true", help="print the whole report as JSON")
    bench.add_argument("--out", metavar="DIR", help="also write bench.md and bench.png to this directory "
                                                    "(needs matplotlib: pip install -e \".[docs]\")")
    bench.set_defaults(func=commands.cmd_bench)


def main(argv: list[str] | None = None) -> int:
    logging.basicConfig(level=logging.INFO, format="%(levelname)s %(name)s: %(message)s")
    args = build_parser().parse_args(argv)
    name = " ".join(filter(None, (args.command, getattr(args, "action", None))))  # e.g. "model check"
    watchdog = watchdog_for(args, name)
    try:
        check_registry_env(args)
        return args.func(args)
    except KeyboardInterrupt:
        print(interrupted(name), file=sys.stderr, flush=True)
        return 130
    except BrokenPipeError:  # the reader of the output stopped (`| head`): end quietly, as a pipeline's tools do
        os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())
        return 0
    except (ValueError, OSError) as exc:
        print(f"tactile {args.command}: error: {exc}", file=sys.stderr)
        return 2
    finally:
        if watchdog is not None:
            watchdog.close()


if __name__ == "__main__":
    sys.exit(main())
