"""The documentation: the results page matches its source, the site builds with warnings as errors, and the
front-facing text carries no commit hashes, work-round numbers or issue numbers."""

import ast
import importlib.util
import io
import json
import os
import re
import subprocess
import sys
import tokenize
from pathlib import Path

import pytest
from conftest import import_script

ROOT = Path(__file__).resolve().parents[1]

#: A commit hash: 7-40 lowercase hex digits with at least one digit and one letter, not part of a longer word, a
#: colour literal (``#1f77b4``) or a hex number (``0x...``).
HASH = re.compile(r"(?<![#\w])(?<!0x)(?=[0-9a-f]*[0-9])(?=[0-9a-f]*[a-f])[0-9a-f]{7,40}(?!\w)")
STOP = re.compile(r"\b[Ss]tops? \d+\b")
ISSUE = re.compile(r"\b[Ii]ssues? #?\d+\b")


def _findings(text: str) -> list[str]:
    return [m.group(0) for pattern in (HASH, STOP, ISSUE) for m in pattern.finditer(text)]


def _prose_of_python(path: Path) -> list[tuple[int, str]]:
    """``(line, text)`` of every comment and docstring in the Python file ``path``."""
    source = path.read_text(encoding="utf-8")
    out = [(tok.start[0], tok.string) for tok in tokenize.generate_tokens(io.StringIO(source).readline)
           if tok.type == tokenize.COMMENT]
    for node in ast.walk(ast.parse(source)):
        if isinstance(node, (ast.Module, ast.ClassDef, ast.FunctionDef, ast.AsyncFunctionDef)) and node.body:
            first = node.body[0]
            if isinstance(first, ast.Expr) and isinstance(first.value, ast.Constant) and isinstance(first.value.value,
                                                                                                 str):
                out.append((first.lineno, first.value.value))
    return out


def test_the_patterns_catch_what_they_are_for_and_spare_colours_and_numbers():
    assert _findings("fixed at `5eedff7` in stop 44 (issue 13)") == ["5eedff7", "stop 44", "issue 13"]
    assert _findings("colour #1f77b4, mask 0xdeadbeef12, 1e-10 m, 10000 seeds, the word effaced, seed 1639205032") == []


def test_front_facing_docs_and_package_prose_carry_no_hashes_stops_or_issue_numbers():
    found = []
    pages = [ROOT / "README.md", ROOT / "CHANGELOG.md",
             *(p for p in (ROOT / "docs").rglob("*.md") if "notes" not in p.relative_to(ROOT / "docs").parts)]
    for page in pages:
        for number, line in enumerate(page.read_text(encoding="utf-8").splitlines(), 1):
            found += [f"{page.relative_to(ROOT)}:{number}: {hit}" for hit in _findings(line)]
    for module in sorted((ROOT / "suture_gym").rglob("*.py")):
        for number, text in _prose_of_python(module):
            found += [f"{module.relative_to(ROOT)}:{number}: {hit}" for hit in _findings(text)]
    assert not found, "\n".join(found)


def test_readme_is_a_front_door_under_250_lines():
    lines = (ROOT / "README.md").read_text(encoding="utf-8").splitlines()
    assert len(lines) < 250, len(lines)


def test_results_page_is_what_the_generator_writes_from_results_json(monkeypatch):
    results_page = import_script(monkeypatch, "results_page")
    doc = json.loads((ROOT / "docs" / "results.json").read_text(encoding="utf-8"))
    assert (ROOT / "docs" / "results.md").read_text(encoding="utf-8") == results_page.render(doc)


def test_results_page_refuses_a_result_without_a_field(monkeypatch):
    results_page = import_script(monkeypatch, "results_page")
    doc = json.loads((ROOT / "docs" / "results.json").read_text(encoding="utf-8"))
    del doc["results"][0]["oracle"]
    with pytest.raises(ValueError, match=r"results\[0\] lacks \['oracle'\]"):
        results_page.render(doc)


def test_an_env_docstring_becomes_a_markdown_page_with_a_table(monkeypatch):
    docs_pages = import_script(monkeypatch, "docs_pages")
    text = ("``X-v0``: A toy.\n\nRewards\n-------\nThe sum:\n* ``a``: one.\n* ``b``: two.\nAfter.\n\n"
            "=====  ====  ===========\nindex  name  description\n=====  ====  ===========\n0      p     a b | c\n"
            "=====  ====  ===========\n")
    page = docs_pages.env_page("X-v0", text)
    assert page.startswith("# `X-v0`\n\nA toy.\n\n## Rewards\n\nThe sum:\n\n* ``a``: one.\n* ``b``: two.\n\nAfter.")
    assert "| index | name | description |\n| --- | --- | --- |\n| 0 | p | a b \\| c |" in page


@pytest.mark.skipif(not all(importlib.util.find_spec(m) for m in ("mkdocs", "material", "mkdocstrings",
                                                                    "mkdocs_gen_files")),
                    reason="the docs extra is not installed (pip install '.[docs]')")
def test_the_documentation_site_builds_with_warnings_as_errors(tmp_path):
    env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(ROOT), os.environ.get("PYTHONPATH", "")]),
           "DISABLE_MKDOCS_2_WARNING": "true", "NO_MKDOCS_2_WARNING": "1"}
    result = subprocess.run([sys.executable, "-m", "mkdocs", "build", "--strict", "--site-dir", str(tmp_path)],
                            cwd=ROOT, env=env, capture_output=True, text=True, timeout=600)
    assert result.returncode == 0, result.stderr[-4000:]
    for page in ("index.html", "design/index.html", "results/index.html", "changelog/index.html",
                 "api/envs/index.html", "envs/NeedleInsert-v3/index.html", "envs/WoundClosureGoal-v3/index.html"):
        assert (tmp_path / page).is_file(), page
    assert "tip_pos_x" in (tmp_path / "envs/NeedleInsert-v3/index.html").read_text(encoding="utf-8")
