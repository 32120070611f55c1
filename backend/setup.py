"""Build of the optional compiled ray kernels (`relief_bsdf.kernels._compiled`); the rest is pyproject.toml.

The extension is optional: without Cython or a C compiler the package installs as pure Python and
`relief_bsdf.kernels` uses numpy.  RELIEF_PURE_PYTHON=1 skips it altogether (the Blender extension's
py3-none-any backend wheel, relief_addon/build_extension.py).  `pip install -e backend` builds it in
place next to its source.
"""
import os

from setuptools import setup

ext_modules = []
if os.environ.get("RELIEF_PURE_PYTHON", "") not in ("1", "true", "yes"):
    try:
        from Cython.Build import cythonize
        from setuptools import Extension
    except ImportError:
        print("relief-bsdf: Cython not available: the ray kernels stay numpy")
    else:
        ext = Extension("relief_bsdf.kernels._compiled", ["src/relief_bsdf/kernels/_compiled.pyx"],
                        extra_compile_args=["-O3", "-ffp-contract=off", "-fno-tree-slp-vectorize", "-fno-math-errno",
                                            "-fno-trapping-math"], optional=True)
        ext_modules = cythonize([ext], language_level=3, quiet=True)

setup(ext_modules=ext_modules)
