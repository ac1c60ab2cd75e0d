"""The model tables as shipped files: what shapes a table (``TableSpec``,
hashed into its file name), the table itself (``ForceTable``), loading and
saving. Building them (the Ritz model, scipy) is physics/tables.py's: the
service only loads, so its start-up imports neither.
"""
from __future__ import annotations

import hashlib
from dataclasses import asdict, dataclass, field
from importlib import resources
from pathlib import Path

import numpy as np
import orjson

MODEL_VERSION = 1
SHAPES = ("uniform", "uneven", "shear")
TABLE_STEP_N = 0.25


@dataclass(frozen=True)
class TableSpec:
    """Every parameter that shapes a table; its hash names the artifact."""

    shape: str
    pdms_nu: float = 0.49
    pdms_E_MPa: float = 0.55
    p: int = 4
    pz: int = 3
    mount_radius_mm: float = 30.0
    bump_E_MPa: float = 2.03
    bump_height_mm: float = 1.0
    step_N: float = TABLE_STEP_N
    model_version: int = field(default=MODEL_VERSION)

    def __post_init__(self) -> None:
        if self.shape not in SHAPES:
            raise ValueError(f"unknown load shape {self.shape!r}; known: {', '.join(SHAPES)}")

    @property
    def key(self) -> str:
        return hashlib.sha256(orjson.dumps(asdict(self), option=orjson.OPT_SORT_KEYS)).hexdigest()[:16]

    @property
    def filename(self) -> str:
        return f"taxel-{self.shape}-{self.key}.json"


@dataclass(frozen=True)
class ForceTable:
    spec: TableSpec
    force_N: np.ndarray
    relative_change: np.ndarray
    max_force_N: float
    rcond: float
    # The inverse, force at DENSE_POINTS equally spaced ΔC/C0 over [0, top] by
    # PCHIP, computed when the table is built and shipped with it: the
    # service then needs no scipy.interpolate to start (0.6 s).
    dense: tuple[np.ndarray, np.ndarray] | None = None

    def with_dense(self) -> ForceTable:
        """This table with its dense inverse (none for a table that is not
        strictly increasing in ΔC/C0, e.g. the shear table: it is not inverted)."""
        from .taxel_response import dense_inverse

        if not np.all(np.diff(self.relative_change) > 0):
            return self
        return ForceTable(self.spec, self.force_N, self.relative_change, self.max_force_N, self.rcond,
                          dense_inverse(self.force_N, self.relative_change))

    def to_json(self) -> bytes:
        table = self if self.dense is not None else self.with_dense()
        dense = {} if table.dense is None else {"dense_dC_C0": table.dense[0], "dense_force_N": table.dense[1]}
        return orjson.dumps(
            {
                "spec": asdict(self.spec),
                "key": self.spec.key,
                "force_N": self.force_N,
                "dC_C0": self.relative_change,
                "max_force_N": self.max_force_N,
                "rcond": self.rcond,
                **dense,
            },
            option=orjson.OPT_SERIALIZE_NUMPY | orjson.OPT_INDENT_2,
        )

    @classmethod
    def from_json(cls, data: bytes) -> ForceTable:
        doc = orjson.loads(data)
        spec = TableSpec(**doc["spec"])
        if doc["key"] != spec.key:
            raise ValueError(f"table key {doc['key']} does not match its parameters ({spec.key}); rebuild it")
        dense = (np.array(doc["dense_dC_C0"]), np.array(doc["dense_force_N"])) if "dense_dC_C0" in doc else None
        return cls(spec, np.array(doc["force_N"]), np.array(doc["dC_C0"]), doc["max_force_N"], doc["rcond"], dense)


def shipped_dir() -> Path:
    return Path(str(resources.files("service").joinpath("data/tables")))


def load(spec: TableSpec, directory: Path | None = None) -> ForceTable:
    """Load a built table; FileNotFoundError says which command builds it."""
    path = (directory or shipped_dir()) / spec.filename
    if not path.exists():
        raise FileNotFoundError(f"no table {path.name} for {spec}; build it with `tactile tables build --shape {spec.shape}`")
    return ForceTable.from_json(path.read_bytes())


def save(table: ForceTable, directory: Path | None = None) -> Path:
    directory = directory or shipped_dir()
    directory.mkdir(parents=True, exist_ok=True)
    path = directory / table.spec.filename
    path.write_bytes(table.to_json())
    return path
