"""Text a user reads speaks to the user: no internal issue numbers ("issue 8", "(issue 38)", "Issues 40, 41") in
`vslam presets`, the shipped presets and configs (their comments are read by whoever copies one), the README (its
bench results table included), the bench notes, targets and `open` reasons rendered into BENCHMARKS.md and that
table, the model cards (models/README.md), or the strings vslam prints (messages, warnings, report headings).
Code comments and docstrings may cite issues; they are not checked."""

import ast
import re
from pathlib import Path

import pytest
import yaml

import vslam
from vslam.cli import main
from vslam.resources import presets_dir

PACKAGE = Path(vslam.__file__).resolve().parent
REPO = PACKAGE.parent
ISSUE = re.compile(r"\b[Ii]ssues?[ -]#?\d+")


def _hits(text: str) -> list[str]:
    return [line.strip() for line in text.splitlines() if ISSUE.search(line)]


def test_presets_command_names_no_issue(capsys):
    assert main(["presets"]) == 0
    assert _hits(capsys.readouterr().out) == []


@pytest.mark.parametrize("folder", ["presets", "configs"])
def test_preset_and_config_files_name_no_issue(folder):
    d = presets_dir() if folder == "presets" else REPO / "configs"
    files = sorted(d.glob("*.yaml"))
    if folder == "configs" and not files:
        pytest.skip("no configs/ folder (installed package, not a checkout)")
    assert files
    found = {f.name: h for f in files if (h := _hits(f.read_text()))}
    assert found == {}


def test_readme_names_no_issue():
    readme = REPO / "README.md"
    if not readme.is_file():
        pytest.skip("no README.md (installed package, not a checkout)")
    # the results table between the bench-table markers (`vslam bench --render`, from configs/bench.yaml) included
    text = readme.read_text()
    assert "<!-- bench-table:start -->" in text
    assert _hits(text) == []


@pytest.mark.parametrize("name", ["models/README.md", "BENCHMARKS.md"])
def test_model_cards_and_benchmarks_name_no_issue(name):
    """The model cards, and BENCHMARKS.md as `vslam bench --render` wrote it (targets, `open` reasons, notes)."""
    path = REPO / name
    if not path.is_file():
        pytest.skip(f"no {name} (installed package, not a checkout)")
    assert _hits(path.read_text()) == []


def test_bench_notes_targets_and_open_reasons_name_no_issue():
    suite = REPO / "configs" / "bench.yaml"
    if not suite.is_file():
        pytest.skip("no configs/bench.yaml (installed package, not a checkout)")
    text = suite.read_text()
    rows = yaml.safe_load(text)["rows"]
    found = {r["name"]: r["note"] for r in rows if ISSUE.search(r.get("note") or "")}
    assert found == {}
    found = {r["name"]: r["target"] for r in rows if ISSUE.search(r.get("target") or "")}
    assert found == {}
    found = [(r["name"], c["metric"], c["open"]) for r in rows for c in r.get("check") or []
             if ISSUE.search(c.get("open") or "")]
    assert found == []
    assert _hits("\n".join(line for line in text.splitlines() if line.lstrip().startswith("#"))) == []


def _docstrings(tree: ast.AST) -> set[int]:
    out = set()
    for node in ast.walk(tree):
        if isinstance(node, (ast.Module, ast.ClassDef, ast.FunctionDef, ast.AsyncFunctionDef)) and node.body:
            first = node.body[0]
            if isinstance(first, ast.Expr) and isinstance(first.value, ast.Constant):
                out.add(id(first.value))
    return out


def test_printed_strings_name_no_issue():
    """Every string literal in vslam/ except docstrings (messages, warnings, help, report headings)."""
    found = []
    for path in sorted(PACKAGE.rglob("*.py")):
        tree = ast.parse(path.read_text(), str(path))
        docs = _docstrings(tree)
        found += [f"{path.relative_to(PACKAGE)}:{node.lineno}: {node.value[:80]!r}" for node in ast.walk(tree)
                  if isinstance(node, ast.Constant) and isinstance(node.value, str) and id(node) not in docs
                  and ISSUE.search(node.value)]
    assert found == []
