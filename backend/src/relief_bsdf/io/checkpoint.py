"""Checkpoints that are data, never code, and are only reused by the run they belong to.

A checkpoint lets a killed run resume.  Two things must never happen: a checkpoint of a
*different* run (another sample, an edited refractive index, another method, seed, grid or
code version) silently standing in for this run's result, and a file planted in the
checkpoint folder running code when it is loaded.  So:

- every checkpoint is **keyed** by a digest (SHA-256) of a JSON document of everything that
  determines its result: the inputs' content digests (`file_digest`), the method, its
  options, the seed, the grid, and the code version (`code_version`, added by the store);
  the key is stored in the file and compared on load; a mismatch (a checkpoint copied from
  another run) is ignored with a one-line note on stderr and the work is done again;
- a checkpoint holds **data only**: JSON (`.json`) or a numpy archive read with
  ``allow_pickle=False`` (`.npz`), with a small tagged encoding (`encode` / `decode`) for
  the values tasks return: None, bool, int, float (NaN and infinities too, the JSON stays
  strict), str, list, tuple, dict (any of these as keys), numeric / boolean / string numpy
  arrays and scalars, and the package's own dataclasses (`relief_bsdf.*`, e.g. a task's
  `TableCells`: stored as their fields, rebuilt only if the named class is a dataclass of
  this package).  Anything else (another object, an object array) is refused when saving
  (`TypeError`): nothing is ever unpickled, and no callable but a relief_bsdf dataclass's
  constructor is ever looked up by name;
- a file that does not parse or does not follow the layout is ignored with a note, never
  trusted; writes are atomic (`relief_bsdf.io.atomic`).

API (the fit's and the diagnosis' checkpoints, `parallel.map_tasks`' per-task ones)::

    store = CheckpointStore(out / "checkpoint.json", {"inputs": {...digests...}, "method": m, "seed": s})
    state = store.load()          # {} when absent, of another run, or damaged (with a note)
    ...
    store.save({"evaluations": cache})      # atomically; a dict of encodable values

Format of a `.json` checkpoint: ``{"format": "relief-checkpoint/1", "key_digest": hex,
"key": {...}, "data": <encoded tree>}``; of a `.npz` one: the entries ``format``,
``key_digest``, ``key`` (JSON text), ``tree`` (JSON text of the encoded tree) and one entry
``a<N>`` per array the tree refers to.
"""
from __future__ import annotations

import base64
import dataclasses
import functools
import importlib
import hashlib
import io
import json
import math
import sys
from pathlib import Path
from typing import Any, Callable

import numpy as np

FORMAT = "relief-checkpoint/1"
_ARRAY_KINDS = "biufcUS"          # bool, ints, floats, complex, str, bytes; never "O" (objects) or "V"


# ---------------------------------------------------------------------------------------------
# keys

def file_digest(path: str | Path, chunk: int = 1 << 20) -> str:
    """SHA-256 of a file's content (hex): the part of a checkpoint key that stands for an input file."""
    h = hashlib.sha256()
    with open(path, "rb") as f:
        for block in iter(lambda: f.read(chunk), b""):
            h.update(block)
    return h.hexdigest()


def input_digests(**paths: str | Path) -> dict[str, str]:
    """{name: file_digest(path)} for the input files of a run (the "inputs" part of a key), e.g.
    ``input_digests(sample=s.path, relief=s.relief_path, recording=s.recording_path)``."""
    return {name: file_digest(p) for name, p in sorted(paths.items())}


@functools.lru_cache(maxsize=1)
def code_version() -> str:
    """The package version plus a digest of its source files (an edited checkout is another code version)."""
    import relief_bsdf
    root = Path(relief_bsdf.__file__).parent
    h = hashlib.sha256()
    for p in sorted(root.rglob("*.py")):
        h.update(p.relative_to(root).as_posix().encode() + b"\0")
        h.update(p.read_bytes())
    return f"{relief_bsdf.__version__}+{h.hexdigest()[:16]}"


def key_digest(key: dict) -> str:
    """SHA-256 (hex) of the canonical JSON of an encoded key document."""
    text = json.dumps(encode(key), sort_keys=True, separators=(",", ":"), allow_nan=False)
    return hashlib.sha256(text.encode()).hexdigest()


# ---------------------------------------------------------------------------------------------
# the data-only encoding

def encode(value: Any, arrays: dict[str, np.ndarray] | None = None) -> Any:
    """A JSON-able tree for `value` (see the module doc for the types).

    With `arrays` (a dict), numpy arrays go there as entries ``a<N>`` and the tree refers to
    them (the `.npz` layout); without it they are inlined as base64 of their bytes.
    """
    if value is None or isinstance(value, (bool, str)):
        return value
    if isinstance(value, int):
        return value
    if isinstance(value, float):
        if math.isfinite(value):
            return float(value)
        return {"float": "nan" if math.isnan(value) else ("inf" if value > 0 else "-inf")}
    if isinstance(value, list):
        return [encode(v, arrays) for v in value]
    if isinstance(value, tuple):
        return {"tuple": [encode(v, arrays) for v in value]}
    if isinstance(value, dict):
        return {"dict": [[encode(k, arrays), encode(v, arrays)] for k, v in value.items()]}
    if isinstance(value, np.generic):
        return {"scalar": _array_node(np.asarray(value), arrays)}
    if isinstance(value, np.ndarray):
        return {"array": _array_node(value, arrays)}
    cls = type(value)
    if dataclasses.is_dataclass(value) and cls.__module__.startswith("relief_bsdf.") and "<" not in cls.__qualname__:
        fields = {f.name: encode(getattr(value, f.name), arrays) for f in dataclasses.fields(value)}
        return {"dataclass": [f"{cls.__module__}:{cls.__qualname__}", fields]}
    raise TypeError(f"a checkpoint holds data only; cannot store a {type(value).__module__}.{type(value).__name__}")


def _array_node(a: np.ndarray, arrays: dict | None) -> Any:
    if a.dtype.kind not in _ARRAY_KINDS:
        raise TypeError(f"a checkpoint holds data only; cannot store an array of dtype {a.dtype}")
    if arrays is not None:
        name = f"a{len(arrays)}"
        arrays[name] = a
        return name
    a = np.ascontiguousarray(a)
    return {"dtype": a.dtype.str, "shape": list(a.shape), "b64": base64.b64encode(a.tobytes()).decode("ascii")}


def decode(tree: Any, arrays: Any = None) -> Any:
    """The value an `encode` tree stands for; ValueError on anything that is not such a tree."""
    if tree is None or isinstance(tree, (bool, int, float, str)):
        return tree
    if isinstance(tree, list):
        return [decode(v, arrays) for v in tree]
    if not isinstance(tree, dict) or len(tree) != 1:
        raise ValueError(f"not a checkpoint value: {str(tree)[:60]}")
    (tag, body), = tree.items()
    if tag == "float" and body in ("nan", "inf", "-inf"):
        return float(body)
    if tag == "tuple" and isinstance(body, list):
        return tuple(decode(v, arrays) for v in body)
    if tag == "dict" and isinstance(body, list):
        out = {}
        for pair in body:
            if not (isinstance(pair, list) and len(pair) == 2):
                raise ValueError("malformed dict entry")
            k = decode(pair[0], arrays)
            out[k if not isinstance(k, list) else tuple(k)] = decode(pair[1], arrays)
        return out
    if tag == "dataclass" and isinstance(body, list) and len(body) == 2 and isinstance(body[1], dict):
        return _dataclass_from(str(body[0]), {str(k): decode(v, arrays) for k, v in body[1].items()})
    if tag in ("array", "scalar"):
        a = _array_from(body, arrays)
        return a if tag == "array" else a.reshape(())[()]
    raise ValueError(f"unknown checkpoint tag {tag!r}")


def _dataclass_from(name: str, values: dict) -> Any:
    """Rebuild a relief_bsdf dataclass; refuse anything else (no other name is ever resolved)."""
    module, _, qualname = name.partition(":")
    if not module.startswith("relief_bsdf.") or not qualname or not all(p.isidentifier() for p in qualname.split(".")):
        raise ValueError(f"{name!r} is not a relief_bsdf data class")
    if "__main__" in module.split("."):     # importing an entry point runs the command line: never
        raise ValueError(f"{name!r}: {module} is an entry point, not a module of data classes")
    try:
        obj: Any = importlib.import_module(module)
        for part in qualname.split("."):
            obj = getattr(obj, part)
    except (ImportError, AttributeError) as e:
        raise ValueError(f"{name!r}: {e}") from None
    if not (isinstance(obj, type) and dataclasses.is_dataclass(obj)):
        raise ValueError(f"{name!r} is not a data class")
    fields = {f.name: f for f in dataclasses.fields(obj)}
    if set(values) != set(fields):
        raise ValueError(f"{name}: fields {sorted(values)} do not match {sorted(fields)}")
    out = obj(**{k: v for k, v in values.items() if fields[k].init})
    for k, v in values.items():
        if not fields[k].init:
            object.__setattr__(out, k, v)
    return out


def _array_from(body: Any, arrays: Any) -> np.ndarray:
    if isinstance(body, str):
        if arrays is None or body not in arrays:
            raise ValueError(f"array {body!r} missing")
        a = np.asarray(arrays[body])
    elif isinstance(body, dict) and set(body) == {"dtype", "shape", "b64"}:
        dt = np.dtype(str(body["dtype"]))
        if dt.kind not in _ARRAY_KINDS:
            raise ValueError(f"array of dtype {dt} is not data")
        shape = tuple(int(s) for s in body["shape"])
        a = np.frombuffer(base64.b64decode(body["b64"], validate=True), dtype=dt).reshape(shape).copy()
    else:
        raise ValueError("malformed array entry")
    if a.dtype.kind not in _ARRAY_KINDS:
        raise ValueError(f"array of dtype {a.dtype} is not data")
    return a


# ---------------------------------------------------------------------------------------------
# one checkpoint file

def _note(message: str) -> None:
    print(f"relief: note: {message}", file=sys.stderr)


class CheckpointStore:
    """One checkpoint file bound to the key of the run that may use it.

    path: ``.json`` (text; arrays inlined) or ``.npz`` (arrays stored natively); the suffix decides.
    key: a dict (encodable, see `encode`) of everything that determines the result; the store
        adds ``code_version`` unless the key already has one.  Two runs share a checkpoint only
        when their keys are equal.
    note: where the one-line notes go (default: stderr, prefixed ``relief: note:``).
    """

    def __init__(self, path: str | Path, key: dict, note: Callable[[str], None] | None = None):
        self.path = Path(path)
        if self.path.suffix.lower() not in (".json", ".npz"):
            raise ValueError(f"{self.path}: a checkpoint is a .json or .npz file")
        self.key = dict(key)
        self.key.setdefault("code_version", code_version())
        self.digest = key_digest(self.key)
        self._note = note or _note

    def load(self) -> dict:
        """The saved dict when the file exists, parses, and belongs to this key; else {} (with a note
        saying why, unless the file is simply absent)."""
        if not self.path.exists():
            return {}
        try:
            digest, data = self._read()
        except Exception as e:  # noqa: BLE001 - any damage: the checkpoint is ignored, never trusted
            self._note(f"ignored checkpoint {self.path}: not a readable {FORMAT} file ({type(e).__name__}: "
                       f"{str(e)[:120]}); starting afresh")
            return {}
        if digest != self.digest:
            self._note(f"ignored checkpoint {self.path}: it belongs to another run (inputs, options, seed, "
                       f"grid or code version differ); starting afresh")
            return {}
        return data

    def ignore(self, why: str) -> dict:
        """For a user of the store that finds the loaded content unfit (`why`): one note, and {} (start afresh)."""
        self._note(f"ignored checkpoint {self.path}: {why}; starting afresh")
        return {}

    def _read(self) -> tuple[str, dict]:
        if self.path.suffix.lower() == ".json":
            doc = json.loads(self.path.read_text(encoding="utf-8"))
            if not isinstance(doc, dict) or doc.get("format") != FORMAT:
                raise ValueError(f"format is not {FORMAT!r}")
            digest, data = str(doc.get("key_digest")), decode(doc.get("data"))
        else:
            with np.load(self.path, allow_pickle=False) as z:
                # format and key first: the (possibly large) arrays of another run's file are never read
                if "format" not in z.files or str(z["format"]) != FORMAT:
                    raise ValueError(f"format is not {FORMAT!r}")
                digest = str(z["key_digest"])
                if digest != self.digest:
                    return digest, {}
                entries = {k: z[k] for k in z.files}
            data = decode(json.loads(str(entries["tree"])), entries)
        if not isinstance(data, dict):
            raise ValueError("the saved value is not a dict")
        return digest, data

    def save(self, data: dict) -> Path:
        """Write `data` (a dict of encodable values) atomically under this store's key."""
        from relief_bsdf.io.atomic import write_bytes_atomic, write_text_atomic
        if not isinstance(data, dict):
            raise TypeError("a checkpoint saves a dict")
        if self.path.suffix.lower() == ".json":
            doc = {"format": FORMAT, "key_digest": self.digest, "key": encode(self.key), "data": encode(data)}
            return write_text_atomic(self.path, json.dumps(doc, allow_nan=False) + "\n")
        arrays: dict[str, np.ndarray] = {}
        tree = encode(data, arrays)
        buf = io.BytesIO()
        np.savez(buf, format=np.str_(FORMAT), key_digest=np.str_(self.digest),
                 key=np.str_(json.dumps(encode(self.key), allow_nan=False)),
                 tree=np.str_(json.dumps(tree, allow_nan=False)), **arrays)
        return write_bytes_atomic(self.path, buf.getvalue())
