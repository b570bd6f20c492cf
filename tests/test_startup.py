"""Start-up: ``rcotorch --version``, ``list`` and ``show`` load neither torch nor scipy, python-control or
matplotlib (the modules each command imports, read from ``python -X importtime``); ``import rcotorch`` imports
its parts on first use and still offers every public name; a user's scenario folder whose files import torch at
the top still lists and shows. The times themselves are measured by benchmarks/startup.py."""

import json
import os
import subprocess
import sys
from pathlib import Path

import pytest
from bench_scripts import run_script

import rcotorch as rt

ROOT = Path(__file__).resolve().parents[1]
HEAVY = ("torch", "scipy", "control", "matplotlib")


def _imported(*args: str, scenarios: Path | None = None, code: str | None = None) -> tuple[set[str], str]:
    """The top-level packages a fresh ``python -m rcotorch ARGS`` (or ``python -c CODE``) imports, and its
    stdout."""
    env = {k: v for k, v in os.environ.items() if k != "RCOTORCH_SCENARIOS"}
    if scenarios is not None:
        env["RCOTORCH_SCENARIOS"] = str(scenarios)
    what = ["-c", code] if code is not None else ["-m", "rcotorch", *args]
    done = subprocess.run([sys.executable, "-X", "importtime", *what], capture_output=True, text=True,
                          env=env, timeout=120, cwd=ROOT)
    assert done.returncode == 0, done.stderr[-2000:]
    names = {line.rsplit("|", 1)[-1].strip() for line in done.stderr.splitlines() if line.startswith("import time:")}
    return {n.split(".")[0] for n in names}, done.stdout


@pytest.mark.parametrize("args", [("--version",), ("list",), ("show", "sdof-stiffness"),
                                  ("show", "thermosphere-no-cooling")])
def test_version_list_and_show_load_no_heavy_package(args):
    loaded, out = _imported(*args)
    assert "rcotorch" in loaded and out.strip()
    assert not loaded & set(HEAVY), f"rcotorch {' '.join(args)} imports {sorted(loaded & set(HEAVY))}"


def test_the_check_sees_an_import_of_torch():
    loaded, _ = _imported(code="import rcotorch; rcotorch.Graph")
    assert "torch" in loaded


def test_import_rcotorch_loads_no_heavy_package_and_offers_every_name():
    loaded, out = _imported(code="import rcotorch; print(len(rcotorch.__all__), sorted(rcotorch.__all__) == "
                                 "sorted(n for n in rcotorch.__all__ if n in dir(rcotorch)), "
                                 "rcotorch.scenario.get('sdof-stiffness').settings['dK'], "
                                 "rcotorch.errors.ConfigError.__name__)")
    assert not loaded & set(HEAVY), sorted(loaded & set(HEAVY))
    assert out.split() == [str(len(rt.__all__)), "True", "0.5", "ConfigError"]


def test_every_public_name_resolves_to_its_definition():
    import rcotorch.blocks.sources
    import rcotorch.data.recording
    import rcotorch.graph
    for name in rt.__all__:
        assert getattr(rt, name) is not None, name
    assert rt.Graph is rcotorch.graph.Graph and rt.load is rcotorch.data.recording.load
    assert rt.WhiteNoise is rcotorch.blocks.sources.WhiteNoise
    assert rt.models.__name__ == "rcotorch.models" and rt.rng.__name__ == "rcotorch.engine.rng"
    assert rt.features.__name__ == "rcotorch.blocks.features" and rt.datasets.__name__ == "rcotorch.data.datasets"
    with pytest.raises(AttributeError, match="no attribute 'Grahp'"):
        rt.Grahp  # noqa: B018


def test_refine_and_refinement_are_functions_beside_the_modules_that_define_them():
    """``rt.refine`` and ``rt.refinement`` are functions; their modules (``rcotorch.run.refine``,
    ``rcotorch.wiring``) have other names, so importing them changes nothing, and the package is a plain module."""
    code = ("import rcotorch.run.refine, rcotorch.wiring, rcotorch as rt, inspect, types; "
            "print(inspect.isfunction(rt.refine), inspect.isfunction(rt.refinement), "
            "rt.refine.__module__, rt.refinement.__module__, type(rt) is types.ModuleType)")
    _, out = _imported(code=code)
    assert out.split() == ["True", "True", "rcotorch.run.refine", "rcotorch.wiring", "True"]


def test_a_user_scenario_that_imports_torch_at_the_top_lists_and_shows(tmp_path):
    (tmp_path / "heavy_case.py").write_text(
        "import torch\n"
        "from rcotorch.scenarios.sdof_stiffness import SdofStiffness\n"
        "class Heavy(SdofStiffness):\n"
        "    name = 'my-heavy'\n"
        "    description = 'built with ' + torch.__name__\n"
        "    settings = dict(SdofStiffness.settings, dK=0.3)\n"
        "SCENARIO = Heavy()\n")
    loaded, out = _imported("list", scenarios=tmp_path)
    assert "torch" in loaded
    assert any(line.split() == ["my-heavy", "[V.A]", "built", "with", "torch"] for line in out.splitlines()), out
    _, card = _imported("show", "my-heavy", scenarios=tmp_path)
    dk = next(line for line in card.splitlines() if line.startswith("dK*"))
    assert "0.3" in dk.split() and "N/m" in dk


def test_startup_benchmark_quick(tmp_path):
    run_script("startup", "--quick", "--out", str(tmp_path / "startup.json"))
    out = json.loads((tmp_path / "startup.json").read_text())
    rows = {r["command"]: r for r in out["results"]}
    assert set(rows) >= {"import torch", "import rcotorch", "rcotorch --version", "rcotorch list",
                         "rcotorch show sdof-stiffness"}
    assert rows["import torch"]["ratio_to_import_torch"] == 1.0 and "torch" in rows["import torch"]["loads"]
    for command in ("rcotorch --version", "rcotorch list", "rcotorch show sdof-stiffness"):
        assert not set(rows[command]["loads"]) & set(HEAVY), rows[command]
