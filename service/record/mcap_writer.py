"""MCAP recordings, written: the log the recorder's thread writes.

Channels (a recording of several boards has each board's under ``/{board}``,
``/{board}/raw``, ``/{board}/sensor/{id}/forces``, …; one board's are as
below and name the board in their messages): ``/raw`` (tactile.RawBytes,
every read of the port; the first one begins with the part of a frame the
decoder held when the recording began), per sensor
``/sensor/{id}/raw`` (tactile.RawFrame), ``/sensor/{id}/forces``
(tactile.Forces), ``/sensor/{id}/grid`` (foxglove.Grid, grids only), and
``/diagnostics``, ``/calibrations`` (tactile.Calibration: each sensor's
calibration document, written before the first frame that uses it, so a
replay reconstructs with it whatever the registry holds then), ``/tare``
(tactile.Tare: a tare made while recording, with the read before which it
took effect, so a replay makes it there), ``/calibration_set`` (tactile.CalibrationSet: a calibration
set while recording, an upload, likewise placed), ``/link`` (tactile.Link: where the link dropped, and where
frames held for the board's INFO went on without it, so a replay holds the same frames), ``/resume`` (tactile.Resume: once a second of reads, the
zeros, INFO and calibrations in force before a read, where a replay whose start was lost to a damaged chunk begins), ``/settings`` (tactile.Settings: the level and mounting the
board's forces were reconstructed with, which its replay takes). log_time is the host receive time (ns); publish_time the
board time of the frame where there is one.

Chunks are small (64 KiB, ~0.2 s at 1 kHz) and the file is flushed after
each, so a crash loses at most the open chunk (mcap_reader.py reads such a
file up to its last complete record).
"""
from __future__ import annotations

import base64
from typing import BinaryIO

import numpy as np
import orjson
from mcap.writer import CompressionType, Writer

from ..calibration.registry import sensor_identity
from ..fanout.encoding import to_export_dict
from ..reconstruct import ForceFrame
from . import schemas

CHUNK_BYTES = 1 << 16
_JSON = orjson.OPT_SERIALIZE_NUMPY
PROFILE = ""
GRID_CELL_M = 0.004


def _ns(t_s: float) -> int:
    return int(round(t_s * 1e9))


class McapLog:
    """Writes a recording; not thread-safe (the recorder's thread owns it)."""

    def __init__(self, stream: BinaryIO) -> None:
        self._stream = stream
        self._writer = Writer(stream, chunk_size=CHUNK_BYTES, compression=CompressionType.ZSTD)
        self._writer.start(profile=PROFILE, library="tactile")
        self._schemas = {
            name: self._writer.register_schema(schema["title"], "jsonschema", schemas.encoded(schema))
            for name, schema in (("raw", schemas.RAW_BYTES), ("frame", schemas.RAW_FRAME), ("forces", schemas.FORCES),
                                 ("diag", schemas.DIAGNOSTICS), ("grid", schemas.FOXGLOVE_GRID),
                                 ("calibration", schemas.CALIBRATION), ("tare", schemas.TARE),
                                 ("calibration_set", schemas.CALIBRATION_SET), ("link", schemas.LINK),
                                 ("baselines", schemas.BASELINES), ("resume", schemas.RESUME),
                                 ("settings", schemas.SETTINGS))
        }
        self._channels: dict[str, int] = {}
        self._sequence: dict[int, int] = {}

    def _channel(self, topic: str, schema: str) -> int:
        channel = self._channels.get(topic)
        if channel is None:
            channel = self._channels[topic] = self._writer.register_channel(topic, "json", self._schemas[schema])
        return channel

    def _add(self, topic: str, schema: str, t_host: float, payload: dict, publish_ns: int | None = None) -> None:
        channel = self._channel(topic, schema)
        sequence = self._sequence.get(channel, 0)
        self._sequence[channel] = sequence + 1
        log_ns = _ns(t_host)
        self._writer.add_message(channel, log_ns, orjson.dumps(payload, option=_JSON), publish_ns or log_ns, sequence)

    def raw(self, data: bytes, t_host: float, prefix: str = "") -> None:
        self._add(f"{prefix}/raw", "raw", t_host, {"t_host": t_host, "data": base64.b64encode(data).decode()})

    def frame(self, frame: ForceFrame, prefix: str = "") -> int:
        """Write one frame's messages; returns how many (a grid has a foxglove.Grid too)."""
        sid = frame.sensor.id
        publish = frame.t_us * 1000
        self._add(f"{prefix}/sensor/{sid}/raw", "frame", frame.t_host,
                  {"sensor": sid, "seq": frame.seq, "t_us": frame.t_us, "capacitance_pF": frame.capacitance_pF}, publish)
        self._add(f"{prefix}/sensor/{sid}/forces", "forces", frame.t_host, to_export_dict(frame), publish)
        if frame.sensor.kind == "grid":
            self._add(f"{prefix}/sensor/{sid}/grid", "grid", frame.t_host, foxglove_grid(frame), publish)
            return 3
        return 2

    def calibration(self, sensor, calibration_id: str, document: dict | None, cycles: list | None,
                    t_host: float) -> None:
        """``sensor``: the SensorInfo (its board and id name it; the INFO it was described under, its identity)."""
        key = sensor_identity(sensor.board_info or {}, sensor)["key"]
        self._add("/calibrations", "calibration", t_host, {"board": sensor.board, "sensor": sensor.id,
                                                           "id": calibration_id, "key": key, "document": document,
                                                           "cycles_at_start": cycles})

    def tare(self, board: str, after_reads: dict[int, int], judge: bool, t_host: float, prefix: str = "") -> None:
        """``after_reads``: {sensor id: the board's reads recorded before the tare took effect for it}."""
        self._add(f"{prefix}/tare", "tare", t_host, {
            "board": board, "judge": judge,
            "sensors": [{"sensor": sid, "after_reads": n} for sid, n in sorted(after_reads.items())]})

    def calibration_set(self, board: str, sensor: int, after_reads: int, document: dict, t_host: float,
                        prefix: str = "") -> None:
        """A calibration set (an upload) for ``sensor`` before the board's read ``after_reads`` of the recording."""
        self._add(f"{prefix}/calibration_set", "calibration_set", t_host,
                  {"board": board, "sensor": sensor, "after_reads": after_reads, "document": document})

    def link(self, board: str, event: str, after_reads: int, t_host: float, prefix: str = "") -> None:
        """The link's ``event`` (pipeline.LINK_EVENTS) before the board's read ``after_reads`` of the recording."""
        self._add(f"{prefix}/link", "link", t_host, {"board": board, "event": event, "after_reads": after_reads})

    def baselines(self, board: str, sensors: list[dict], info: dict | None, t_host: float, prefix: str = "",
                  left: list[dict] = ()) -> None:
        """``sensors``: each tared sensor's {sensor, baseline_pF, std_pF, loaded, …} when the recording
        began (one taring: its window so far, ``taring``); ``info``: the board's INFO then in force
        (Interpreter.info_document), if any; ``left``: the zeros of sensors that had left their address
        (Replacements.left_zeros), if any."""
        self._add(f"{prefix}/baselines", "baselines", t_host,
                  {"board": board, "sensors": sensors, **({"info": info} if info is not None else {}),
                   **({"left": left} if left else {})})

    def resume(self, board: str, after_reads: int, sensors: list[dict], info: dict | None, described: list[int],
               in_force: list[tuple], left: list[dict], identify: dict | None, t_host: float,
               prefix: str = "") -> None:
        """The zeros (``sensors``, as ``baselines``) and INFO in force before the board's read ``after_reads``
        of the recording, the sensors then described (``described``, tared or not) and ``in_force``: (SensorInfo,
        calibration id) each seen sensor was reconstructed with (named as in /calibrations, whose entry for it
        may be lost with the recording's start); ``left`` as ``baselines``; ``identify`` as ``settings``."""
        calibrations = [{"board": sensor.board, "sensor": sensor.id, "id": calibration_id,
                         "key": sensor_identity(sensor.board_info or {}, sensor)["key"]}
                        for sensor, calibration_id in in_force]
        self._add(f"{prefix}/resume", "resume", t_host, {"board": board, "after_reads": after_reads, "sensors": sensors,
                                                         "described": described, "calibrations": calibrations,
                                                         **({"info": info} if info is not None else {}),
                                                         **({"left": left} if left else {}),
                                                         **({"identify": identify} if identify else {})})

    def settings(self, board: str, level: str, mounting: str, identify: dict | None, t_host: float,
                 prefix: str = "") -> None:
        """How the board's forces are reconstructed, before its first read; ``identify``: its frames' wait for
        the board's INFO then (Identification.state; None: none, a recording's or replay's bytes)."""
        self._add(f"{prefix}/settings", "settings", t_host, {"board": board, "level": level, "mounting": mounting,
                                                             **({"identify": identify} if identify else {})})

    def diagnostics(self, t_host: float, diagnostics: dict, prefix: str = "") -> None:
        """``diagnostics``: {"counters": the decoder's, "rejected": the interpreter's}, as the schema says."""
        self._add(f"{prefix}/diagnostics", "diag", t_host, diagnostics)

    def close(self) -> None:
        self._writer.finish()


def foxglove_grid(frame: ForceFrame) -> dict:
    """A grid frame as foxglove.Grid: row-major FLOAT32 forces (NaN = no reading)."""
    info = frame.sensor
    sec, frac = divmod(frame.t_host, 1.0)
    return {
        "timestamp": {"sec": int(sec), "nsec": int(frac * 1e9)},
        "frame_id": f"tactile_{info.board}_{info.id}" if info.board else f"tactile_sensor_{info.id}",
        "pose": {"position": {"x": 0.0, "y": 0.0, "z": 0.0}, "orientation": {"x": 0.0, "y": 0.0, "z": 0.0, "w": 1.0}},
        "column_count": info.cols,
        "cell_size": {"x": GRID_CELL_M, "y": GRID_CELL_M},
        "row_stride": 4 * info.cols,
        "cell_stride": 4,
        "fields": [{"name": "force_N", "offset": 0, "type": schemas.FOXGLOVE_FLOAT32}],
        "data": base64.b64encode(np.asarray(frame.forces_N, dtype="<f4").tobytes()).decode(),
    }
