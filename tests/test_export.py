"""The replay's exports: batch JSON lines equal to the per-frame reference,
the Parquet table, the batch contact summary, the offline pipeline."""
import dataclasses
import io

import numpy as np
import orjson
import pytest

from service.cli import main
from service.fanout import encoding
from service.pipeline import Pipeline
from service.reconstruct import Reconstructor
from service.reconstruct.contact import summarise
from service.record import export
from service.record.contact_batch import summaries
from service.replay import replay
from tests.regenerate_goldens import DATA


class Collect:
    def __init__(self):
        self.frames = []

    def write(self, frames):
        self.frames += frames


@pytest.fixture(scope="module")
def frames():
    """Both committed fault captures: open channels (NaN), seq gaps, taxel
    flags, grids and quads."""
    out = []
    for name in ("press_faults", "demo_leak_drift"):
        sink = Collect()
        replay(DATA / f"{name}.bin", writer=sink)
        out += sink.frames
    return out


def reference(frames):
    return [orjson.dumps(encoding.to_export_dict(f), option=orjson.OPT_SERIALIZE_NUMPY) + b"\n" for f in frames]


def test_the_captures_hold_what_the_encoder_must_get_right(frames):
    docs = [orjson.loads(line) for line in reference(frames)]
    assert {d["kind"] for d in docs} == {"grid", "quad"}
    assert any(None in d["taxels_N"] for d in docs if d["kind"] == "grid")
    assert any(d["flags"] for d in docs) and any(d.get("taxel_flags") for d in docs)
    assert any(d.get("contact") and d["contact"]["contacts"] for d in docs)
    assert any(d.get("contact") and d["contact"]["cop_x_mm"] is None for d in docs)


@pytest.mark.parametrize("batch", [1, 7, 500, 10_000])
def test_batch_json_lines_equal_the_per_frame_encoding_line_for_line(frames, batch):
    lines = b"".join(export.encode_lines(frames[i : i + batch]) for i in range(0, len(frames), batch))
    assert lines.splitlines(keepends=True) == reference(frames)


def test_writers_that_gather_small_batches_write_what_they_would_at_once(frames, tmp_path):
    """An MCAP replay writes each recorded read (a frame or two per sensor);
    the writers gather them (JsonLines with ``gather``, Parquet always) and
    write the same bytes / table, what waits written at close."""
    import pyarrow.parquet as pq
    from service.record.export_parquet import Parquet

    stream = io.BytesIO()
    lines = export.JsonLines(stream, gather=True)
    parquet, whole = Parquet(tmp_path / "small.parquet"), Parquet(tmp_path / "whole.parquet")
    for i in range(0, len(frames), 3):
        lines.write(frames[i:i + 3])
        parquet.write(frames[i:i + 3])
    assert len(stream.getvalue().splitlines()) < len(frames)  # some wait for the close
    lines.close()
    parquet.close()
    whole.write(frames)
    whole.close()
    assert stream.getvalue().splitlines(keepends=True) == reference(frames)
    assert pq.read_table(tmp_path / "small.parquet").equals(pq.read_table(tmp_path / "whole.parquet"))


def test_a_large_batch_is_exported_in_pieces_of_bounded_memory(frames, tmp_path, monkeypatch):
    """A raw capture's replay hands the writers ~4 000 frames a call. Encoded
    whole, each 8×8 batch took 10 MB of lines and as much joined, which glibc
    gave back to the kernel and faulted in again at the next (80 000 page
    faults for 60 000 frames, most of the export's system time): the lines are
    written, and the Parquet columns made, a bounded piece at a time."""
    from service.record import export_parquet

    grids = [f for f in frames if f.sensor.kind == "grid" and f.forces_N.size == 64]
    batch = (grids * (5000 // len(grids) + 1))[:5000]
    writes = []

    class Sizes:
        def write(self, data):
            writes.append(len(data))

    export.JsonLines(Sizes()).write(batch)
    assert sum(writes) == len(b"".join(reference(batch))) and max(writes) < 2_000_000
    tables = []
    real_table = export_parquet.table
    monkeypatch.setattr(export_parquet, "table", lambda fs: tables.append(len(fs)) or real_table(fs))
    parquet = export_parquet.Parquet(tmp_path / "large.parquet")
    parquet.write(batch)
    parquet.close()
    assert sum(tables) == 5000 and max(tables) <= 1024


def test_keys_added_to_the_export_dict_are_followed(frames, monkeypatch):
    """Whatever to_export_dict gives — new keys, a known key meaning something
    else — the batch encoder writes the same bytes."""
    rng = np.random.default_rng(3)
    frames = [dataclasses.replace(f, calibration=f"cal-{f.sensor.id}",
                                  sigma_N=None if f.seq % 5 == 0 else rng.random(f.forces_N.shape).astype(np.float32))
              for f in frames[:800]]
    original = encoding.to_export_dict

    def extended(frame):
        return {**original(frame), "calibration": frame.calibration, "sigma_N": frame.sigma_N,
                "seq": frame.seq + 1, "unknown": {"level": frame.level}}

    monkeypatch.setattr(encoding, "to_export_dict", extended)
    monkeypatch.setattr(export, "to_export_dict", extended)
    assert export.encode_lines(frames).splitlines(keepends=True) == reference(frames)
    assert b'"unknown":{"level":"full"}' in export.encode_lines(frames[:1])


def test_the_batch_contact_summary_is_the_per_frame_one_bit_for_bit():
    rng = np.random.default_rng(1)
    for rows, cols in ((8, 8), (3, 5)):
        forces = rng.random((2000, rows * cols)) * rng.random((2000, 1)) * 0.2 - 0.02
        forces[rng.random(forces.shape) < 0.02] = np.nan
        forces[5] = np.nan
        expected = [None if np.isnan(f).all() else summarise(f, rows, cols) for f in forces]
        assert [orjson.dumps(s) for s in summaries(forces, rows, cols)] == [orjson.dumps(s) for s in expected]
        assert max(s["contacts"] for s in expected if s) >= 3


def test_parquet_holds_the_json_lines_and_opens_in_pandas_and_polars(tmp_path, capsys):
    import pandas
    import polars

    capture = DATA / "press_faults.bin"
    assert main(["replay", str(capture), "--export", str(tmp_path / "out.parquet")]) == 0
    assert main(["replay", str(capture), "--export", str(tmp_path / "out.jsonl")]) == 0
    docs = [orjson.loads(line) for line in (tmp_path / "out.jsonl").read_bytes().splitlines()]
    table = pandas.read_parquet(tmp_path / "out.parquet")
    assert len(polars.read_parquet(tmp_path / "out.parquet")) == len(table) == len(docs)
    grids = polars.read_parquet(tmp_path / "out.parquet").filter(polars.col("kind") == "grid")
    taxels = grids["taxels_N"].explode()
    missing = sum(v is None for d in docs for v in d.get("taxels_N", []))
    assert missing > 0 and taxels.null_count() == missing and not taxels.is_nan().any()  # nulls, as JSON's
    for doc, row in zip(docs, table.itertuples()):
        assert (row.sensor, row.seq, row.t_us, row.kind, list(row.flags)) == (doc["sensor"], doc["seq"], doc["t_us"],
                                                                             doc["kind"], doc["flags"])
        key, other = ("taxels_N", "fxyz_N") if doc["kind"] == "grid" else ("fxyz_N", "taxels_N")
        as_json = lambda values: [None if v is None or v != v else v for v in values]  # noqa: E731 — pandas: NaN or None
        assert as_json(getattr(row, key)) == doc[key]
        assert getattr(row, other) is None and row.calibration == doc["calibration"]
        assert as_json(row.sigma_N) == [None if v is None else float(np.float32(v)) for v in doc["sigma_N"]]
        if doc["kind"] == "grid":
            assert {name: list(hits) for name, hits in row.taxel_flags} == doc["taxel_flags"]
            contact = {k: None if isinstance(v, float) and np.isnan(v) else v for k, v in row.contact.items()}
            assert contact == doc["contact"]


def test_an_export_of_no_recording_leaves_no_parquet_behind(tmp_path, capsys):
    path = tmp_path / "no.mcap"
    path.write_bytes(b"not an mcap file")
    assert main(["replay", str(path), "--export", str(tmp_path / "out.parquet")]) == 2
    assert not (tmp_path / "out.parquet").exists()


def test_an_offline_pipeline_keeps_no_history_and_publishes_the_same_frames():
    data = (DATA / "press_faults.bin").read_bytes()
    published = {True: [], False: []}
    for keep in (True, False):
        pipeline = Pipeline(Reconstructor(hold_until_tared=True), clock=lambda: 0.0, keep_history=keep)
        pipeline.listeners.append(published[keep].extend)
        pipeline.feed(data, 0.0)
        pipeline.finish(0.0)
        assert bool(pipeline.latest) == bool(pipeline.rates) == keep
    assert reference(published[False]) == reference(published[True])


def test_a_raw_capture_replays_alike_in_small_and_large_chunks():
    """Paced (4 KiB chunks, timed) and as fast as possible (1 MiB) give the same lines."""
    from service.record.pacing import Pacer

    fast, paced = io.BytesIO(), io.BytesIO()
    replay(DATA / "demo_leak_drift.bin", fast)
    replay(DATA / "demo_leak_drift.bin", paced, pacer=Pacer(1e9))
    assert fast.getvalue() == paced.getvalue() and fast.getvalue().count(b"\n") > 500


def test_parquet_rows_equal_the_json_lines_for_grids_of_two_sizes_and_quads_in_any_batch(tmp_path):
    """Columns are built from buffers (no pandas); each row still holds what
    the frame's JSON line says, whatever the batch holds."""
    import pyarrow as pa

    from firmware_sim.board import BoardConfig, capture
    from firmware_sim.urlhandler.protocol_sim import parse_sensors
    from service.record.export_parquet import table

    raw = tmp_path / "mixed.bin"
    raw.write_bytes(capture(BoardConfig(sensors=parse_sensors("grid8x8,grid3x5,quad"), scene="press"), 1.0)[0])
    sink = Collect()
    replay(raw, writer=sink)
    frames = sink.frames
    assert {(f.sensor.kind, f.forces_N.size) for f in frames} == {("grid", 64), ("grid", 15), ("quad", 3)}
    docs = [orjson.loads(line) for line in reference(frames)]
    assert {(d.get("rows"), d.get("cols"), len(d.get("taxels_N", d.get("fxyz_N")))) for d in docs} == \
        {(8, 8, 64), (3, 5, 15), (None, None, 3)}  # a grid's shape is in its line, not only its length
    for batch in (1, 13, len(frames)):
        got = pa.concat_tables([table(frames[i : i + batch]) for i in range(0, len(frames), batch)])
        got.validate(full=True)
        for doc, row in zip(docs, got.to_pylist()):
            key, other = ("taxels_N", "fxyz_N") if doc["kind"] == "grid" else ("fxyz_N", "taxels_N")
            assert row[key] == doc[key] and row[other] is None  # JSON's null is Parquet's null, not NaN
            assert (row["board"], row["sensor"], row["seq"], row["t_us"], row["flags"], row["calibration"]) == \
                (doc["board"], doc["sensor"], doc["seq"], doc["t_us"], doc["flags"], doc["calibration"])
            assert (row["rows"], row["cols"]) == (doc.get("rows"), doc.get("cols"))
            assert row["sigma_N"] == [None if v is None else float(np.float32(v)) for v in doc["sigma_N"]]
            if doc["kind"] == "grid":
                assert dict(row["taxel_flags"]) == doc["taxel_flags"]
                assert row["contact"] == doc["contact"]
            else:
                assert row["taxel_flags"] is None and row["contact"] is None


def test_binary_frames_carry_each_taxels_flags_to_clients_and_the_gateway(frames):
    """Encoding v4: a binary client, and a gateway rebuilding frames from the
    published encoding, see which taxels are flagged, as a JSON client does."""
    import struct

    from service.client import TactileClient
    from service.fanout.encoding import DEFAULT_FIELDS, decode_binary, to_binary
    from service.net.zenoh_feed import _frame

    flagged = [f for f in frames if f.sensor.kind == "grid" and f.taxel_flag_lists()]
    quads = [f for f in frames if f.sensor.kind == "quad"][:5]
    assert len(flagged) > 20 and quads
    chosen = flagged[:: max(1, len(flagged) // 40)] + quads
    records = decode_binary(struct.pack("<H", len(chosen)) + b"".join(to_binary(f) for f in chosen))
    client = TactileClient("http://localhost:1")
    client._sensors = {(f.sensor.board, f.sensor.id): {"kind": f.sensor.kind, "rows": f.sensor.rows,
                                                       "cols": f.sensor.cols} for f in chosen}
    for frame, record in zip(chosen, records):
        assert record["flags"] == [name for name in encoding.FRAME_FLAG_BITS if name in frame.flags]
        as_json = encoding.to_json_dict(frame)
        if frame.sensor.kind == "grid":
            assert record["taxel_flags"] == as_json["taxel_flags"] == frame.taxel_flag_lists()
            assert client._shaped_frames([record], DEFAULT_FIELDS)[0]["taxel_flags"] == as_json["taxel_flags"]
            assert _frame(frame.sensor, record).taxel_flag_lists() == frame.taxel_flag_lists()
        else:
            assert "taxel_flags" not in record
            assert "taxel_flags" not in client._shaped_frames([record], DEFAULT_FIELDS)[0]
    without = decode_binary(struct.pack("<H", 1) + to_binary(flagged[0], frozenset({"force"})))[0]
    assert "taxel_flags" not in without and without["force_N"].shape == (64,)
    for fields in ({"flags"}, {"raw", "flags"}, {"sigma", "flags"}):  # every record still cut where it ends
        message = struct.pack("<H", len(chosen)) + b"".join(to_binary(f, frozenset(fields)) for f in chosen)
        assert [(r["sensor_id"], r["seq"]) for r in decode_binary(message)] == [(f.sensor.id, f.seq) for f in chosen]


def test_binary_version_3_records_from_a_service_not_yet_upgraded_still_decode():
    """A v3 record is a v4 one without taxel flags (n 0 when neither force
    nor σ was asked for): a gateway or client upgraded first reads it; a v3
    grid record with raw channels alone cannot be sized and says so."""
    import struct

    from service.fanout.encoding import _RECORD, decode_binary, to_binary

    sink = Collect()
    replay(DATA / "press_faults.bin", writer=sink)
    grid = next(f for f in sink.frames if f.sensor.kind == "grid" and not np.isnan(f.forces_N).all())
    quad = next(f for f in sink.frames if f.sensor.kind == "quad")

    def as_v3(record: bytes) -> bytes:
        return bytes([3]) + record[1:]

    fields = frozenset({"force", "sigma", "raw"})
    v3 = decode_binary(struct.pack("<H", 2) + as_v3(to_binary(grid, fields)) + as_v3(to_binary(quad, fields)))
    v4 = decode_binary(struct.pack("<H", 2) + to_binary(grid, fields) + to_binary(quad, fields))
    for old, new in zip(v3, v4):
        assert old.keys() == new.keys() and old["seq"] == new["seq"]
        for key in ("force_N", "sigma_N", "capacitance_pF"):
            np.testing.assert_array_equal(old[key], new[key])
    raw_only = (_RECORD.pack(3, 0, grid.sensor.id, 2, grid.seq, grid.t_us, 0.0, np.nan, 0, 0, 1) + b"c" + b"\x01b"
                + np.asarray(grid.capacitance_pF, "<f4").tobytes())  # a v3 grid record: raw alone, n = 0
    with pytest.raises(ValueError, match="cannot be sized"):
        decode_binary(struct.pack("<H", 1) + raw_only)


def test_a_frame_in_the_tare_window_exports_one_null_sigma_per_force_as_the_api_gives():
    """A recording replays its tare window as it ran live: forces null, no σ.
    docs/api.md: ``sigma_N`` is one σ per force, null where there is none —
    the WebSocket frame's ``[null, …]`` — where the JSON line gave one null
    for the whole list and the Parquet row a null list (the tester's s3b: 99
    such lines). Both now give a null per force, for grids and quads."""
    from firmware_sim.board import BoardConfig, capture
    from service.record.export_parquet import table

    pipeline = Pipeline(Reconstructor())  # live: the tare window is published, null and flagged
    published = []
    pipeline.listeners.append(published.extend)
    pipeline.feed(capture(BoardConfig(scene="idle", seed=2), 0.3)[0], 1000.0)
    taring = [f for f in published if f.sigma_N is None]
    assert {(f.sensor.kind, f.forces_N.size) for f in taring} == {("grid", 64), ("quad", 3)}
    docs = [orjson.loads(line) for line in export.encode_lines(taring).splitlines()]
    rows = table(taring).to_pylist()
    for frame, doc, row in zip(taring, docs, rows, strict=True):
        nulls = [None] * (64 if frame.sensor.kind == "grid" else 3)
        assert doc["sigma_N"] == nulls and row["sigma_N"] == nulls
        api = orjson.loads(orjson.dumps(encoding.to_json_dict(frame), option=orjson.OPT_SERIALIZE_NUMPY))
        assert doc["sigma_N"] == (api["sigma_N"] if frame.sensor.kind == "grid"
                                  else [api["wrench_sigma"]["force"][axis] for axis in "xyz"])
