"""Zenoh sessions for the service and its clients: the command line's options
mapped onto Zenoh's own configuration keys, and the key expressions used.

Keys (docs/scale.md):

    tactile/<board>/<sensor>/frame    every frame (binary encoding, u16 count + records)
    tactile/<board>/<sensor>/latest   queryable: the latest frame, same encoding
    tactile/<board>/sensors           queryable: the board's INFO and sensor shapes (JSON)
    tactile/<board>/health            the /health document (JSON), once per second
    tactile/<board>/alive/<instance>  liveliness token: present while the board's service runs

Every service process is an ``instance`` (``host:pid:random``): its frame and
health samples carry it as their attachment, its sensors document and its
liveliness token name it, so that a gateway tells apart two services that
publish one board name (service/net/board_claims.py).
"""
from __future__ import annotations

import json
import os
import re
import secrets
import socket
from collections.abc import Iterable
from pathlib import Path

import zenoh

PREFIX = "tactile"
MODES = ("peer", "client", "router")
DEFAULT_PORT = 7447


def frame_key(board: str, sensor: int | str) -> str:
    return f"{PREFIX}/{board}/{sensor}/frame"


def latest_key(board: str, sensor: int | str) -> str:
    return f"{PREFIX}/{board}/{sensor}/latest"


def sensors_key(board: str) -> str:
    return f"{PREFIX}/{board}/sensors"


def health_key(board: str) -> str:
    return f"{PREFIX}/{board}/health"


def alive_key(board: str, instance: str = "*") -> str:
    return f"{PREFIX}/{board}/alive/{instance}"


def instance_id() -> str:
    """This process as a publisher: host, pid and a random part (two
    containers may share a host name and a pid), safe as a key chunk."""
    host = re.sub(r"[^A-Za-z0-9._-]", "_", socket.gethostname()) or "host"
    return f"{host}:{os.getpid()}:{secrets.token_hex(3)}"


def instance_of_alive(key) -> str:
    """The instance an alive token's key names ("" for a service from before
    instances, whose token is ``tactile/<board>/alive``)."""
    chunks = str(key).split("/")
    return chunks[3] if len(chunks) > 3 else ""


def instance_of_sample(sample: zenoh.Sample) -> str:
    """The instance a frame or health sample's attachment names ("" without one)."""
    attachment = sample.attachment
    return "" if attachment is None else attachment.to_bytes()[:128].decode("utf-8", "replace")


def session_config(file: str | Path | None = None, connect: Iterable[str] = (), listen: Iterable[str] = (),
                   mode: str | None = None, multicast: bool | None = None) -> zenoh.Config:
    """A zenoh.Config: ``file`` (a Zenoh JSON5 configuration) or Zenoh's
    defaults, then the options over it on Zenoh's keys — connect/endpoints,
    listen/endpoints, mode, scouting/multicast/enabled. ValueError naming
    what Zenoh refused (a bad file, endpoint or mode)."""
    if mode is not None and mode not in MODES:
        raise ValueError(f"zenoh mode {mode!r} is none of {', '.join(MODES)}")
    try:
        config = zenoh.Config.from_file(str(file)) if file is not None else zenoh.Config()
        connect, listen = list(connect), list(listen)
        if connect:
            config.insert_json5("connect/endpoints", json.dumps(connect))
        if listen:
            config.insert_json5("listen/endpoints", json.dumps(listen))
        if mode is not None:
            config.insert_json5("mode", json.dumps(mode))
        if multicast is not None:
            config.insert_json5("scouting/multicast/enabled", json.dumps(multicast))
    except zenoh.ZError as exc:
        raise ValueError(f"zenoh configuration{f' {file}' if file else ''}: {exc}") from None
    return config


def open_session(config: zenoh.Config) -> zenoh.Session:
    """Open a session; OSError saying why not (e.g. a listen port in use).
    Zenoh's own log goes to stdout only when RUST_LOG asks for it."""
    zenoh.try_init_log_from_env()
    try:
        return zenoh.open(config)
    except zenoh.ZError as exc:
        text = str(exc)
        if "in use" in text:  # Zenoh's message names its Rust sources; what a user needs is the way out
            listening = config.get_json("listen/endpoints")
            raise OSError(f"zenoh session: cannot listen on {listening}: address already in use (another tactile "
                          "service with --zenoh on this host?); give this one its own, e.g. --zenoh-listen "
                          "tcp/127.0.0.1:7448, and a gateway or client both endpoints") from None
        raise OSError(f"zenoh session: {text}") from None
