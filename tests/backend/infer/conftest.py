"""Shared checks of the infer tests."""
from pathlib import Path

import numpy as np
import pytest


def check_export(out: Path, tmp_path: Path, fmt: str, side: str | None) -> None:
    """`relief export` of an inferred boundary (OUT/boundary.h5) in `fmt` works as for any table: rc 0, files
    written, a recording export finite and not all zero (the inside table is the relief's, not measured)."""
    from relief_bsdf.cli import main
    from relief_bsdf.io.recording import read_recording
    suffix = {"radiance-xml": ".xml", "is-bsdf": ".bsdf", "recording-csv": ".csv"}[fmt]
    target = tmp_path / f"inferred{suffix}"
    args = ["export", str(out / "boundary.h5"), "--format", fmt, "-o", str(target)] + (["--from", side] if side else [])
    assert main(args) == 0
    written = sorted(tmp_path.glob("inferred*"))
    assert written and all(p.stat().st_size > 1000 for p in written), written
    if fmt == "recording-csv":
        rec = read_recording(target)
        assert np.all(np.isfinite(rec.bsdf_sr)) and rec.bsdf_sr.max() > 0


@pytest.fixture
def export_check():
    return check_export
