"""What several ``tactile`` commands share on their command line: the
checked value types (ports, positive numbers, speeds, scenes, the scheduler
slice) and the option groups (reconstruction, HTTP, serving, Zenoh).
cli.py builds each command's parser from them.
"""
from __future__ import annotations

import argparse
import os
import urllib.parse

from . import cli_commands as commands
from .calibration.cli import existing_registry, new_or_existing_registry
from .physics.mountings import MOUNTINGS
from .reconstruct.levels import DEFAULT_LEVEL, LEVELS
from .record.pacing import parse_speed


def _slice_us(text: str) -> int:
    from .sched import MAX_SLICE_US, MIN_SLICE_US

    try:
        value = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"slice {text!r} must be a whole number of microseconds") from None
    if value and not MIN_SLICE_US <= value <= MAX_SLICE_US:
        raise argparse.ArgumentTypeError(f"slice {value} us is outside {MIN_SLICE_US}..{MAX_SLICE_US} (or 0 for the default)")
    return value


def port(text: str, free_ok: bool = False) -> int:
    try:
        value = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"port {text!r} is not a whole number") from None
    low = 0 if free_ok else 1
    if not low <= value <= 65535:
        raise argparse.ArgumentTypeError(f"port {value} is outside {low}..65535")
    return value


def port_or_free(text: str) -> int:
    """A port, or 0 for any free one."""
    return port(text, free_ok=True)


def web_origin(text: str) -> str:
    """An --allow-origin value: what a browser sends as Origin, scheme://host[:port]
    (one without its scheme could never match, silently)."""
    parts = urllib.parse.urlsplit(text.strip())
    try:
        parts.port  # noqa: B018 — urlsplit checks the port only when asked
    except ValueError:
        raise argparse.ArgumentTypeError(f"origin {text!r}: its port is not 0-65535") from None
    if parts.scheme not in ("http", "https") or not parts.hostname or parts.path.strip("/") or parts.query:
        raise argparse.ArgumentTypeError(f"origin {text!r}: expected http(s)://HOST[:PORT] as a browser sends it, "
                                         "e.g. http://lab-pc:3000")
    return text.strip()


def bare_host(text: str) -> str:
    """An --allow-host value: a host name or address as a Host header names it, without scheme or path."""
    if not text.strip() or any(c in text for c in "/@?# ") or "://" in text:
        raise argparse.ArgumentTypeError(f"host {text!r}: expected a bare name or address, e.g. lab-pc or "
                                         "lab-pc.local (no scheme, no path)")
    return text.strip()


def directory_or_new(text: str) -> str:
    """A directory, existing or to be made (a file there made every recording a 409 'File exists')."""
    if os.path.exists(text) and not os.path.isdir(text):
        raise argparse.ArgumentTypeError(f"{text!r} is a file, not a directory")
    return text


def positive(text: str) -> float:
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r} is not a number") from None
    if not value > 0:
        raise argparse.ArgumentTypeError(f"{text!r} must be > 0")
    return value


def bench_seconds(text: str) -> float:
    """The scenes begin with 1 s unloaded (the tare's): the loaded errors need frames after it."""
    value = positive(text)
    if value < 2:
        raise argparse.ArgumentTypeError(f"{text} s holds no loaded frame (each scene begins with 1 s unloaded, "
                                         "for the tare): give at least 2")
    return value


def speed(text: str) -> float:
    try:
        return parse_speed(text)
    except ValueError as exc:
        raise argparse.ArgumentTypeError(str(exc)) from None


class SceneHelp(str):
    """The --scene help, naming the simulator's scenes only when help is shown
    (importing the simulator takes a second)."""

    def __mod__(self, params):
        return f"one of {' | '.join(commands.scene_names())} (default: {params['default']})"


def scene(text: str) -> str:
    names = commands.scene_names()
    if text not in names:
        raise argparse.ArgumentTypeError(f"unknown scene {text!r}; known scenes: {', '.join(names)}")
    return text


def add_reconstruction_options(parser: argparse.ArgumentParser, stores: bool = False) -> None:
    """``stores``: the command stores into the registry (serve: uploads, load cycles), so it may make one."""
    parser.set_defaults(registry_reads=not stores)
    default = "%(default)s" if parser.prog.split()[-1] != "replay" else "the recording's own, else %(default)s"
    parser.add_argument("--level", default=DEFAULT_LEVEL, choices=LEVELS,
                        help="fidelity level; auto takes the cheapest meeting the scene's error budget and says which "
                             f"(default: {default})")
    parser.add_argument("--mounting", default="flat", choices=list(MOUNTINGS),
                        help=f"grid mounting: picks the load-shape table (default: {default})")
    parser.add_argument("--registry", metavar="PATH", type=new_or_existing_registry if stores else existing_registry,
                        help="calibration registry: each sensor's active calibration is used (default: "
                             "$TACTILE_REGISTRY, else $XDG_DATA_HOME/tactile/registry.sqlite3)" + (
                                 "; made, saying so, if missing" if stores else "; it must exist"))
    parser.add_argument("--calibration", action="append", metavar="ID|FILE",
                        help="use this calibration (a registry id or an exported JSON file) for the sensor it was "
                             "made for, over the registry's active one (repeatable; a recording's own come first)")


def add_http_options(parser: argparse.ArgumentParser) -> None:
    """Where and to whom the API is served (serve, replay --serve, gateway)."""
    parser.add_argument("--host", default="127.0.0.1", help="address to bind (default: %(default)s; beyond localhost "
                                                                "a token is required, see --token)")
    parser.add_argument("--port", type=port, default=8000, help="HTTP port (default: %(default)s)")
    parser.add_argument("--log-level", default="warning", choices=["critical", "error", "warning", "info", "debug"],
                        help="server log level (default: %(default)s)")
    parser.add_argument("--token", help="require this bearer token on mutating endpoints (default: none on localhost, "
                                        "a random one printed at start when binding beyond it; env TACTILE_TOKEN)")
    parser.add_argument("--allow-host", action="append", default=[], metavar="NAME", type=bare_host,
                        help="a host name clients may use for this service besides localhost and IP addresses "
                             "(repeatable; DNS names are refused otherwise, against DNS rebinding)")
    parser.add_argument("--allow-origin", action="append", default=[], metavar="ORIGIN", type=web_origin,
                        help="a web origin (e.g. http://lab-pc:3000) whose pages may change state or stream "
                             "(repeatable; default: only the service's own dashboard)")


def add_serving_options(parser: argparse.ArgumentParser, stores: bool = False) -> None:
    """What ``serve`` and ``replay --serve`` share: both end in cmd_serve."""
    add_http_options(parser)
    parser.add_argument("--recordings-dir", default="recordings", metavar="DIR", type=directory_or_new,
                        help="where POST /record/start and the dashboard's Record write (default: %(default)s, "
                             "created on demand)")
    parser.add_argument("--silence-s", type=positive, default=2.0, metavar="S",
                        help="after this long without a byte, ask the board INFO? and then reopen the link "
                             "(default: %(default)s)")
    add_reconstruction_options(parser, stores)
    parser.add_argument("--grid-batch-ms", type=float, default=0.0, metavar="MS",
                        help="let grids wait up to MS to be reconstructed together with the reads that come "
                             "meanwhile: less CPU for up to MS more grid latency; quads never wait (default: "
                             "%(default)s; docs/performance.md)")
    parser.add_argument("--sched-slice-us", type=_slice_us, default=0, metavar="US",
                        help="ask Linux >= 6.12 for this scheduler time slice (100-100000 us) so the service is "
                             "woken promptly on a busy host; 0 keeps the kernel's default (default: %(default)s)")

def add_zenoh_options(parser: argparse.ArgumentParser) -> None:
    """``serve --zenoh``: frames, health and latest frames on Zenoh (docs/scale.md)."""
    zenoh = parser.add_argument_group("zenoh", "publish on Zenoh under tactile/<board>/ (docs/scale.md)")
    zenoh.add_argument("--zenoh", nargs="?", const="", metavar="CONFIG",
                       help="publish on Zenoh; CONFIG: a Zenoh JSON5 configuration file (default: listen on "
                            "tcp/127.0.0.1:7447 only unless --zenoh-listen is given; multicast scouting off unless --multicast)")
    zenoh.add_argument("--zenoh-endpoint", action="append", default=[], metavar="ENDPOINT",
                       help="connect to this Zenoh endpoint, e.g. tcp/192.168.1.10:7447 (repeatable)")
    zenoh.add_argument("--zenoh-listen", action="append", default=[], metavar="ENDPOINT",
                       help="listen on this Zenoh endpoint, e.g. tcp/0.0.0.0:7447 (repeatable)")
    zenoh.add_argument("--zenoh-mode", choices=["peer", "client", "router"], help="Zenoh mode (default: peer)")
    add_multicast_options(zenoh)


def add_multicast_options(group) -> None:
    """Scouting finds and joins every Zenoh peer on the LAN (another lab's
    boards of the same name among them): off unless asked, or a CONFIG says."""
    choice = group.add_mutually_exclusive_group()
    choice.add_argument("--multicast", action="store_true",
                        help="turn Zenoh's multicast scouting on: find and join the Zenoh peers of the LAN "
                             "(default: off, unless a CONFIG turns it on)")
    choice.add_argument("--no-multicast", action="store_true",
                        help="turn Zenoh's multicast scouting off, even if a CONFIG turns it on")
