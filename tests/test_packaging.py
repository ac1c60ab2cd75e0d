"""What an install from a wheel needs besides the Python packages."""
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
