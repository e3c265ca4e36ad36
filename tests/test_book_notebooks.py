"""The committed chapter notebooks are clean sources: no outputs, no execution counts,
no saved widget state, and a kernelspec the book build can start (``python3``).

Outputs belong in the built book (``_build/``), not in git: they bloat diffs, go stale, and
JupyterLab's autosave would otherwise commit whatever a reader last ran. How to keep them
clean: see "Keeping the notebooks output-free" in the README
(``python scripts/clear_notebooks.py`` or the git filter it installs).
"""

from __future__ import annotations

import json
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parent.parent
NOTEBOOKS = sorted((ROOT / "notebooks").glob("*.ipynb"))


def test_there_are_chapter_notebooks():
    assert len(NOTEBOOKS) >= 6


@pytest.mark.parametrize("path", NOTEBOOKS, ids=lambda p: p.name)
def test_notebook_is_output_free(path):
    nb = json.loads(path.read_text(encoding="utf-8"))
    dirty = []
    for i, cell in enumerate(nb["cells"]):
        if cell["cell_type"] != "code":
            continue
        if cell.get("outputs"):
            dirty.append(f"cell {i}: {len(cell['outputs'])} output(s)")
        if cell.get("execution_count") is not None:
            dirty.append(f"cell {i}: execution_count {cell['execution_count']}")
    assert not dirty, (f"{path.name} has saved outputs ({'; '.join(dirty[:5])}); run "
                       "`python scripts/clear_notebooks.py` before committing")
    assert "widgets" not in nb.get("metadata", {}), (
        f"{path.name} stores widget state in its metadata; run scripts/clear_notebooks.py")
    assert nb["metadata"].get("kernelspec", {}).get("name") == "python3"


def test_clear_notebooks_script_cleans_a_dirty_copy(tmp_path):
    """The README's cleaning command really removes outputs (and nothing else)."""
    import subprocess
    import sys

    source = NOTEBOOKS[0]
    nb = json.loads(source.read_text(encoding="utf-8"))
    code = next(c for c in nb["cells"] if c["cell_type"] == "code")
    code["outputs"] = [{"output_type": "stream", "name": "stdout", "text": ["hello\n"]}]
    code["execution_count"] = 7
    nb["metadata"]["widgets"] = {"application/vnd.jupyter.widget-state+json": {}}
    dirty = tmp_path / source.name
    dirty.write_text(json.dumps(nb, indent=1), encoding="utf-8")
    proc = subprocess.run([sys.executable, str(ROOT / "scripts" / "clear_notebooks.py"),
                           str(dirty)], capture_output=True, text=True)
    assert proc.returncode == 0, proc.stderr
    cleaned = json.loads(dirty.read_text(encoding="utf-8"))
    assert [c["source"] for c in cleaned["cells"]] == [c["source"] for c in nb["cells"]]
    assert all(not c.get("outputs") and c.get("execution_count") is None
               for c in cleaned["cells"] if c["cell_type"] == "code")
    assert "widgets" not in cleaned["metadata"]
    # --check reports a dirty notebook with exit status 1 and leaves it unchanged
    dirty.write_text(json.dumps(nb, indent=1), encoding="utf-8")
    check = subprocess.run([sys.executable, str(ROOT / "scripts" / "clear_notebooks.py"),
                            "--check", str(dirty)], capture_output=True, text=True)
    assert check.returncode == 1
    assert json.loads(dirty.read_text(encoding="utf-8"))["cells"][0] == nb["cells"][0]


CHAPTERS_WITH_CODE_LINE = ["01_kalman_filter", "02_bayesian_aggregation", "03_rkn", "04_acrkn", "06_mts3",
                           "07_planning"]


@pytest.mark.parametrize("name", CHAPTERS_WITH_CODE_LINE)
def test_chapter_links_its_modules_in_the_api_reference(name):
    """Each chapter's opening cell names its modules with {py:mod} roles (links into the API
    page, book/api.rst) and every named module exists; the chapter's own code cells import
    from at least one of them."""
    import importlib
    import re

    nb = json.loads((ROOT / "notebooks" / f"{name}.ipynb").read_text(encoding="utf-8"))
    opening = "".join(nb["cells"][0]["source"])
    assert "**Code for this chapter.**" in opening
    assert "{doc}`API reference <../book/api>`" in opening
    modules = re.findall(r"\{py:mod\}`(pgm_wm[\w.]*)`", opening)
    assert modules, "no module linked"
    for module in modules:
        importlib.import_module(module)
    code = "".join("".join(c["source"]) for c in nb["cells"] if c["cell_type"] == "code")
    assert any(f"from {m} import" in code for m in modules)


def exercise_counts(nb: dict) -> tuple[int, int]:
    """(number of exercises, number of solutions/hints/open-problem labels) in a notebook's
    exercise section (from "## Exercises" to the next "## What..." heading)."""
    import re

    text = "\n".join("".join(c["source"]) for c in nb["cells"])
    text = text[text.index("## Exercises"):]
    end = re.search(r"^## What", text, re.M)
    text = text[: end.start()] if end else text
    numbers = set(re.findall(r"^(?:\*\*(\d+)\.|(\d+)\. \*\*)", text, re.M))
    return len(numbers), len(re.findall(r"Solution|Hint for|Open problem", text))


@pytest.mark.parametrize("name", CHAPTERS_WITH_CODE_LINE)
def test_every_exercise_has_a_solution_or_is_marked_open(name):
    nb = json.loads((ROOT / "notebooks" / f"{name}.ipynb").read_text(encoding="utf-8"))
    n_exercises, n_answers = exercise_counts(nb)
    assert n_exercises >= 3, name
    assert n_answers >= n_exercises, f"{name}: {n_exercises} exercises, {n_answers} solutions"
