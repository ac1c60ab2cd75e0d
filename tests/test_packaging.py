"""What an install from a wheel needs besides the Python packages."""
import subprocess
import sys
import tomllib
from pathlib import Path

import pytest

from service.api.dashboard import find_web_dir

ROOT = Path(__file__).parents[1]


def test_every_dashboard_file_goes_into_the_wheel():
    config = tomllib.loads((ROOT / "pyproject.toml").read_text())
    shipped = config["tool"]["setuptools"]["data-files"]["share/tactile/web"]
    assert sorted(shipped) == sorted(f"web/{path.name}" for path in (ROOT / "web").iterdir() if path.is_file())


def test_the_dashboard_is_found_where_a_wheel_installs_it(tmp_path):
    installed = tmp_path / "share" / "tactile" / "web"
    installed.mkdir(parents=True)
    (installed / "index.html").write_text("<html></html>")
    assert find_web_dir([tmp_path / "checkout" / "web", installed]) == installed


def test_missing_dashboard_files_name_where_they_were_looked_for(tmp_path):
    with pytest.raises(RuntimeError, match="checkout"):
        find_web_dir([tmp_path / "checkout" / "web"])


def test_importing_the_api_looks_for_no_dashboard_files():
    # In a fresh interpreter where no index.html exists anywhere: the import
    # succeeds without asking (nor importing the service's module); only
    # create_app looks, and says where it did.
    code = """
import pathlib
asked = []
real_is_file = pathlib.Path.is_file
def is_file(self):
    if self.name == "index.html":
        asked.append(str(self))
        return False
    return real_is_file(self)
pathlib.Path.is_file = is_file
import sys
import service.api.app
assert asked == [], asked
assert "service.live_service" not in sys.modules  # the service, for type hints only
from service.live_service import TactileService
try:
    service.api.app.create_app(TactileService("sim://"))
except RuntimeError as exc:
    print(len(asked), exc)
"""
    result = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=60)
    assert result.returncode == 0, result.stderr
    assert result.stdout.startswith("3 the dashboard's files are in none of ") and "reinstall tactile" in result.stdout


def test_create_app_fails_clearly_without_the_dashboard(tmp_path, monkeypatch):
    from service.api import app, dashboard
    from service.live_service import TactileService

    monkeypatch.setattr(dashboard, "web_dir_candidates", lambda: [tmp_path / "nowhere" / "web"])
    with pytest.raises(RuntimeError, match="nowhere"):
        app.create_app(TactileService("sim://"))


def test_a_replay_starts_without_scipy_the_model_builder_or_pandas(tmp_path):
    # Start-up is most of a short replay's time: scipy.sparse (pulled in by the
    # Ritz model that builds the tables) took 0.3 s of it, pandas (which
    # pyarrow.array imports) 0.26 s of a Parquet export.
    from firmware_sim.board import BoardConfig, capture
    from firmware_sim.urlhandler.protocol_sim import parse_sensors

    raw = tmp_path / "tiny.bin"
    raw.write_bytes(capture(BoardConfig(sensors=parse_sensors("grid,quad")), 0.3)[0])
    for suffix in ("jsonl", "parquet"):
        code = f"""
import sys
from service.cli import main
code = main(["replay", "--raw", {str(raw)!r}, "--export", {str(tmp_path / ("out." + suffix))!r}])
print(code, sorted(m for m in sys.modules if m.startswith(("scipy", "service.physics.ritz", "service.physics.tables",
                                                           "pandas"))))
"""
        result = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=60)
        assert result.returncode == 0, result.stderr
        assert result.stdout.splitlines()[-1] == "0 []"
    assert (tmp_path / "out.jsonl").read_bytes().count(b"\n") > 200
    import pyarrow.parquet as pq

    assert pq.read_table(tmp_path / "out.parquet").num_rows == (tmp_path / "out.jsonl").read_bytes().count(b"\n")
