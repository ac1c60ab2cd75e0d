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
    elif field.startswith("sensitivity"):  # "sensitivity=VALUE" on taxel 27
        taxels["sensitivity_pct_per_N"][27] = float(field.split("=")[1])
    elif field.startswith("curves="):
        taxels["curves"] = json.loads(field.split("=")[1])
    elif field.startswith("curve="):  # "curve=F0,F1" on taxel 27
        taxels["curves"] = {"27": {"force_N": [float(f) for f in field.split("=")[1].split(",")],
                                   "relative": [0.0, 0.5]}}
    elif field.startswith("curve_relative="):  # "curve_relative=JSON" at 0 and 10 N on taxel 27
        taxels["curves"] = {"27": {"force_N": [0.0, 10.0], "relative": json.loads(field.split("=")[1])}}
    elif field.startswith("max_force"):
        taxels["max_force_N"][5] = float(field.split("=")[1])
    elif field.startswith("created"):
        document["created"] = json.loads(field.split("=")[1])
    elif field.startswith("mounting"):
        document["mounting"] = json.loads(field.split("=")[1])
    elif field.startswith("taxels."):  # "taxels.NAME[5]=JSON"
        name, value = field.removeprefix("taxels.").split("[5]=")
        taxels[name][5] = json.loads(value)
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
    # the short form's range (0.1, 10) %/N: at level0 these read a 5 N load as -4.4, 5.5e4 and 0.0055 N, unflagged
    ("sensitivity=-1.25", "taxels.sensitivity_pct_per_N[27] = -1.25 is outside (0.1, 10) %/N"),
    ("sensitivity=0.0001", "taxels.sensitivity_pct_per_N[27] = 0.0001 is outside (0.1, 10) %/N"),
    ("sensitivity=1000", "taxels.sensitivity_pct_per_N[27] = 1000 is outside (0.1, 10) %/N"),
    # a curve's forces from 0 up to where the stiffest plausible taxel's gap closes (37.68 N / 0.08 = 471 N):
    # -100..-99 N read a 5 N load as -99.9 ± 0.018 N, 0..1e9 N as 1.1e8 N; a session's max_force_N likewise
    ("curve=-100,-99", "taxels.curves['27']: force_N starts at -100 N, below 0"),
    ("curve=0,1e9", "taxels.curves['27']: force_N reaches 1e+09 N, past 471 N"),
    ("curve=0,480", "taxels.curves['27']: force_N reaches 480 N, past 471 N"),
    ("max_force=1e9", "taxels.max_force_N[5] = 1e+09 is outside (0, 471] N"),
    ("max_force=-3", "taxels.max_force_N[5] = -3 is outside (0, 471] N"),
    ('curves=[1]', "taxels.curves: expected an object {taxel: {force_N, relative}}, got [1]"),
    ('curves="x"', "taxels.curves: expected an object {taxel: {force_N, relative}}, got 'x'"),
    # each point within what taxels of gain 0.08 to 8 read at its force on the model table, ±0.005: at 10 N
    # R(0.8 N) - 0.005 = 0.00437 to R(80 N) = the table's top 0.7846 + 0.005. The press scene's 5 N read
    # 5e-301 N ± 0.013 N with relative [0, 1e300], 0 N with [0.5, 0.6], 5 N at any load with ±1e300; unflagged
    ("curve_relative=[0, 1e300]", "taxels.curves['27']: relative[1] = 1e+300 at 10 N is outside [0.00437, 0.79]"),
    ("curve_relative=[0, 0.004]", "taxels.curves['27']: relative[1] = 0.004 at 10 N is outside [0.00437, 0.79]"),
    ("curve_relative=[0.5, 0.6]", "taxels.curves['27']: relative[0] = 0.5 at 0 N is outside [-0.005, 0.005]"),
    ("curve_relative=[-1e300, 1e300]", "taxels.curves['27']: relative[0] = -1e+300 at 0 N is outside [-0.005, "),
    ('curve_relative=["0", "0.1"]', "taxels.curves['27']: expected {force_N: [...], relative: [...]}"),
    ("curve_relative=[false, true]", "taxels.curves['27']: expected {force_N: [...], relative: [...]}"),
    ("created=1", "created: expected an ISO 8601 time as a string, got 1"),
    ('created={"x": 1}', "created: expected an ISO 8601 time as a string, got {'x': 1}"),
    ("created=[1]", "created: expected an ISO 8601 time as a string, got [1]"),
    ("created=null", "created: expected an ISO 8601 time as a string, got None"),  # registry: NOT NULL
    # a list was a TypeError (unhashable) and a traceback; {}, 0 and null were stored, the service's mounting used
    ('mounting=["flat"]', "mounting: ['flat'] is not one of flat, curved"),
    ("mounting=[1.0, 2.0]", "mounting: [1.0, 2.0] is not one of flat, curved"),
    ("mounting={}", "mounting: {} is not one of flat, curved"),
    ("mounting=0", "mounting: 0 is not one of flat, curved"),
    ("mounting=null", "mounting: None is not one of flat, curved"),
    # a standard error from 0 to the gain it is of (table 1's taxel 5: 0.95235): -1e150 read ~1 N ± 1e150 N,
    # 1e300 σ null (saturated) beside a number, unflagged; a string was taken as its number
    ("taxels.gain_se[5]=-1e150", "taxels.gain_se[5] = -1e+150 is outside [0, 0.9524], the taxel's gain"),
    ("taxels.gain_se[5]=1e300", "taxels.gain_se[5] = 1e+300 is outside [0, 0.9524], the taxel's gain"),
    ("taxels.gain_se[5]=-0.001", "taxels.gain_se[5] = -0.001 is outside [0, 0.9524], the taxel's gain"),
    ("taxels.gain_se[5]=0.96", "taxels.gain_se[5] = 0.96 is outside [0, 0.9524], the taxel's gain: a standard "
                               "error is not negative, nor past the value it is of (that is then undetermined)"),
    ('taxels.gain_se[5]="0.01"', "taxels.gain_se: expected a list of 64 numbers"),
    ('taxels.c0_pF[5]="10"', "taxels.c0_pF: expected a list of 64 numbers"),
    # a residual RMS from 0 to 471 N: 1e300 made σ null beside a number, -1e150 σ 1e150 N
    ("taxels.residual_rms_N[5]=1e300", "taxels.residual_rms_N[5] = 1e+300 is outside [0, 471] N"),
    ("taxels.residual_rms_N[5]=-0.5", "taxels.residual_rms_N[5] = -0.5 is outside [0, 471] N"),
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


def quad(**changes) -> dict:
    """A quad document the service can use (fits 34/35's numbers), with ``changes``."""
    from service.readings import SensorInfo
    from service.reconstruct.calibration_upload import upload_document

    fits = {"normal_fit": [-0.0009, 0.0343], "shear_fit": [0.0077, 0.0004]}
    document = upload_document(SensorInfo(1, "quad", 2, 2), fits, "flat", {"key": "sensor:Q-1"})
    return {**{k: v for k, v in document.items() if k != "id"}, **changes}


@pytest.mark.parametrize("changes, message", [
    ({"normal_fit_se": 5}, "normal_fit_se: expected the standard errors [c2, c1] of normal_fit, got 5"),
    ({"normal_fit_se": [1]}, "normal_fit_se: expected the standard errors [c2, c1] of normal_fit, got [1]"),
    ({"normal_fit_se": [1, "2"]}, "normal_fit_se: expected the standard errors [c2, c1] of normal_fit, got [1, '2']"),
    ({"shear_fit_se": {"a": 1}}, "shear_fit_se: expected the standard errors [a, b] of shear_fit, got {'a': 1}"),
    ({"coupling": [1]}, "coupling: expected a number, got [1]"),
    ({"coupling": {"c": 0.1}}, "coupling: expected a number, got {'c': 0.1}"),
    ({"coupling": True}, "coupling: expected a number, got True"),
    ({"statistics": "x"}, "statistics: expected an object, got 'x'"),
    ({"created": {"x": 1}}, "created: expected an ISO 8601 time as a string, got {'x': 1}"),
    # standard errors not negative, the slope's at most the slope (c1 0.0343, a 0.0077): 1e300 gave σ 3e301 N;
    # said as a grid taxel's gain_se is (one helper), naming the field, the value and what it is the error of
    ({"normal_fit_se": [0.0001, -0.0001]}, "normal_fit_se[1] = -0.0001 is outside [0, 0.0343], c1: a standard "
                                           "error is not negative"),
    ({"normal_fit_se": [0.0001, 1e300]}, "normal_fit_se[1] = 1e+300 is outside [0, 0.0343], c1: a standard error"),
    ({"normal_fit_se": [-1, 0.0001]}, "normal_fit_se[0] = -1 is outside [0, inf), c2: a standard error"),
    ({"shear_fit_se": [0.0078, 0.0]}, "shear_fit_se[0] = 0.0078 is outside [0, 0.0077], a: a standard error"),
    # a residual RMS at most the axis's usable force (0.9·c1/(2|c2|) = 17.15 N, 0.9·a/(2b) = 8.66 N), was 1e3 N
    ({"statistics": {"rms_N": {"x": 0.03, "y": 0.03, "z": 999}}},
     "statistics.rms_N.z: 999 is outside [0, 17.15] N, the axis's usable force"),
    ({"statistics": {"rms_N": {"x": 9, "y": 0.03, "z": 0.02}}},
     "statistics.rms_N.x: 9 is outside [0, 8.66"),
])
def test_a_quad_document_with_a_field_of_another_type_or_out_of_range_is_not_imported_and_named(tmp_path, capsys,
                                                                                                changes, message):
    """They raised TypeError, IndexError, AttributeError (a 500 from PUT) or failed inside SQLite; the
    ranges' were taken and gave absurd σ."""
    path = tmp_path / "q.json"
    path.write_text(json.dumps(quad(**changes)))
    registry = tmp_path / "r.sqlite3"
    assert main(["calibrations", "import", str(path), "--registry", str(registry)]) == 2
    assert f"{path}: not imported, the service could not use it: {message}" in capsys.readouterr().err


def test_values_at_the_ends_of_their_ranges_are_imported(tmp_path):
    """The ends of the ranges: taxel 5's gain_se at 0.9523 (table 1's gain 0.95235), a residual of 471 N,
    a curve just within its bounds, a quad's c1 standard error at c1 (0.0343) and Fz residual at its
    usable 17.15 N."""
    grid = usable()
    grid["taxels"]["gain_se"][5], grid["taxels"]["residual_rms_N"][5] = 0.9523, 470.9
    force = [0.25 * k for k in range(49)]  # a concave response the model cannot follow (test_calibration_errors)
    grid["taxels"]["curves"] = {"2": {"force_N": force, "relative": [0.02 * f - 0.0008 * f * f for f in force]},
                                "3": {"force_N": [0.0, 10.0], "relative": [0.004, 0.0044]}}
    edge = quad(normal_fit_se=[0.0, 0.0343], statistics={"rms_N": {"x": 8.6, "y": 0.0, "z": 17.1}})
    with reg.Registry(tmp_path / "r.sqlite3") as registry:
        for document in (grid, edge):
            path = tmp_path / "c.json"
            path.write_text(json.dumps(document))
            assert registry.import_(path) == reg.calibration_id(document)


def test_a_quad_document_with_its_standard_errors_gives_the_slopes_relative_errors():
    """normal_fit_se, shear_fit_se [se of each coefficient]: c1's and a's σ over c1 and a."""
    from service.reconstruct.sensor_calibration import from_document
    from service.readings import SensorInfo

    document = quad(normal_fit_se=[0.0001, 0.000686], shear_fit_se=[0.000231, 0.00001], coupling=0.0)
    calibration = from_document({**document, "id": "q"}, SensorInfo(1, "quad", 2, 2))
    assert calibration.quad_relative_se == pytest.approx((0.000686 / 0.0343, 0.000231 / 0.0077))  # 2 %, 3 %


def test_a_usable_document_imports_with_the_id_of_its_content(tmp_path):
    path = tmp_path / "c.json"
    path.write_text(json.dumps(usable()))
    with reg.Registry(tmp_path / "r.sqlite3") as registry:
        assert registry.import_(path) == reg.calibration_id(usable())


def test_a_document_that_is_not_json_names_the_field_that_is_not_a_number():
    with pytest.raises(ValueError, match=r"^statistics\.worst\[1\] = inf is not a JSON number"):
        reg.calibration_id({"statistics": {"worst": [0.1, float("inf")]}})
