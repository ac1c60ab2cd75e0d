"""Pydantic models of the HTTP schema (OpenAPI): the request bodies the API
accepts, and the frame messages built by ``service.fanout.encoding``, which
they document but do not encode (frames are serialised by the fan-out)."""
from __future__ import annotations

from pydantic import BaseModel, Field, StrictFloat, StrictInt

Number = StrictFloat | StrictInt  # a JSON number: true is no sensitivity, "1.2" no capacitance


class RecordRequest(BaseModel):
    model_config = {"extra": "forbid"}  # an old client's "path" is refused by name, never taken as one

    name: str | None = Field(default=None, description="a bare file name ending in .mcap, written into the service's "
                             "recordings directory (default: recording-<time>.mcap); the raw bytes go beside it as .bin")


class GridCalibrationUpload(BaseModel):
    sensitivity_pct_per_N: list[Number] = Field(description="per taxel, row-major, measured 0–10 N slope in %/N")
    c0_pF: list[Number] | None = Field(default=None, description="per taxel, row-major, measured unloaded "
                                      "capacitance in pF, 0.01–1000 (lets a tare tell a load; table 1's when absent)")


class QuadCalibrationUpload(BaseModel):
    normal_fit: tuple[Number, Number] = Field(description="ΔC/C0 = c2 F² + c1 F: [c2, c1]; c2 ≤ 0 (0 = linear), "
                                             "c1 in (0.001, 1) /N, |c2| ≤ 0.45·c1")
    shear_fit: tuple[Number, Number] = Field(description="ΔC/C0 = a F − b F²: [a, b]; a in (0.001, 1) /N, 0 ≤ b ≤ 0.45·a")
    c0_pF: list[Number] | None = Field(default=None, description="C11, C12, C21, C22: measured unloaded capacitances "
                                      "in pF, 0.01–1000 (a tare takes readings around them; ~2.2 pF when absent)")


class CalibrationDocumentUpload(BaseModel):
    """A whole calibration document, as ``tactile calibrations export`` writes
    it (gains with their errors, measured C0, empirical curves, crosstalk,
    fatigue): checked field by field when it is applied."""

    model_config = {"extra": "allow"}
    schema_: StrictInt = Field(alias="schema", description="the document format's version (1)")


class Header(BaseModel):
    sensor_id: int
    sensor_name: str
    kind: str = Field(description="grid | quad")
    seq: int = Field(description="board scan counter, wraps at 65536")
    board_time_us: int = Field(description="board clock at the end of the scan, µs, wraps at 2^32")
    stamp: float = Field(description="host receive time, s since the epoch")
    scan_stamp: float | None = Field(description="the scan's time on the host clock, s since the epoch: the board "
                                     "clock mapped by the arrival times (docs/clock.md); null until mapped")
    calibration: str = Field(description="id of the calibration the forces rest on: a registry id, or "
                             "builtin-table1 / builtin-fits34-35 (the papers', not measured on this sensor)")


class Vector3(BaseModel):
    x: float | None
    y: float | None
    z: float | None


class Wrench(BaseModel):
    force: Vector3


class Contact(BaseModel):
    total_N: float
    cop_x_mm: float | None = Field(description="centre of pressure, array frame (origin at the centre, x along columns)")
    cop_y_mm: float | None
    area_mm2: float
    contacts: int = Field(description="4-connected regions above 0.05 N")


class ContactReply(Contact):
    """``GET /sensors/{id}/contact``: the latest frame's contact summary."""

    stale: bool = Field(description="the sensor sent no frame for /health's stale threshold: the summary is not current")


class Raw(BaseModel):
    capacitance_pF: list[float | None]


class FrameMessage(BaseModel):
    """One reconstructed frame (fields present as subscribed)."""

    header: Header
    rows: int | None = None
    cols: int | None = None
    force_N: list[float | None] | None = Field(default=None, description="grid: normal force per taxel, row-major")
    sigma_N: list[float | None] | None = Field(default=None, description="grid: 1-σ of each force in N "
                                               "(null: no force, or saturated)")
    wrench: Wrench | None = Field(default=None, description="quad: force in N (Fz positive in compression)")
    wrench_sigma: Wrench | None = Field(default=None, description="quad: 1-σ of each force component in N")
    raw: Raw | None = None
    contact: Contact | None = None
    flags: list[str] | None = None
    taxel_flags: dict[str, list[int]] | None = Field(default=None, description="flag name → row-major taxel indices")
