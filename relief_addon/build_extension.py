"""Build the Blender extension zips (one per platform) with the backend and its wheels bundled.

    python relief_addon/build_extension.py --out dist [--platforms linux-x64,windows-x64,macos-arm64]
                                           [--cache build/wheels] [--offline]

Steps:
1. wheel of the backend (`backend/`, import name `relief_bsdf`), built locally;
2. the backend's runtime dependencies, i.e. the transitive closure of its requirements as
   installed in this environment, at the versions pinned in requirements/runtime.txt, minus
   what Blender ships (numpy; bpy itself).  Binary wheels for each target platform come from
   PyPI with `pip download --only-binary=:all: --platform ... --python-version 3.11 --no-deps`
   (Blender 4.2 to 5.0 embed Python 3.11); pure-Python packages that only publish an sdist are
   built into a py3-none-any wheel once.  Everything is cached under `--cache` (gitignored), so a
   second build is offline;
3. a staging folder with blender_manifest.toml (plus the `wheels` list and the chosen
   `platforms`) and the add-on's Python files;
4. Blender's own `blender_ext.py build --split-platforms` (runs under plain Python), then
   `blender_ext.py validate` on every zip;
5. `reader_report` on every zip: what it can read, checked by reading the demo X3P and an npz
   with the zip's own relief_bsdf (SurfaceTopography blocked where the zip has no wheel of it).
   Only a zip that reads its main inputs is reported "validated"; otherwise the build fails.

A package with no wheel for a platform is reported and left out of that platform's zip (the
feature needing it then fails there with a clear error; SurfaceTopography's instrument formats
fall back to the project's own readers (io/native_readers.py, io/native_instruments.py: X3P, GWY,
PLU, SDF, Zygo MetroPro .dat, Wyko .opd, NanoScope .di/.spm, ...); the report lists the suffixes
the zip's own relief_bsdf registers and the common instrument formats it still cannot read.
"""
from __future__ import annotations

import argparse
import json
import os
import re
import shutil
import subprocess
import sys
from importlib import metadata
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
ADDON_DIR = ROOT / "relief_addon"
PY_VERSION = "3.11"
NOT_BUNDLED = {"numpy", "bpy", "relief-bsdf"}   # Blender ships numpy (bpy 5.0.1 needs numpy < 2)

# pip --platform tags per Blender platform; pip expands each to the older compatible tags.
PLATFORM_TAGS = {
    "linux-x64": ["manylinux_2_28_x86_64", "manylinux2014_x86_64", "linux_x86_64"],
    "windows-x64": ["win_amd64"],
    "macos-arm64": ["macosx_14_0_arm64", "macosx_11_0_universal2"],
}


def _norm(name: str) -> str:
    return re.sub(r"[-_.]+", "-", name).lower()


def blender_ext_script() -> Path:
    """Blender's extension builder/validator inside the installed bpy module."""
    import importlib.util
    spec = importlib.util.find_spec("bpy")
    if spec is None or spec.origin is None:
        raise SystemExit("build_extension: the bpy module is not installed in this Python")
    hits = sorted(Path(spec.origin).parent.glob("*/scripts/addons_core/bl_pkg/cli/blender_ext.py"))
    if not hits:
        raise SystemExit("build_extension: blender_ext.py not found inside the bpy module")
    return hits[-1]


def pinned_versions() -> dict[str, str]:
    pins = {}
    for line in (ROOT / "requirements" / "runtime.txt").read_text().splitlines():
        line = line.split("#", 1)[0].strip()
        if "==" in line:
            name, ver = line.split("==", 1)
            pins[_norm(name)] = ver.strip()
    return pins


def dependency_closure(top: str = "relief-bsdf") -> dict[str, dict]:
    """{normalised name: {"name", "version", "pure"}} of every runtime dependency of `top`."""
    from packaging.requirements import Requirement
    pins = pinned_versions()
    out: dict[str, dict] = {}
    stack = [top]
    while stack:
        name = stack.pop()
        key = _norm(name)
        if key in out:
            continue
        dist = metadata.distribution(name)
        wheel_meta = dist.read_text("WHEEL") or ""
        out[key] = {"name": dist.metadata["Name"], "version": pins.get(key, dist.version),
                    "pure": "Root-Is-Purelib: true" in wheel_meta}
        for r in dist.requires or []:
            req = Requirement(r)
            if req.marker is not None and not req.marker.evaluate({"extra": ""}):
                continue
            stack.append(req.name)
    return {k: v for k, v in out.items() if k not in NOT_BUNDLED}


def _pip(*args: str, env: dict | None = None) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "pip", *args], capture_output=True, text=True, env=env)


def _wheel_name_key(path: Path) -> str:
    return _norm(path.name.split("-")[0])


def build_backend_wheel(cache: Path) -> Path:
    out = cache / "backend"
    shutil.rmtree(out, ignore_errors=True)
    out.mkdir(parents=True)
    # pure Python (py3-none-any): without the optional compiled ray kernels (backend/setup.py), which the
    # add-on's platforms would each need built; relief_bsdf.kernels falls back to numpy (the same tables)
    env = dict(os.environ, RELIEF_PURE_PYTHON="1")
    r = _pip("wheel", "--no-deps", "--no-build-isolation", "-w", str(out), str(ROOT / "backend"), env=env)
    if r.returncode != 0:
        r = _pip("wheel", "--no-deps", "-w", str(out), str(ROOT / "backend"), env=env)
    if r.returncode != 0:
        raise SystemExit(f"build_extension: building the backend wheel failed:\n{r.stderr[-2000:]}")
    wheels = sorted(out.glob("relief_bsdf-*.whl"))
    if not wheels:
        raise SystemExit("build_extension: the backend wheel was not produced")
    return wheels[-1]


def _find_cached(cache: Path, name: str, version: str, tags: list[str] | None) -> Path | None:
    stem = re.sub(r"[-_.]+", "_", name).lower()
    for w in cache.glob("*.whl"):
        parts = w.name[:-4].split("-")
        if re.sub(r"[-_.]+", "_", parts[0]).lower() != stem or parts[1] != version:
            continue
        plat = parts[-1]
        if plat == "any" or tags is None or _platform_matches(plat, tags):
            return w
    return None


def _platform_matches(wheel_plat: str, tags: list[str]) -> bool:
    fam = {"linux": ("manylinux", "linux"), "win": ("win_amd64",), "macosx": ("macosx",)}
    for p in wheel_plat.split("."):
        for t in tags:
            if t.startswith("manylinux") or t.startswith("linux"):
                if p.startswith(fam["linux"]) and p.endswith("x86_64"):
                    return True
            elif t == "win_amd64" and p == "win_amd64":
                return True
            elif t.startswith("macosx") and p.startswith("macosx") and (p.endswith("arm64") or p.endswith("universal2")):
                return True
    return False


def fetch_wheels(deps: dict[str, dict], platforms: list[str], cache: Path, offline: bool) -> tuple[list[Path], list[str]]:
    """Wheels for every dependency and platform (from the cache or PyPI); and what is missing."""
    cache.mkdir(parents=True, exist_ok=True)
    found: dict[str, Path] = {}
    missing = []
    for key, d in sorted(deps.items()):
        spec = f"{d['name']}=={d['version']}"
        pure_hit = _find_cached(cache, d["name"], d["version"], None)
        if pure_hit is not None and pure_hit.name.endswith("-any.whl"):
            found[pure_hit.name] = pure_hit
            continue
        for plat in platforms:
            tags = PLATFORM_TAGS[plat]
            hit = _find_cached(cache, d["name"], d["version"], tags)
            if hit is None and not offline:
                args = ["download", "--only-binary=:all:", "--no-deps", "--python-version", PY_VERSION,
                        "--implementation", "cp", "-d", str(cache), "--quiet"]
                for t in tags:
                    args += ["--platform", t]
                r = _pip(*args, spec)
                hit = _find_cached(cache, d["name"], d["version"], tags)
                if hit is None and d["pure"]:
                    # pure Python published as an sdist only: build the universal wheel once
                    _pip("wheel", "--no-deps", "-w", str(cache), "--quiet", spec)
                    hit = _find_cached(cache, d["name"], d["version"], None)
                if hit is None:
                    print(f"  no wheel of {spec} for {plat}: {r.stderr.strip().splitlines()[-1:]}", file=sys.stderr)
            if hit is None:
                missing.append(f"{spec} ({plat})")
                continue
            found[hit.name] = hit
            if hit.name.endswith("-any.whl"):
                break
    return sorted(found.values()), missing


def stage(stage_dir: Path, wheels: list[Path], platforms: list[str]) -> Path:
    """The extension's source folder: add-on modules, manifest with wheels, wheels/."""
    shutil.rmtree(stage_dir, ignore_errors=True)
    (stage_dir / "wheels").mkdir(parents=True)
    for p in ADDON_DIR.rglob("*"):
        rel = p.relative_to(ADDON_DIR)
        if "__pycache__" in rel.parts or p.name == "build_extension.py" or p.is_dir():
            continue
        dst = stage_dir / rel
        dst.parent.mkdir(parents=True, exist_ok=True)
        shutil.copy2(p, dst)
    for w in wheels:
        shutil.copy2(w, stage_dir / "wheels" / w.name)
    text = (ROOT / "blender_manifest.toml").read_text()
    text = re.sub(r"(?m)^platforms\s*=.*$", "platforms = " + json.dumps(platforms), text)
    if wheels:
        wheel_list = ",\n".join(f'  "./wheels/{w.name}"' for w in wheels)
        # `wheels` must be a top-level key: insert it before the first table header
        head, sep, tail = text.partition("\n[")
        text = head.rstrip() + f"\n\nwheels = [\n{wheel_list},\n]\n" + (sep + tail if sep else "")
    (stage_dir / "blender_manifest.toml").write_text(text)
    return stage_dir


def build(out: Path, platforms: list[str], cache: Path, offline: bool = False) -> list[Path]:
    for p in platforms:
        if p not in PLATFORM_TAGS:
            raise SystemExit(f"build_extension: unknown platform {p!r}; choose from {', '.join(PLATFORM_TAGS)}")
    ext = blender_ext_script()
    deps = dependency_closure()
    print(f"bundling {len(deps)} packages for {', '.join(platforms)} (numpy not bundled)")
    backend = build_backend_wheel(cache)
    wheels, missing = fetch_wheels(deps, platforms, cache / "pypi", offline)
    if missing:
        print("left out (no wheel): " + "; ".join(missing), file=sys.stderr)
    src = stage(cache.parent / "extension_stage", [backend, *wheels], platforms)
    out.mkdir(parents=True, exist_ok=True)
    for old in out.glob("relief_addon-*.zip"):
        old.unlink()
    r = subprocess.run([sys.executable, str(ext), "build", "--source-dir", str(src), "--output-dir", str(out),
                        "--split-platforms"], capture_output=True, text=True)
    if r.returncode != 0:
        raise SystemExit(f"build_extension: blender_ext build failed:\n{r.stdout[-3000:]}\n{r.stderr[-3000:]}")
    zips = sorted(out.glob("relief_addon-*.zip"))
    failed = []
    for z in zips:
        v = subprocess.run([sys.executable, str(ext), "validate", str(z)], capture_output=True, text=True)
        if v.returncode != 0:
            raise SystemExit(f"build_extension: {z.name} does not validate:\n{v.stdout}\n{v.stderr}")
        rep = reader_report(z, cache)
        size = f"{z.stat().st_size / 1e6:.1f} MB"
        if rep["main_ok"]:
            print(f"built and validated {z} ({size}): manifest valid; {rep['text']}")
        else:
            failed.append(z.name)
            print(f"built {z} ({size}), NOT validated: {rep['text']}", file=sys.stderr)
    if failed:
        raise SystemExit(f"build_extension: {', '.join(failed)} cannot read the main inputs (x3p, npz)")
    return zips


MAIN_INPUTS = ("x3p", "npz")
OWN_FORMATS = ("sdf", "npz")     # read by io.heightmaps itself; the rest come from the zip's io.native_readers.READERS
#: instrument formats a user is likely to bring (SurfaceTopography reads them all); the report names
#: those a zip without SurfaceTopography cannot read
COMMON_FORMATS = ("x3p", "gwy", "plu", "dat", "opd", "di", "spm", "nid", "mi", "frt", "ibw", "sur", "datx", "plux")


def _zip_wheels(z: Path) -> list[str]:
    import zipfile
    with zipfile.ZipFile(z) as zf:
        return [n.rsplit("/", 1)[-1] for n in zf.namelist() if n.endswith(".whl")]


def surface_topography_complete(wheel_names: list[str]) -> bool:
    """The wheels hold SurfaceTopography *and* every package it needs (muFFT, muGrid, ...: compiled
    ones may lack a wheel for a platform where SurfaceTopography has one); without them it cannot
    be imported there, and `io.native_readers` reads instead."""
    has = {_norm(w.split("-")[0]) for w in wheel_names}
    return "surfacetopography" in has and set(dependency_closure("SurfaceTopography")) <= has


def reader_report(z: Path, cache: Path) -> dict:
    """What the zip `z` can read, checked by reading files with its own bundled readers.

    The zip's relief_bsdf wheel is unpacked and, in a fresh Python (this one's numpy, scipy
    and h5py), reads the demo X3P and an npz with SurfaceTopography made unimportable when
    the zip bundles no wheel of it (what Blender on that platform will have).  Formats: the
    project's own (sdf, npz and the suffixes the zip's own `io.native_readers.READERS` registers:
    x3p, gwy, plu, dat, opd, di, ...), float tif/exr (Blender's own OpenImageIO), and every
    SurfaceTopography format when its wheel and those of all it needs are bundled
    (`surface_topography_complete`; the wheel of another platform cannot run here: this
    Python's SurfaceTopography stands in for it in the check).  main_ok: the main inputs
    (x3p, npz) read.
    """
    import zipfile
    wheels = _zip_wheels(z)
    backend = [w for w in wheels if w.startswith("relief_bsdf-")]
    if not backend:
        return {"main_ok": False, "formats": [], "text": "no relief_bsdf wheel in the zip: reads nothing"}
    unpack = cache.parent / "reader_check" / z.stem
    shutil.rmtree(unpack, ignore_errors=True)
    unpack.mkdir(parents=True)
    with zipfile.ZipFile(z) as zf:
        inner = next(n for n in zf.namelist() if n.endswith(backend[0]))
        (unpack / backend[0]).write_bytes(zf.read(inner))
    with zipfile.ZipFile(unpack / backend[0]) as wf:
        wf.extractall(unpack / "site")
    st = surface_topography_complete(wheels)
    code = ("import sys, numpy as np\n"
            + ("" if st else "sys.modules['SurfaceTopography'] = None\n")
            + f"sys.path.insert(0, {str(unpack / 'site')!r})\n"
            "from relief_bsdf.io.heightmaps import read_relief, write_relief\n"
            "from relief_bsdf.surface.relief import Relief\n"
            f"r = read_relief({str(ROOT / 'scenes' / 'demo' / 'relief.x3p')!r})\n"
            f"p = write_relief({str(unpack / 'probe.npz')!r}, Relief(np.zeros((4, 4)), 1e-6, 1e-6))\n"
            "read_relief(p)\n"
            "import relief_bsdf; assert relief_bsdf.__file__.startswith(sys.path[0]), relief_bsdf.__file__\n"
            "from relief_bsdf.io.native_readers import READERS\n"
            "print('OWN', ' '.join(sorted(k.lstrip('.') for k in READERS)))\n"
            "print('READ', r.metadata['reader'], r.shape)\n")
    res = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                         env={k: v for k, v in __import__("os").environ.items() if k != "PYTHONPATH"})
    ok = res.returncode == 0 and "READ" in res.stdout
    own = res.stdout.split("OWN", 1)[1].split("\n", 1)[0].split() if "OWN" in res.stdout else []
    formats = list(dict.fromkeys(own + list(OWN_FORMATS) + ["tif", "exr"]))  # tif/exr: Blender's OpenImageIO
    missing = [f for f in COMMON_FORMATS if f not in formats]
    text = (f"reads {', '.join(formats)}"
            + (" and every SurfaceTopography format (dat, plu, opd, di, nid, ibw, mi, frt, ...)" if st else
               " with its own readers (no SurfaceTopography for this platform: its wheel or one it needs is "
               "missing; " + (f"{', '.join(missing)} not available" if missing else
                              "every common instrument format covered") + ")")
            + (f"; checked: the demo X3P and an npz read with this zip's readers "
               f"({res.stdout.split('READ', 1)[1].strip()})"
               if ok else f"; FAILED to read the demo X3P / an npz with this zip's readers: "
                          f"{(res.stderr.strip().splitlines() or ['no output'])[-1]}"))
    return {"main_ok": ok, "formats": formats + (["surfacetopography"] if st else []), "text": text}


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--out", type=Path, default=ROOT / "dist")
    ap.add_argument("--platforms", default=",".join(PLATFORM_TAGS))
    ap.add_argument("--cache", type=Path, default=ROOT / "build" / "wheels")
    ap.add_argument("--offline", action="store_true", help="use cached wheels only")
    a = ap.parse_args(argv)
    build(a.out, [p for p in a.platforms.split(",") if p], a.cache.resolve(), a.offline)
    return 0


if __name__ == "__main__":
    sys.exit(main())
