"""The README's Python examples run and give what they say."""

import re
from pathlib import Path

import pytest

README = Path(__file__).resolve().parents[1] / "README.md"


def _blocks():
    return re.findall(r"```python\n(.*?)```", README.read_text(), flags=re.S)


@pytest.mark.parametrize("index", range(len(_blocks())))
def test_readme_example_runs(index, capsys):
    namespace: dict = {}
    exec(compile(_blocks()[index], f"README.md example {index}", "exec"), namespace)
    graph = namespace["graph"]
    ident = [b for b in graph.blocks.values() if type(b).__name__ == "RCOEstimator"][0]
    dc = ident.dc_gain()[:, 0, 0]
    assert ((dc - 5.0).abs() < 0.05).all(), dc
