"""Force → ΔC/C0 tables of the 8x8 taxel, built offline from the Ritz model.

Three load shapes, each a curve over a force grid:

``uniform``  the paper's q0 on the central 3×3 mm (eq 18 scaling);
``uneven``   the array mounted on a 30 mm radius (paper §4.3): the bump's top
             is a cylinder, x²/2R below flat at x, and a flat loading bar
             presses it through the bump's own compliance (Winkler,
             E = 2.03 MPa over its 1 mm height), so the pressure
             k (δ − x²/2R)⁺ is concentrated on the centre line at small
             force and spreads to the whole bump as force grows;
``shear``    a uniform tangential traction on the 3×3 mm (capacitance from
             gap tilt and electrode slide).

A table is a versioned artifact keyed by a hash of every parameter that
shaped it; the service only loads them (JSON, milliseconds). A table ends at
the force where the gap would close by MAX_GAP_CLOSURE anywhere (the model is
not trusted past it); the service saturates there with a flag.
"""
from __future__ import annotations

import hashlib
from dataclasses import asdict, dataclass, field
from importlib import resources
from pathlib import Path
from typing import Callable

import numpy as np
import orjson

from .capacitance import gap_field, shear_relative_change
from .ritz import Load, RitzOptions, RitzSystem, Taxel, paper_stack, patch_load

MODEL_VERSION = 1
SHAPES = ("uniform", "uneven", "shear")
Q0_MPA = 0.1
TABLE_STEP_N = 0.25
SHEAR_MAX_N = 10.0


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

    def taxel(self) -> Taxel:
        return Taxel(stack=paper_stack(self.pdms_nu, self.pdms_E_MPa))

    def options(self) -> RitzOptions:
        return RitzOptions(p=self.p, pz=self.pz)


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


def _grid(max_force_N: float, step_N: float) -> np.ndarray:
    return np.append(np.arange(0.0, max_force_N, step_N), max_force_N)


def _contact_depth(force_N: float, k_MPa_per_mm: float, radius_mm: float, half_mm: float) -> float:
    """Bar indentation δ (mm) that carries ``force_N`` on the curved bump."""
    def carried(delta):
        c = min(np.sqrt(2 * radius_mm * delta), half_mm)
        return 2 * half_mm * 2 * k_MPa_per_mm * (delta * c - c**3 / (6 * radius_mm)) - force_N

    from scipy.optimize import brentq  # building tables only: not on the service's start-up path

    return brentq(carried, 0.0, 10.0)


def uneven_load(force_N: float, spec: TableSpec, taxel: Taxel) -> Load:
    half_mm = taxel.half_load_um / 1000
    k = spec.bump_E_MPa / spec.bump_height_mm
    delta = _contact_depth(force_N, k, spec.mount_radius_mm, half_mm)

    def traction(x, y):
        xm = x / 1000
        inside = (np.abs(x) <= taxel.half_load_um + 1e-9) & (np.abs(y) <= taxel.half_load_um + 1e-9)
        return np.where(inside, k * np.maximum(delta - xm**2 / (2 * spec.mount_radius_mm), 0.0), 0.0)

    return Load(traction, "z", points_per_element=32)


def build(spec: TableSpec, progress: Callable[[float], None] = lambda fraction: None) -> ForceTable:
    """Solve the model for ``spec`` and tabulate ΔC/C0 against force."""
    taxel = spec.taxel()
    unit_force = Q0_MPA * (2 * taxel.half_load_um / 1000) ** 2  # N carried by q0 on the load area
    if spec.shape == "shear":
        system = RitzSystem(taxel, spec.options(), "x")
        progress(0.5)
        solution = system.solve(patch_load(Q0_MPA, taxel.half_load_um, "x"))
        forces = _grid(SHEAR_MAX_N, spec.step_N)
        table = ForceTable(spec, forces, shear_relative_change(solution, unit_force, forces), SHEAR_MAX_N, system.rcond)
        progress(1.0)
        return table
    system = RitzSystem(taxel, spec.options(), "z")
    progress(0.3)
    uniform = gap_field(system.solve(patch_load(Q0_MPA, taxel.half_load_um)), unit_force)
    forces = _grid(uniform.max_force_N, spec.step_N)
    if spec.shape == "uniform":
        progress(1.0)
        return ForceTable(spec, forces, uniform.relative_change(forces), uniform.max_force_N, system.rcond)
    values = [0.0]
    for i, force in enumerate(forces[1:], 1):
        field_ = gap_field(system.solve(uneven_load(force, spec, taxel)), force)
        value = field_.relative_change(force)[0]
        if np.isnan(value):
            forces = forces[:i]
            break
        values.append(value)
        progress(0.3 + 0.7 * i / len(forces))
    progress(1.0)
    return ForceTable(spec, forces, np.array(values), float(forces[-1]), system.rcond)


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
