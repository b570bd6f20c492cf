"""The ```python examples of the README and of docs/ run, in order, one namespace per file, and give what they
say. (```py blocks are illustrations or are run by the tests of their subject.)"""

import re
from pathlib import Path

import numpy as np
import pytest

ROOT = Path(__file__).resolve().parents[1]
FILES = [ROOT / "README.md"] + sorted((ROOT / "docs").glob("*.md"))


def _blocks(path: Path) -> list[str]:
    return re.findall(r"```python\n(.*?)```", path.read_text(), flags=re.S)


def _run(path: Path) -> dict:
    namespace: dict = {}
    for i, block in enumerate(_blocks(path)):
        exec(compile(block, f"{path.relative_to(ROOT)} example {i}", "exec"), namespace)
    return namespace


def test_readme_first_refinement_and_refined_model(capsys):
    ns = _run(ROOT / "README.md")
    dc = ns["ident"].dc_gain()[:, 0, 0]
    assert dc.shape == (4,) and ((dc - 5.0).abs() < 0.01).all(), dc
    z = ns["z"]
    err = np.max(np.abs(ns["refined"](z) - ns["true"](z)) / np.abs(ns["true"](z)))
    assert err < 1e-3, err
    assert ns["refined"].input_labels == ["w"] and ns["refined"].output_labels == ["y"]


@pytest.mark.parametrize("path", [p for p in FILES[1:] if _blocks(p)], ids=lambda p: p.name)
def test_docs_examples_run(path, capsys):
    ns = _run(path)
    if path.name == "method.md":                                   # the graph wired by hand
        assert ((ns["graph"].blocks["refine"].dc_gain()[:, 0, 0] - 5.0).abs() < 0.05).all()
    if path.name == "data.md":
        assert ns["est"].values.shape == (105712 - 40650, 2) and ns["rec"].units == {"V1": "V", "V2": "V"}
    if path.name == "own-problem.md":                              # the damper with a basis of the user's own
        res = ns["damper_result"]
        assert res.status == ["converged"] * 4
        assert ((res.lower["C_D"] <= 0.8) & (res.upper["C_D"] >= 0.8)).all()
    if path.name == "python-control.md":
        assert ns["known"].inputs == {"w": 1, "u": 1} and ns["known"].outputs == {"y": 1, "y0": 1}


def test_no_reader_facing_text_points_outside_the_repository():
    for path in FILES + sorted((ROOT / "scenarios").glob("*.py")) + sorted((ROOT / "rcotorch").rglob("*.py")):
        text = path.read_text()
        assert "../shared" not in text and "shared/data" not in text and "shared/docs" not in text, path


def test_every_file_the_docs_and_code_name_is_in_the_repository():
    """Markdown links resolve, and a Markdown file named in code, tests or docs exists in the repository."""
    names = {p.name for p in ROOT.rglob("*.md") if ".venv" not in p.parts and "build" not in p.parts}
    texts = FILES + sorted((ROOT / "scenarios").glob("*.py")) + sorted((ROOT / "rcotorch").rglob("*.py")) + \
        sorted((ROOT / "tests").glob("*.py")) + sorted((ROOT / "benchmarks").glob("*.py"))
    for path in texts:
        text = path.read_text()
        if path.suffix == ".md":
            for target in re.findall(r"\]\(([^)#\s]+)(?:#[^)]*)?\)", text):
                if "://" in target or target.startswith("mailto:"):
                    continue
                assert (path.parent / target).exists(), f"{path.name} links to {target}, which does not exist"
        for name in re.findall(r"\b([A-Za-z][\w-]*\.md)\b", text):
            assert name in names, f"{path.relative_to(ROOT)} names {name}, which is not in the repository"
