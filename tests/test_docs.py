"""The documentation: the results page matches its JSON source."""

import json
from pathlib import Path

import pytest

from conftest import import_script

ROOT = Path(__file__).resolve().parents[1]


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
