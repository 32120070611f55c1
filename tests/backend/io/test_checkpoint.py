"""Checkpoints are data, keyed by everything that determines the result, and validated on load."""
from __future__ import annotations

import json
import math
import pickle
import shutil

import numpy as np
import pytest

from relief_bsdf.io.checkpoint import FORMAT, CheckpointStore, code_version, decode, encode, file_digest


def _value():
    return {"evaluations": {"1.0,0.0": 14.1, "1.25,0.3": float("nan"), "inf": float("inf")},
            "rows": np.arange(12.0).reshape(3, 4), "mask": np.array([True, False]), "label": "fit",
            "pair": (1, 2.5), "n": np.int64(7), "cplx": np.array([1 + 2j]), "none": None,
            (3, "a"): [1, {"x": np.float32(2.5)}]}


def _same(a, b) -> bool:
    if isinstance(a, np.ndarray):
        return isinstance(b, np.ndarray) and a.dtype == b.dtype and np.array_equal(a, b, equal_nan=a.dtype.kind == "f")
    if isinstance(a, float) and math.isnan(a):
        return isinstance(b, float) and math.isnan(b)
    if isinstance(a, dict):
        return isinstance(b, dict) and a.keys() == b.keys() and all(_same(a[k], b[k]) for k in a)
    if isinstance(a, (list, tuple)):
        return type(a) is type(b) and len(a) == len(b) and all(_same(x, y) for x, y in zip(a, b))
    return type(a) is type(b) and a == b


@pytest.mark.parametrize("suffix", [".json", ".npz"])
def test_round_trip_of_task_values(tmp_path, suffix):
    store = CheckpointStore(tmp_path / f"ck{suffix}", {"method": "microfacet", "seed": 3})
    assert store.load() == {}
    store.save(_value())
    assert _same(store.load(), _value())
    if suffix == ".json":       # strict JSON (no NaN literal): any JSON reader accepts it
        json.loads((tmp_path / "ck.json").read_text(), parse_constant=lambda c: pytest.fail(f"literal {c}"))


@pytest.mark.parametrize("suffix", [".json", ".npz"])
def test_a_checkpoint_copied_to_another_key_is_ignored_with_a_note(tmp_path, suffix, capsys):
    a = CheckpointStore(tmp_path / "a" / f"ck{suffix}", {"inputs": {"sample": "digest-A"}, "n": 1.49})
    a.save({"rms_before": 14.10})
    (tmp_path / "b").mkdir()
    shutil.copy(a.path, tmp_path / "b" / f"ck{suffix}")
    b = CheckpointStore(tmp_path / "b" / f"ck{suffix}", {"inputs": {"sample": "digest-A"}, "n": 1.60})
    assert b.load() == {}
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and str(b.path) in err[0] and "another run" in err[0]
    # the same key reads it back (the copy itself is fine)
    same = CheckpointStore(tmp_path / "b" / f"ck{suffix}", {"inputs": {"sample": "digest-A"}, "n": 1.49})
    assert same.load() == {"rms_before": 14.10}


def test_key_covers_code_version_and_input_content(tmp_path):
    f = tmp_path / "relief.npz"
    f.write_bytes(b"one")
    k1 = CheckpointStore(tmp_path / "c.json", {"relief": file_digest(f)}).digest
    f.write_bytes(b"two")
    k2 = CheckpointStore(tmp_path / "c.json", {"relief": file_digest(f)}).digest
    assert k1 != k2
    k3 = CheckpointStore(tmp_path / "c.json", {"relief": file_digest(f), "code_version": "0.0.0+other"}).digest
    assert k3 != k2 and "code_version" in CheckpointStore(tmp_path / "c.json", {}).key
    assert code_version() == code_version() and "+" in code_version()


def test_pickle_and_objects_are_never_loaded_or_saved(tmp_path, capsys):
    class Payload:
        def __reduce__(self):
            return (exec, ("open(%r, 'w').write('ran')" % str(tmp_path / "pwned"),))

    store = CheckpointStore(tmp_path / "ck.npz", {"k": 1})
    with pytest.raises(TypeError):
        store.save({"x": Payload()})
    with pytest.raises(TypeError):
        store.save({"x": np.array([Payload()], dtype=object)})
    # a planted pickle under the checkpoint's name, and an npz holding an object array
    (tmp_path / "ck.npz").write_bytes(pickle.dumps({"x": Payload()}))
    assert store.load() == {}
    np.savez(tmp_path / "ck.npz", allow_pickle=True, format=np.str_(FORMAT), key_digest=np.str_(store.digest),
             tree=np.str_('{"dict": [["x", {"array": "a0"}]]}'), a0=np.array([Payload()], dtype=object))
    assert store.load() == {}
    assert not (tmp_path / "pwned").exists()
    assert len(capsys.readouterr().err.strip().splitlines()) == 2


def test_malformed_trees_are_refused():
    for bad in ({"eval": "x"}, {"float": "1e999"}, {"array": {"dtype": "|O", "shape": [1], "b64": ""}},
                {"tuple": [1], "dict": []}):
        with pytest.raises(ValueError):
            decode(bad)
    assert decode(encode(float("-inf"))) == float("-inf")


def test_package_dataclasses_round_trip_others_are_refused(tmp_path):
    import dataclasses

    from relief_bsdf.bsdf.builder import TableCells
    cells = TableCells(values_per_sr=np.ones((2, 3, 4), np.float32), sigma_per_sr=np.zeros((2, 3, 4), np.float32),
                       specular_R=0.04, specular_T=0.9, lost=0.0, lost_detail={"escaped": 0.0}, outside_table=0.01)
    store = CheckpointStore(tmp_path / "ck.npz", {"k": 1})
    store.save({"result": cells})
    back = store.load()["result"]
    assert isinstance(back, TableCells) and back.specular_R == 0.04 and back.mueller_per_sr is None
    assert np.array_equal(back.values_per_sr, cells.values_per_sr) and back.values_per_sr.dtype == np.float32

    @dataclasses.dataclass
    class Foreign:
        x: int = 1
    with pytest.raises(TypeError):
        encode(Foreign())
    for name in ("os:system", "builtins:eval", "relief_bsdf.io.checkpoint:decode", "relief_bsdf.io.checkpoint:_x.y",
                 "relief_bsdf.cli.__main__:X"):      # importing it would run the command line
        with pytest.raises(ValueError):
            decode({"dataclass": [name, {}]})


def test_arrays_of_another_runs_npz_are_never_read(tmp_path, capsys):
    """Format and key are read first: a file of another run is set aside before its arrays are touched
    (here an object array, which reading would refuse)."""
    store = CheckpointStore(tmp_path / "ck.npz", {"k": 1})
    np.savez(tmp_path / "ck.npz", allow_pickle=True, format=np.str_(FORMAT), key_digest=np.str_("0" * 64),
             tree=np.str_('{"dict": []}'), a0=np.array([object()], dtype=object))
    assert store.load() == {}
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "belongs to another run" in err[0]
