"""The layering contract (pyproject.toml [tool.importlinter], docs/architecture.md) holds, and the
checker would see a break: imports inside functions count, a reversed layer order is refused."""
from __future__ import annotations

from pathlib import Path

import pytest

importlinter_cli = pytest.importorskip("importlinter.cli", reason="import-linter (requirements/test.txt)")

REPO = Path(__file__).resolve().parents[2]


def _lint(config: Path) -> int:
    return importlinter_cli.lint_imports(config_filename=str(config), no_cache=True, no_logo=True)


def test_the_project_keeps_its_import_contract():
    assert _lint(REPO / "pyproject.toml") == 0


def test_a_function_local_import_breaks_a_contract(tmp_path):
    """`bake` imports methods.microfacet only inside a function: a contract forbidding it must fail."""
    cfg = tmp_path / "local.ini"
    cfg.write_text("[importlinter]\nroot_packages =\n    relief_bsdf\ninclude_external_packages = False\n\n"
                   "[importlinter:contract:local]\nname = bake without methods\ntype = forbidden\n"
                   "source_modules =\n    relief_bsdf.bake\nforbidden_modules =\n    relief_bsdf.methods\n")
    assert _lint(cfg) == 1


def test_a_reversed_layer_order_breaks_the_layers_contract(tmp_path):
    cfg = tmp_path / "reversed.ini"
    cfg.write_text("[importlinter]\nroot_packages =\n    relief_bsdf\ninclude_external_packages = False\n\n"
                   "[importlinter:contract:reversed]\nname = core above plate\ntype = layers\n"
                   "layers =\n    relief_bsdf.core\n    relief_bsdf.plate\n")
    assert _lint(cfg) == 1


def test_the_jobs_layer_is_imported_by_the_front_ends_only():
    """Below the front ends (cli, the add-on) no module imports `relief_bsdf.jobs`, directly or not."""
    import grimp
    g = grimp.build_graph("relief_bsdf", "relief_addon", include_external_packages=False, cache_dir=None)
    users = {m for m in g.find_downstream_modules("relief_bsdf.jobs", as_package=True)}
    assert users, "the front ends call the jobs"
    assert all(m.startswith(("relief_bsdf.cli", "relief_addon")) or m == "relief_bsdf" for m in users), sorted(users)
