"""Force tables: shipped artifacts, keys, loading, and their physics."""
import time

import numpy as np
import pytest

from service.physics import tables
from service.physics.tables import SHAPES, ForceTable, TableSpec


@pytest.mark.parametrize("shape", SHAPES)
def test_default_tables_ship_and_load_fast(shape):
    t0 = time.perf_counter()
    table = tables.load(TableSpec(shape))
    assert time.perf_counter() - t0 < 0.1
    assert table.force_N[0] == 0 and table.relative_change[0] == 0
    assert np.all(np.diff(table.force_N) > 0)


def test_uniform_table_matches_a_fresh_low_order_build():
    shipped = tables.load(TableSpec("uniform"))
    fresh = tables.build(TableSpec("uniform", p=3, pz=3))
    at = np.array([1.0, 5.0, 10.0])
    np.testing.assert_allclose(np.interp(at, fresh.force_N, fresh.relative_change),
                               np.interp(at, shipped.force_N, shipped.relative_change), rtol=2e-3)


def test_normal_tables_are_monotone_and_stop_before_gap_closure():
    for shape in ("uniform", "uneven"):
        table = tables.load(TableSpec(shape))
        assert np.all(np.diff(table.relative_change) > 0)
        assert 20 < table.max_force_N < 60 and np.isfinite(table.relative_change).all()


def test_uneven_load_gives_more_change_than_uniform_at_low_force():
    uniform, uneven = (tables.load(TableSpec(s)) for s in ("uniform", "uneven"))
    at = np.array([0.25, 0.5])
    assert np.all(np.interp(at, uneven.force_N, uneven.relative_change) > np.interp(at, uniform.force_N, uniform.relative_change))


def test_shear_barely_changes_the_capacitance():
    shear, uniform = tables.load(TableSpec("shear")), tables.load(TableSpec("uniform"))
    assert abs(np.interp(5, shear.force_N, shear.relative_change)) < 0.05 * np.interp(5, uniform.force_N, uniform.relative_change)


def test_key_changes_with_every_parameter_and_is_checked(tmp_path):
    base = TableSpec("uniform")
    assert len({base.key, TableSpec("uniform", pdms_nu=0.495).key, TableSpec("uniform", p=5).key, TableSpec("uneven").key}) == 4
    table = tables.load(base)
    path = tables.save(table, tmp_path)
    tampered = path.read_text().replace('"pdms_nu": 0.49', '"pdms_nu": 0.48')
    with pytest.raises(ValueError, match="does not match its parameters"):
        ForceTable.from_json(tampered.encode())


def test_missing_table_names_the_command(tmp_path):
    with pytest.raises(FileNotFoundError, match="tactile tables build --shape uniform"):
        tables.load(TableSpec("uniform", pdms_nu=0.48), tmp_path)


def test_unknown_shape_is_named():
    with pytest.raises(ValueError, match="unknown load shape 'twist'"):
        TableSpec("twist")
