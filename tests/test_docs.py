"""The docs as references: the README's results table is the file its command wrote,
the README stays a front page, and no top-level docs page carries dates or
commit-stamped history (dated runs live in ``docs/results/<study>/``)."""

import glob
import os
import re

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
README_WORDS = 820  # "about 800": words with a letter or digit, tables included


def _read(*path):
    with open(os.path.join(ROOT, *path)) as fh:
        return fh.read()


def test_readme_table_is_the_comparison_tables_file():
    table = _read("docs", "results", "comparison-table", "readme.md").strip()
    assert table in _read("README.md"), "README's table differs from its file: run " \
        "python experiments/comparison_table.py --readme-only and copy readme.md in"


def _words(text):
    return [w for w in text.split() if re.search(r"[A-Za-z0-9]", w)]


def test_readme_is_a_front_page():
    n = len(_words(_read("README.md")))
    assert n <= README_WORDS, f"README.md has {n} words; keep it a front page"


DATED = re.compile(r"\b20\d\d-\d\d-\d\d\b|\b(?:commit|at) [0-9a-f]{7,40}\b")


def _dated(paths):
    out = []
    for path in paths:
        for i, line in enumerate(open(path), 1):
            if DATED.search(line):
                out.append(f"{os.path.relpath(path, ROOT)}:{i}: {line.strip()[:80]}")
    return out


def test_docs_pages_carry_no_dated_history():
    pages = [os.path.join(ROOT, "README.md")] + sorted(glob.glob(os.path.join(ROOT, "docs",
                                                                              "*.md")))
    bad = _dated(pages)
    assert not bad, "dates or commits in reference pages (move them under " \
        "docs/results/<study>/):\n" + "\n".join(bad)


def test_dated_finder_finds_dates_and_commits(tmp_path):
    p = tmp_path / "d.md"
    p.write_text("ran on 2026-12-01\nthe suite at 5afeb27 took\nsee commit 119b708\n"
                 "a cache of 2026 entries\n")
    assert [b.split(":")[1] for b in _dated([str(p)])] == ["1", "2", "3"]


def _python_blocks(text):
    return re.findall(r"```python\n(.*?)```", text, flags=re.S)


def test_integration_guide_code_runs_as_written(capsys):
    """The Python in docs/integration.md, run as a reader would paste it."""
    blocks = _python_blocks(_read("docs", "integration.md"))
    assert blocks, "docs/integration.md has no Python example"
    for code in blocks:
        exec(compile(code, "docs/integration.md", "exec"), {"__name__": "__doc_example__"})
    assert "(1, 360, 640, 3) (1, 360, 640, 4)" in capsys.readouterr().out


def test_python_block_finder_finds_blocks():
    assert _python_blocks("x\n```python\nprint(1)\n```\n```sh\nls\n```") == ["print(1)\n"]
