"""Build of the optional compiled ray kernels (`relief_bsdf.kernels._compiled`); the rest is pyproject.toml.

The extension is optional: without Cython or a working C compiler the package installs as pure Python
and `relief_bsdf.kernels` uses numpy (the same tables).  RELIEF_PURE_PYTHON=1 skips it altogether (the
Blender extension's py3-none-any backend wheel, relief_addon/build_extension.py).  `pip install -e
backend` builds it in place next to its source.  The compiler flags keep the numbers those of numpy:
no fused multiply-add (-ffp-contract=off); -fno-math-errno and -fno-trapping-math change no value and
let gcc vectorise the loops; no SLP packing (kernels module doc).
"""
import os

from setuptools import setup
from setuptools.command.build_ext import build_ext

FLAGS = ["-O3", "-ffp-contract=off", "-fno-tree-slp-vectorize", "-fno-math-errno", "-fno-trapping-math"]


class OptionalBuildExt(build_ext):
    """build_ext that warns and goes on when an extension does not compile (numpy is then used); an
    extension not built is dropped from the outputs, which an editable or wheel build would copy."""

    def build_extensions(self):
        self._failed = set()
        super().build_extensions()
        self.extensions = [ext for ext in self.extensions if ext.name not in self._failed]

    def build_extension(self, ext):
        try:
            super().build_extension(ext)
        except Exception as exc:                  # no compiler, a failing one, missing headers
            self._failed.add(ext.name)
            print(f"relief-bsdf: {ext.name} not built ({exc}); the ray kernels stay numpy")


ext_modules = []
if os.environ.get("RELIEF_PURE_PYTHON", "") not in ("1", "true", "yes"):
    try:
        from Cython.Build import cythonize
        from setuptools import Extension
    except ImportError:
        print("relief-bsdf: Cython not available: the ray kernels stay numpy")
    else:
        ext = Extension("relief_bsdf.kernels._compiled", ["src/relief_bsdf/kernels/_compiled.pyx"],
                        extra_compile_args=FLAGS, optional=True)
        ext_modules = cythonize([ext], language_level=3, quiet=True)

setup(ext_modules=ext_modules, cmdclass={"build_ext": OptionalBuildExt})
