"""The Zenoh options of ``serve --zenoh`` and ``gateway`` as a session
configuration (docs/scale.md): loopback only and multicast scouting off
unless asked.
"""
from __future__ import annotations

import sys


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
