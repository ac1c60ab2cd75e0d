"""``tactile calibrations import`` refuses what the service could not use,
naming the field, as ``calibrate`` refuses to store it: such documents were
stored and activated, and serve and replay then fell back to the built-in
calibration with a log line."""
import json

import pytest

from service.calibration import registry as reg
from service.cli import main


def usable() -> dict:
    """An 8x8 document the service can use: table 1's values for one sensor."""
    document = {k: v for k, v in reg.builtin_document().items() if k != "id"}
    return {**document, "sensor": {"key": "sensor:T-1", "sensor_serial": "T-1", "sensor_id": 0}}


def broken(field: str) -> dict:
    document = usable()
    taxels = document["taxels"]
    if field == "kind":
        document["kind"] = "ring"
    elif field == "rows":
        document["rows"] = "8"
    elif field == "short":
        taxels["gain"] = taxels["gain"][:10]
    elif field == "null":
        taxels["c0_pF"][4] = None
    elif field == "nan":
        taxels["gain"][3] = float("nan")
    else:
        force, relative = [0.0, 2.0, 5.0, 9.0], [0.0, 0.02, 0.05, 0.09]
        taxels["curves"] = {"0": {"force_N": force[::-1] if field == "reversed" else force,
                                  "relative": relative[::-1] if field == "reversed" else relative[:3]}}
    return document


@pytest.mark.parametrize("field, message", [
    ("kind", "kind: 'ring' is neither 'grid' nor 'quad'"),
    ("rows", "rows, cols: '8', 8 is not a grid's shape (two positive integers)"),
    ("short", "taxels.gain: 10 values for the 64 taxels"),
    ("null", "taxels.c0_pF[4] is null: expected a number"),
    ("nan", "taxels.gain[3] = nan is not a JSON number"),
    ("reversed", "taxels.curves['0']: must be finite and strictly increasing"),
    ("lengths", "taxels.curves['0']: force_N (4 values) and relative (3) are not two lists of one length"),
])
def test_a_document_the_service_cannot_use_is_not_imported_and_the_field_is_named(tmp_path, capsys, field, message):
    path = tmp_path / "c.json"
    path.write_text(json.dumps(broken(field)))  # json writes NaN as it is
    registry = tmp_path / "r.sqlite3"
    assert main(["calibrations", "import", str(path), "--activate", "--registry", str(registry)]) == 2
    error = capsys.readouterr().err
    assert f"{path}: not imported, the service could not use it: {message}" in error, error
    with reg.Registry(registry) as stored:
        assert [row["id"] for row in stored.list()] == [reg.BUILTIN_ID]


def test_a_usable_document_imports_with_the_id_of_its_content(tmp_path):
    path = tmp_path / "c.json"
    path.write_text(json.dumps(usable()))
    with reg.Registry(tmp_path / "r.sqlite3") as registry:
        assert registry.import_(path) == reg.calibration_id(usable())


def test_a_document_that_is_not_json_names_the_field_that_is_not_a_number():
    with pytest.raises(ValueError, match=r"^statistics\.worst\[1\] = inf is not a JSON number"):
        reg.calibration_id({"statistics": {"worst": [0.1, float("inf")]}})
