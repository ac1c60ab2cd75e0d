"""Force tables: shipped artifacts, keys, loading, and their physics."""
import time

import numpy as np
import pytest

from service.physics import table_files, tables
from service.physics.table_files import SHAPES, ForceTable, TableSpec


@pytest.mark.parametrize("shape", SHAPES)
def test_default_tables_ship_and_load_fast(shape):
    t0 = time.perf_counter()
    table = table_files.load(TableSpec(shape))
    assert time.perf_counter() - t0 < 0.1
    assert table.force_N[0] == 0 and table.relative_change[0] == 0
    assert np.all(np.diff(table.force_N) > 0)


def test_uniform_table_matches_a_fresh_low_order_build():
    shipped = table_files.load(TableSpec("uniform"))
    fresh = tables.build(TableSpec("uniform", p=3, pz=3))
    at = np.array([1.0, 5.0, 10.0])
    np.testing.assert_allclose(np.interp(at, fresh.force_N, fresh.relative_change),
                               np.interp(at, shipped.force_N, shipped.relative_change), rtol=2e-3)


def test_normal_tables_are_monotone_and_stop_before_gap_closure():
    for shape in ("uniform", "uneven"):
        table = table_files.load(TableSpec(shape))
        assert np.all(np.diff(table.relative_change) > 0)
        assert 20 < table.max_force_N < 60 and np.isfinite(table.relative_change).all()


def test_uneven_load_gives_more_change_than_uniform_at_low_force():
    uniform, uneven = (table_files.load(TableSpec(s)) for s in ("uniform", "uneven"))
    at = np.array([0.25, 0.5])
    assert np.all(np.interp(at, uneven.force_N, uneven.relative_change) > np.interp(at, uniform.force_N, uniform.relative_change))


def test_shear_barely_changes_the_capacitance():
    shear, uniform = table_files.load(TableSpec("shear")), table_files.load(TableSpec("uniform"))
    assert abs(np.interp(5, shear.force_N, shear.relative_change)) < 0.05 * np.interp(5, uniform.force_N, uniform.relative_change)


def test_key_changes_with_every_parameter_and_is_checked(tmp_path):
    base = TableSpec("uniform")
    assert len({base.key, TableSpec("uniform", pdms_nu=0.495).key, TableSpec("uniform", p=5).key, TableSpec("uneven").key}) == 4
    table = table_files.load(base)
    path = table_files.save(table, tmp_path)
    tampered = path.read_text().replace('"pdms_nu": 0.49', '"pdms_nu": 0.48')
    with pytest.raises(ValueError, match="does not match its parameters"):
        ForceTable.from_json(tampered.encode())


def test_missing_table_names_the_command(tmp_path):
    with pytest.raises(FileNotFoundError, match="tactile tables build --shape uniform"):
        table_files.load(TableSpec("uniform", pdms_nu=0.48), tmp_path)


def test_unknown_shape_is_named():
    with pytest.raises(ValueError, match="unknown load shape 'twist'"):
        TableSpec("twist")


def test_shipped_tables_carry_their_pchip_inverse_exactly():
    """The dense inverse shipped with each table (so the service starts
    without scipy.interpolate) is the table's PCHIP inverse, bit for bit."""
    from scipy.interpolate import PchipInterpolator

    from service.physics.table_files import ForceTable, shipped_dir
    from service.physics.taxel_response import DENSE_POINTS

    checked = 0
    for path in sorted(shipped_dir().glob("*.json")):
        table = ForceTable.from_json(path.read_bytes())
        if table.dense is None:
            assert not np.all(np.diff(table.relative_change) > 0)  # only a table that is never inverted
            continue
        dense_r = np.linspace(0.0, table.relative_change[-1], DENSE_POINTS)
        assert np.array_equal(table.dense[0], dense_r)
        assert np.array_equal(table.dense[1], PchipInterpolator(table.relative_change, table.force_N)(dense_r))
        checked += 1
    assert checked == 2


def test_the_unleak_matrix_is_the_inverse_leakage_filter():
    from scipy.signal import lfilter

    from service.reconstruct.crosstalk import unleak_matrix

    for e in (0.0, 0.01, 0.03, 0.3):
        reference = lfilter([1.0], [1.0 - e, e], np.eye(64), axis=-1)
        np.testing.assert_allclose(unleak_matrix(64, e), reference, rtol=0, atol=1e-15)
