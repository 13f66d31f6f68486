"""The documentation site's generated pages, written by mkdocs-gen-files when ``mkdocs build`` runs (mkdocs.yml).

Pages built rather than committed:

- ``index.md``: the README, its links made relative to ``docs/``;
- ``changelog.md``: CHANGELOG.md;
- ``envs/index.md`` and one ``envs/<id>.md`` per registered env id, from the docstring that
  :func:`suture_gym.envs.docs.env_docstring` builds from the task class and its default config (what
  ``help(env.unwrapped)`` shows), turned from its reStructuredText-like markup into Markdown by :func:`env_page`.
"""

from __future__ import annotations

import re
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]

_ROLE = re.compile(r":(?:class|func|meth|mod|attr|data|obj):`~?([^`]+)`")


def _rst_table(lines: list[str]) -> list[str]:
    """A simple reStructuredText table (``=====  ====`` rules, the last column running to the line's end) as a
    Markdown table."""
    rule = lines[0]
    spans = [(m.start(), m.end()) for m in re.finditer(r"=+", rule)]

    def cells(line: str) -> list[str]:
        out = [line[a:b].strip() for a, b in spans[:-1]]
        return out + [line[spans[-1][0]:].strip()]

    body = [line for line in lines[1:] if not set(line) <= {"=", " "}]
    head, rows = cells(body[0]), [cells(line) for line in body[1:]]
    table = ["| " + " | ".join(head) + " |", "|" + " --- |" * len(head)]
    return table + ["| " + " | ".join(c.replace("|", "\\|") for c in row) + " |" for row in rows]


def env_page(env_id: str, docstring: str) -> str:
    """The Markdown page of the env id ``env_id`` from its generated docstring ``docstring``."""
    lines = _ROLE.sub(r"``\1``", docstring).splitlines()
    out = [f"# `{env_id}`", ""]
    i = 0
    while i < len(lines):
        line = lines[i]
        if line.startswith("=====") and set(line) <= {"=", " "}:
            end = i + 1
            rules = 1
            while end < len(lines) and rules < 3:
                rules += lines[end].startswith("=====")
                end += 1
            out += ["", *_rst_table(lines[i:end]), ""]
            i = end
            continue
        if i + 1 < len(lines) and lines[i + 1] and set(lines[i + 1]) == {"-"} and len(lines[i + 1]) == len(line):
            out += ["", f"## {line}", ""]
            i += 2
            continue
        if line.startswith("* ") and out and out[-1] and not out[-1].startswith(("* ", "  ")):
            out.append("")
        elif out and out[-1].startswith("* ") and line and not line.startswith(("* ", "  ")):
            out.append("")
        out.append(line)
        i += 1
    if out and out[2].startswith(f"``{env_id}``: "):
        out[2] = out[2][len(f"``{env_id}``: "):]
    text = "\n".join(out)
    return re.sub(r"\n{3,}", "\n\n", text).strip() + "\n"


def env_pages() -> dict[str, str]:
    """``{path: Markdown}`` of the per-id pages and their index, for every registered id."""
    import suture_gym  # noqa: F401  (registers the ids)
    from suture_gym.envs.docs import env_docstring
    from suture_gym.envs.registry import ENV_IDS, GOAL_ENV_IDS, task_class

    pages = {}
    index = ["# Environments", "", "One page per registered id, generated from its task class and default config "
             "(the same text as `help(env.unwrapped)`).", "", "| id | task |", "| --- | --- |"]
    for env_id, goal in [*((i, False) for i in ENV_IDS), *((i, True) for i in GOAL_ENV_IDS)]:
        task = task_class((GOAL_ENV_IDS if goal else ENV_IDS)[env_id])
        name = env_id.removeprefix("SutureGym/")
        pages[f"envs/{name}.md"] = env_page(env_id, env_docstring(task, goal))
        index.append(f"| [`{env_id}`]({name}.md) | {task.__name__}{' (goal-conditioned)' if goal else ''} |")
    pages["envs/index.md"] = "\n".join(index) + "\n"
    return pages


def home_page(readme: str) -> str:
    """The site's home page: the README with its links made relative to ``docs/``."""
    text = readme.replace("](docs/", "](").replace("](CHANGELOG.md)", "](changelog.md)")
    return text.replace("](notes/)", "](notes/index.md)")


def main() -> None:
    import mkdocs_gen_files

    pages = {"index.md": home_page((ROOT / "README.md").read_text(encoding="utf-8")),
             "changelog.md": (ROOT / "CHANGELOG.md").read_text(encoding="utf-8"), **env_pages()}
    for path, text in pages.items():
        with mkdocs_gen_files.open(path, "w") as f:
            f.write(text)
    mkdocs_gen_files.set_edit_path("index.md", "../README.md")
    mkdocs_gen_files.set_edit_path("changelog.md", "../CHANGELOG.md")


if __name__ in {"__main__", "<run_path>"}:  # run by mkdocs-gen-files (runpy.run_path) or by hand
    main()
