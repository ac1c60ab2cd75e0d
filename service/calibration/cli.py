"""``tactile calibrate`` and ``tactile calibrations list|show|activate|export|import``.

``add_parsers(subparsers)`` registers both on the ``tactile`` command's
subparsers; each sets ``func`` to a function of the parsed arguments that
returns the exit code and raises ValueError/OSError for the CLI to print.
"""
from __future__ import annotations

import argparse
import json
import os
import sys
import time
from pathlib import Path

import numpy as np

from ..physics.mountings import MOUNTINGS
from .registry import Registry


def existing_registry(text: str) -> str:
    """A ``--registry`` a command reads: a path that does not exist is a
    mistake to name, not an empty registry to make (a typo there silently
    left every sensor on its built-in calibration)."""
    if not Path(text).is_file():
        raise argparse.ArgumentTypeError(f"no registry at {text} (one is made by `tactile calibrate` or "
                                         "`tactile calibrations import` naming it; without --registry the default one is used)")
    return text


def check_registry_env(args) -> None:
    """A command that only reads the registry, given none, with
    $TACTILE_REGISTRY naming a file that does not exist: ValueError (a
    typo there made an empty registry as silently as one in --registry)."""
    named = os.environ.get("TACTILE_REGISTRY")
    if getattr(args, "registry_reads", False) and args.registry is None and named and not Path(named).is_file():
        raise ValueError(f"no registry at $TACTILE_REGISTRY={named} (one is made by `tactile calibrate` or "
                         "`tactile calibrations import`; unset it for the default one)")


def new_or_existing_registry(text: str) -> str:
    """A ``--registry`` a command stores into: made if missing, in a directory that exists."""
    if not Path(text).is_file() and not Path(text).parent.is_dir():
        raise argparse.ArgumentTypeError(f"no directory {Path(text).parent} for the registry {text}")
    return text


def _registry_option(parser: argparse.ArgumentParser, stores: bool = False) -> None:
    parser.set_defaults(registry_reads=not stores)  # cli.main checks $TACTILE_REGISTRY alike (check_registry_env)
    parser.add_argument("--registry", metavar="PATH", type=new_or_existing_registry if stores else existing_registry,
                        help="calibration registry (default: $TACTILE_REGISTRY, else "
                             "$XDG_DATA_HOME/tactile/registry.sqlite3)" + (
                                 "; made if missing" if stores else "; it must exist"))


def add_parsers(subparsers) -> None:
    """Register ``calibrate`` and ``calibrations`` on ``subparsers``."""
    cal = subparsers.add_parser("calibrate", help="calibrate a grid or a quad from a reference-load session")
    cal.add_argument("session", metavar="SESSION", help="the board's bytes: raw capture (.bin) or recording (.mcap)")
    cal.add_argument("--reference", required=True, metavar="REF.csv",
                     help="the reference instrument's log: t_s,force_N (a grid) or t_s,fx_N,fy_N,fz_N (a quad)")
    cal.add_argument("--sensor", type=int, metavar="ID", help="sensor id on the board (default: the only grid, "
                                                              "or the only quad for a 3-axis reference)")
    _registry_option(cal, stores=True)
    cal.add_argument("--board", metavar="NAME",
                     help="the board's name in the service (--source NAME=URL): a board without a serial keys its "
                          "sensors' calibrations by it; also picks that board's bytes from a recording of several")
    cal.add_argument("--report", metavar="DIR", help="write calibration.md, response.png, residuals.png here")
    cal.add_argument("--full-scale", type=float, default=10.0, metavar="N", help="full scale in N (default: %(default)s)")
    cal.add_argument("--mounting", default="flat", choices=list(MOUNTINGS),
                     help="model table's mounting (default: %(default)s)")
    cal.add_argument("--zero-reference", action="store_true",
                     help="subtract the level the reference rests at between loads (an instrument not zeroed "
                          "before the session); without it, a reference resting off 0 is used as logged, with a warning")
    cal.add_argument("--partial", action="store_true",
                     help="store the taxels that fit even if others fail (those keep their previous calibration)")
    cal.add_argument("--no-activate", action="store_true", help="store without making it the sensor's active one")
    cal.add_argument("--fatigue", choices=["paper", "none"],
                     help="a quad's sensitivity loss with load cycles from this calibration on: paper (001 §5.2: "
                          "−22 %% over the first thousands of cycles; the default, for a new sensor) or none (a sensor "
                          "cycled long before, whose loss has settled); grids: none (paper 000 reports none)")
    cal.set_defaults(func=cmd_calibrate)

    cals = subparsers.add_parser("calibrations", help="the calibration registry").add_subparsers(dest="action",
                                                                                                required=True)
    listing = cals.add_parser("list", help="every stored calibration, the active ones marked")
    listing.add_argument("--sensor-key", help="only this sensor's (e.g. sensor:A8-2291)")
    for name, helptext in (("show", "one calibration as JSON"), ("activate", "make it its sensor's active one")):
        sub = cals.add_parser(name, help=helptext)
        sub.add_argument("id", help="a calibration id (a unique prefix will do)")
        _registry_option(sub)
    _registry_option(listing)
    export = cals.add_parser("export", help="write one calibration as JSON")
    export.add_argument("id", help="a calibration id (a unique prefix will do)")
    export.add_argument("out", metavar="OUT.json", help="the JSON file to write")
    _registry_option(export)
    imp = cals.add_parser("import", help="store a calibration exported elsewhere (same id), or a table-1-style CSV")
    imp.add_argument("file", metavar="IN.json|TABLE.csv",
                     help="a calibration exported by `tactile calibrations export`, or a CSV with columns "
                          "row,col,c0_pF,sensitivity_pct_per_N (needs --sensitivity-fit and --sensor-key)")
    imp.add_argument("--activate", action="store_true", help="also make it its sensor's active one")
    imp.add_argument("--sensitivity-fit", choices=["intercept", "origin"],
                     help="a CSV's sensitivity is the 0-10 N least-squares slope with an intercept (table 1's) "
                          "or through the origin (they differ by ~2.5 %%): required for a CSV")
    imp.add_argument("--sensor-key", help="a CSV's sensor, as the registry names it (e.g. sensor:A8-2291 or "
                                          "board:TMX-000123/sensor:0)")
    _registry_option(imp, stores=True)
    listing.set_defaults(func=cmd_list)
    for name, func in (("show", cmd_show), ("activate", cmd_activate), ("export", cmd_export), ("import", cmd_import)):
        cals.choices[name].set_defaults(func=func)


def cmd_calibrate(args) -> int:
    from .calibrate import calibrate, document, summary_lines

    if args.report:
        from ..reports.plotting import require

        require("the calibration report's PNGs")
    started = time.perf_counter()
    Registry(args.registry).close()  # an unusable registry is said before a fit of seconds, not after it
    if _three_axis(args.reference):
        return _calibrate_quad(args, started)
    if args.fatigue == "paper":
        raise ValueError("--fatigue paper: paper 001's fatigue is the quad's; paper 000 reports none for the grid")
    result = calibrate(args.session, args.reference, args.sensor, args.full_scale, args.mounting, args.partial,
                       board=args.board, zero_reference=args.zero_reference)
    with Registry(args.registry) as registry:
        key = registry_key(result)
        previous = registry.active(key, result.session.info.rows, result.session.info.cols)
        doc = document(result, previous)
        check_usable(doc, result.session.info, args.mounting, "sensitivity_pct_per_N", 1.24, "%/N")
        cid = registry.add(doc, activate=not args.no_activate)
    elapsed = time.perf_counter() - started
    print("\n".join(summary_lines(result)))
    print(f"stored {cid} for {key} in {registry.path}{'' if args.no_activate else ' (active)'}; "
          f"{len(result.fits)} taxels calibrated in {elapsed:.2f} s")
    if args.report:
        from .report import write_report

        print(f"report: {write_report(result, doc, cid, args.report)}")
    return 0


def _three_axis(path: str) -> bool:
    """Whether the reference is a force/torque log (a quad's session)."""
    from .reference import HEADER_3D

    try:
        with open(path, encoding="utf-8-sig", errors="replace") as stream:
            return tuple(c.strip() for c in stream.readline().split(",")) == HEADER_3D
    except FileNotFoundError:
        return False  # the grid path says which file is missing


def _calibrate_quad(args, started: float) -> int:
    from .calibrate_quad import calibrate_quad, quad_document, quad_summary

    result = calibrate_quad(args.session, args.reference, args.sensor, board=args.board,
                            zero_reference=args.zero_reference)
    doc = quad_document(result, fatigue=args.fatigue or "paper")
    check_usable(doc, result.session.info, "flat", "normal_fit", 0.0343, "/N")
    with Registry(args.registry) as registry:
        cid = registry.add(doc, activate=not args.no_activate)
    print("\n".join(quad_summary(result)))
    print("fatigue: none (--fatigue none)" if args.fatigue == "none" else
          "fatigue: paper 001's loss from this calibration's count 0 (a new sensor; one cycled long before reads "
          "high as it goes: --fatigue none)")
    print(f"stored {cid} for {registry_key(result)} in {registry.path}{'' if args.no_activate else ' (active)'}; "
          f"calibrated in {time.perf_counter() - started:.2f} s")
    return 0


UNIT_WARN_RATIO = 3.0  # fitted slopes this far off the paper's are said (a sensor's spread is tens of per cent)


def check_usable(doc: dict, info, mounting: str, slope_field: str, paper_slope: float, unit: str) -> None:
    """ValueError, nothing stored, when the service would refuse to load the
    calibration (the same checks: ``serve`` fell back to the built-in one
    with a log line); a slope orders of magnitude off the paper's names the
    likely cause, a reference in other units than N, and a usable one
    UNIT_WARN_RATIO off is warned of on stderr."""
    from ..reconstruct.sensor_calibration import calibration_id, from_document

    if slope_field == "normal_fit":
        slopes = [doc["normal_fit"][1]]  # [c2, c1(, c0)]: the small-force slope
    else:
        taxels = doc["taxels"]
        slopes = [v for v, source in zip(taxels[slope_field], taxels["source"]) if source == "this session" and v]
    if not slopes:  # nothing of this session's to judge
        slopes = [paper_slope]
    ratio = float(np.median(slopes)) / paper_slope
    hint = (f"the fitted slopes ({min(slopes):.3g}–{max(slopes):.3g} {unit}) are {1 / ratio if ratio < 1 else ratio:.1f}× "
            f"{'below' if ratio < 1 else 'above'} the paper's {paper_slope:g} {unit}: is the reference's force in "
            f"{'grams or mN' if ratio < 1 else 'lbf, kgf or kN'} rather than N?")
    try:
        from_document({**doc, "id": calibration_id(doc)}, info, mounting)
    except ValueError as exc:
        far = ratio < 0.05 or ratio > 20
        raise ValueError(f"calibration not stored: the service could not use it ({exc}){'; ' + hint if far else ''}") from None
    if ratio < 1 / UNIT_WARN_RATIO or ratio > UNIT_WARN_RATIO:  # usable, yet more unlike any sensor of the papers' than a unit
        print(f"WARNING: {hint}", file=sys.stderr)


def registry_key(result) -> str:
    from .registry import sensor_identity

    return sensor_identity(result.session.board, result.session.info)["key"]


def cmd_list(args) -> int:
    with Registry(args.registry) as registry:
        for row in registry.list(args.sensor_key):
            mark = "*" if row["active"] else " "
            print(f"{mark} {row['id']:<16}  {row['created']:<25}  {row['sensor_key']}  {row.get('note', '')}".rstrip())
    return 0


def cmd_show(args) -> int:
    with Registry(args.registry) as registry:
        print(json.dumps(registry.get(args.id), indent=1, sort_keys=True))
    return 0


def cmd_activate(args) -> int:
    with Registry(args.registry) as registry:
        doc = registry.activate(args.id)
    print(f"{doc['id']} is now active for {doc['sensor']['key']}")
    return 0


def cmd_export(args) -> int:
    with Registry(args.registry) as registry:
        cid = registry.export(args.id, args.out)
    print(f"{cid} → {args.out}")
    return 0


def cmd_import(args) -> int:
    document = None
    if Path(args.file).suffix.lower() == ".csv":
        from .table_import import table_document

        if not args.sensitivity_fit or not args.sensor_key:
            raise ValueError(f"{args.file}: a table's sensitivity is ambiguous: name its reading with "
                             "--sensitivity-fit intercept|origin, and its sensor with --sensor-key")
        document = table_document(args.file, args.sensitivity_fit, args.sensor_key)
    with Registry(args.registry) as registry:
        cid = registry.import_(args.file) if document is None else registry.add(document)
        if args.activate:
            registry.activate(cid)
    print(f"imported {cid}{' (active)' if args.activate else ''}")
    return 0


def main(argv: list[str] | None = None) -> int:
    """``python -m service.calibration.cli calibrate|calibrations ...``, the same commands on their own
    (until service/cli.py registers them)."""
    import sys

    parser = argparse.ArgumentParser(prog="tactile")
    add_parsers(parser.add_subparsers(dest="command", required=True))
    args = parser.parse_args(argv)
    try:
        return args.func(args)
    except (ValueError, OSError) as exc:
        print(f"tactile {args.command}: error: {exc}", file=sys.stderr)
        return 2


if __name__ == "__main__":
    raise SystemExit(main())
