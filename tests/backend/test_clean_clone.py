"""A clone of the repository alone passes its tests: the instrument files are in the repository with
their source and licence, the tests that need ../shared are marked and left out by name where it is
absent, and LICENSE is the licence the manifests declare."""
from __future__ import annotations

import re
import shutil
import subprocess
import sys
import tomllib
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[2]
DATA = REPO / "tests" / "data" / "topography"
SHARED_TOPOGRAPHY = REPO.parent / "shared" / "data" / "topography"


@pytest.mark.shared_data
def test_instrument_files_are_byte_identical_copies_of_shared():
    """Every file of ../shared/data/topography is in tests/data/topography, byte for byte."""
    names = sorted(p.name for p in SHARED_TOPOGRAPHY.iterdir() if p.is_file())
    assert "ST_x3p-2.x3p" in names
    for name in names:
        assert (DATA / name).read_bytes() == (SHARED_TOPOGRAPHY / name).read_bytes(), name


def test_instrument_files_name_their_source_licence_and_reference():
    """SOURCE.md names the upstream repository, commit and the MIT licence text; every instrument file
    has its row of reference figures in README.md."""
    source = (DATA / "SOURCE.md").read_text(encoding="utf-8")
    assert "ContactEngineering/SurfaceTopography" in source
    assert re.search(r"\b[0-9a-f]{40}\b", source)
    assert "MIT licence" in source and "Permission is hereby granted, free of charge" in source
    table = (DATA / "README.md").read_text(encoding="utf-8")
    files = sorted(p.name for p in DATA.glob("ST_*"))
    assert len(files) == 10
    assert [f for f in files if f"| {f} |" not in table] == []


def _mini_repo(root: Path, with_shared: bool) -> Path:
    """root/repo with the suite's tests/conftest.py, one test marked shared_data and one not;
    root/shared beside it when `with_shared`."""
    tests = root / "repo" / "tests"
    tests.mkdir(parents=True)
    shutil.copy(REPO / "tests" / "conftest.py", tests / "conftest.py")
    (root / "repo" / "pytest.ini").write_text("[pytest]\nmarkers =\n    shared_data: reads ../shared\n")
    (tests / "test_mini.py").write_text(
        "import pytest\n\n"
        "def test_alone():\n    assert True\n\n"
        "@pytest.mark.shared_data\n"
        "def test_needs_shared():\n    assert True\n")
    if with_shared:
        (root / "shared").mkdir()
    return root / "repo"


def _run(repo: Path, workers: list[str]) -> str:
    r = subprocess.run([sys.executable, "-m", "pytest", "-p", "no:cacheprovider", "-q", "--strict-markers",
                        *workers, "tests"], cwd=repo, capture_output=True, text=True, timeout=120)
    assert r.returncode == 0, r.stdout[-2000:] + r.stderr[-2000:]
    return r.stdout


# in one process, and on two pytest-xdist workers as `make test-fast` runs (the workers report to the controller)
WORKERS = [pytest.param(["-p", "no:xdist"], id="one-process"), pytest.param(["-n", "2"], id="xdist")]


@pytest.mark.parametrize("workers", WORKERS)
def test_shared_data_tests_are_left_out_and_named_where_shared_is_absent(tmp_path, workers):
    out = _run(_mini_repo(tmp_path, with_shared=False), workers)
    assert re.search(r"^1 passed", out, re.M), out
    lines = [line for line in out.splitlines() if line.startswith("shared_data:")]
    assert len(lines) == 1 and "tests/test_mini.py::test_needs_shared" in lines[0], out
    assert "test_alone" not in lines[0]


@pytest.mark.parametrize("workers", WORKERS)
def test_shared_data_tests_run_where_shared_is_present(tmp_path, workers):
    out = _run(_mini_repo(tmp_path, with_shared=True), workers)
    assert "2 passed" in out and "deselected" not in out
    assert not any(line.startswith("shared_data:") for line in out.splitlines()), out


def test_licence_file_is_the_licence_the_manifests_declare():
    """backend/pyproject.toml and blender_manifest.toml declare GPL-3.0-or-later; LICENSE holds the GPL 3 text."""
    backend = tomllib.loads((REPO / "backend" / "pyproject.toml").read_text(encoding="utf-8"))
    blender = tomllib.loads((REPO / "blender_manifest.toml").read_text(encoding="utf-8"))
    assert backend["project"]["license"] == {"text": "GPL-3.0-or-later"}
    assert blender["license"] == ["SPDX:GPL-3.0-or-later"]
    text = (REPO / "LICENSE").read_text(encoding="utf-8")
    assert text.split()[:5] == ["GNU", "GENERAL", "PUBLIC", "LICENSE", "Version"]
    assert "Version 3, 29 June 2007" in text and "END OF TERMS AND CONDITIONS" in text
