"""The manual (docs/, mkdocs.yml): it names everything the file contract names, it documents every
option of every `relief` command, and it builds with `mkdocs build --strict` (broken links, broken
anchors and pages left out of the nav fail)."""
from __future__ import annotations

import argparse
import re
import subprocess
import sys
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[2]
DOCS = REPO / "docs"
CONTRACT = REPO.parent / "shared" / "formats.md"


def _sections(text: str) -> dict[str, str]:
    """Markdown text cut at its `## ` headings: {heading: body}."""
    parts = re.split(r"^## +(.+)$", text, flags=re.M)
    return {title.strip(): body for title, body in zip(parts[1::2], parts[2::2])}


def _section(sections: dict[str, str], words: str) -> str:
    hits = [body for title, body in sections.items() if words in title]
    assert len(hits) == 1, f"formats.md: expected one section titled with {words!r}, found {len(hits)}"
    return hits[0]


def contract_names(text: str) -> dict[str, set[str]]:
    """Every column, key, effect name, subcommand and flag the contract names, by kind."""
    sec = _sections(text)
    rec = _section(sec, "recording.csv")
    header = next(line.strip() for line in rec.splitlines() if line.strip().startswith("wavelength_nm,"))
    sample = _section(sec, "sample.toml")
    diag = _section(sec, "diagnosis.json")
    cli = _section(sec, "Command line")
    return {
        "recording.csv columns": set(header.split(",")),
        "sample.toml keys": set(re.findall(r"^\s*([a-z_]+)\s*=", sample, re.M))
        | set(re.findall(r"^\s*\[([a-z]+)\]", sample, re.M)),
        # diagnosis.json: its JSON keys, the keys named in its prose, the effect names and statuses
        "diagnosis.json keys and names": set(re.findall(r'"([a-z_]+)"\s*:', diag))
        | set(re.findall(r"`([a-z_]+)`", diag)),
        # relief info --json, fit.json, infer.json: the JSON keys written in the command-line section
        "info / fit.json / infer.json keys": set(re.findall(r'"([a-z_A-Z]+)"\s*:', cli)),
        "subcommands": set(re.findall(r"^\s{4}relief ([a-z][a-z-]*|--version)\b", cli, re.M)),
        "flags": set(re.findall(r"(?<![\w-])(--[a-z][a-z0-9-]*)", cli)),
    }


def _named(word: str, text: str) -> bool:
    return re.search(r"(?<![\w-])" + re.escape(word) + r"(?![\w-])", text) is not None


def test_contract_parser_finds_what_the_contract_names():
    """The parser on a contract-shaped text finds each kind of name (so an empty parse cannot pass)."""
    text = ("## Goniophotometer recording: `recording.csv`\n\n    a_nm,b_deg\n\n    wavelength_nm,side,bsdf_sr\n"
            "## Sample description: `sample.toml`\n\n    [plate]\n    thickness_mm = 2.0\n"
            "## Diagnosis result: `diagnosis.json`\n\n    {\"format\": 1, \"effects\": []}\nand `stop`.\n"
            "## Command line (stable)\n\n    relief info FILE [--json]\n        {\"kind\": \"relief\"}\n"
            "    relief --version\n")
    names = contract_names(text)
    assert names == {"recording.csv columns": {"wavelength_nm", "side", "bsdf_sr"},
                     "sample.toml keys": {"plate", "thickness_mm"},
                     "diagnosis.json keys and names": {"format", "effects", "stop"},
                     "info / fit.json / infer.json keys": {"kind"},
                     "subcommands": {"info", "--version"},
                     "flags": {"--json", "--version"}}


@pytest.mark.shared_data
def test_docs_name_every_key_and_column_of_the_contract():
    """Every column, key, effect name, subcommand and flag of ../shared/formats.md appears in
    docs/formats.md or docs/cli.md (subcommands and flags in docs/cli.md)."""
    names = contract_names(CONTRACT.read_text(encoding="utf-8"))
    assert len(names["recording.csv columns"]) == 8
    assert len(names["sample.toml keys"]) >= 15
    assert len(names["diagnosis.json keys and names"]) >= 30
    assert len(names["info / fit.json / infer.json keys"]) >= 20
    assert len(names["subcommands"]) >= 12
    cli = (DOCS / "cli.md").read_text(encoding="utf-8")
    both = (DOCS / "formats.md").read_text(encoding="utf-8") + cli
    missing = {kind: sorted(n for n in found if not _named(n, cli if kind in ("subcommands", "flags") else both))
               for kind, found in names.items()}
    missing["subcommands"] = sorted(c for c in names["subcommands"] if f"relief {c}" not in cli)
    assert not any(missing.values()), f"named by ../shared/formats.md, absent from the manual: {missing}"


def test_cli_page_documents_every_command_and_option():
    """Every `relief` subcommand has its section in docs/cli.md, and every option it takes appears in
    that section or in the conventions shared by every command."""
    from relief_bsdf.cli import build_parser
    sub = next(a for a in build_parser()._actions if isinstance(a, argparse._SubParsersAction))
    sec = _sections((DOCS / "cli.md").read_text(encoding="utf-8"))
    shared = sec["Conventions shared by every command"]
    missing = {}
    for name, parser in sub.choices.items():
        assert f"relief {name}" in sec, f"docs/cli.md has no section '## relief {name}'"
        opts = {o for a in parser._actions for o in a.option_strings if o.startswith("--") and o != "--help"}
        lost = sorted(o for o in opts if not _named(o, sec[f"relief {name}"] + shared))
        if lost:
            missing[name] = lost
    assert not missing, f"options not documented in docs/cli.md: {missing}"


def test_docs_build_strict(tmp_path):
    """`mkdocs build --strict` succeeds: no broken link or anchor, no page outside the nav."""
    r = subprocess.run([sys.executable, "-m", "mkdocs", "build", "--strict", "--config-file", str(REPO / "mkdocs.yml"),
                        "--site-dir", str(tmp_path / "site")], capture_output=True, text=True, timeout=120)
    assert r.returncode == 0, r.stderr[-3000:]
    for page in ("formats", "cli", "physics", "architecture", "blender", "validation", "performance"):
        assert (tmp_path / "site" / page / "index.html").is_file(), page
