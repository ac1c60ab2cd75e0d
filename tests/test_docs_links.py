"""Every relative link in README.md and docs/*.md names a file of the product
(docs/calibration.md sent readers to ../shared/protocol.md, which a clone
does not have), and every module a doc names exists (`service/….py`, or a
bare `name.py`: docs named runtime.py, select.py and taxel.py long after
they were gone)."""
import re
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
DOCS = [ROOT / "README.md", *sorted((ROOT / "docs").glob("*.md"))]
LINK = re.compile(r"\]\(([^)#\s]+)(?:#[^)]*)?\)")
MODULE = re.compile(r"`((?:service|firmware_sim|scripts|tests)/[\w/]+\.py)")
BARE = re.compile(r"`(\w+\.py)\b")  # a module named without its folder: some file of the product has that name
OUTSIDE = re.compile(r"`(\.\./[^`\s]+)`")  # a path above the doc's folder, as text


@pytest.mark.parametrize("doc", DOCS, ids=lambda p: p.name)
def test_relative_links_name_files_of_the_product(doc):
    targets = [t for t in LINK.findall(doc.read_text()) if not re.match(r"[a-z]+:", t)]
    missing = [t for t in targets if not (doc.parent / t).resolve().exists()]
    assert missing == []
    assert all((doc.parent / t).resolve().is_relative_to(ROOT) for t in targets)


@pytest.mark.parametrize("doc", DOCS, ids=lambda p: p.name)
def test_modules_and_paths_a_doc_names_exist(doc):
    text = doc.read_text()
    assert [m for m in MODULE.findall(text) if not (ROOT / m).exists()] == []
    names = {p.name for folder in ("service", "firmware_sim", "scripts", "tests") for p in (ROOT / folder).rglob("*.py")}
    assert [m for m in BARE.findall(text) if m not in names] == []
    inside = [(doc.parent / p).resolve() for p in OUTSIDE.findall(text)]
    assert [p for p in inside if not (p.is_relative_to(ROOT) and p.exists())] == []


def test_the_tests_the_code_names_exist():
    """A docstring sent readers to tests/test_sigma.py, which never existed."""
    named = {m for path in (ROOT / "service").rglob("*.py") for m in re.findall(r"tests/test_\w+\.py", path.read_text())}
    assert named and [m for m in sorted(named) if not (ROOT / m).exists()] == []
