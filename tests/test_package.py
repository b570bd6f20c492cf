"""The package as a user gets it: a wheel built from the checkout, installed (not editable) into a fresh virtual
environment, and its command line run from another folder; the scenario cards of ``rcotorch show``; the set-up
script ``./dev``."""

import json
import os
import re
import shutil
import site
import subprocess
import sys
import sysconfig
from pathlib import Path

import pytest

from rcotorch.run import scenario as scenarios
from rcotorch.run.cli import main

ROOT = Path(__file__).resolve().parents[1]
LEFT_OUT = shutil.ignore_patterns(".git", ".venv", "runs", "build", "dist", "*.egg-info", "__pycache__",
                                  ".pytest_cache", ".ruff_cache")


def _sh(*cmd, **kw) -> subprocess.CompletedProcess:
    out = subprocess.run([str(c) for c in cmd], capture_output=True, text=True, timeout=600, **kw)
    assert out.returncode == 0, f"{cmd}: exit {out.returncode}\n{out.stdout}\n{out.stderr}"
    return out


def _engine_built_for(src: Path) -> None:
    """Where the engine this checkout runs was compiled after the last change to every file it is compiled from
    (its C sources, setup.py with the flags, pyproject.toml), put it in the copy's build folder where the wheel's
    build leaves it: setuptools' build_ext skips an extension whose built file is newer than its sources, as in
    any build after the first, and the wheel packs that file instead of the same sources compiled again with the
    same flags (about 50 s of CPU, for the same machine code). Otherwise (no engine in the checkout, or one older
    than a source) the wheel's build compiles it."""
    name = "_engine" + sysconfig.get_config_var("EXT_SUFFIX")
    built = ROOT / "rcotorch" / "engine" / name
    sources = [*(ROOT / "rcotorch" / "engine" / "csrc").iterdir(), ROOT / "setup.py", ROOT / "pyproject.toml"]
    if not built.is_file() or any(s.stat().st_mtime >= built.stat().st_mtime for s in sources):
        return
    lib = src / "build" / f"lib.{sysconfig.get_platform()}-{sys.implementation.cache_tag}" / "rcotorch" / "engine"
    lib.mkdir(parents=True)
    shutil.copy2(built, lib / name)             # copy2 keeps its time, newer than the copied sources'


def _numba_cache_copied(purelib: Path) -> None:
    """Copy the code numba compiled for this checkout's modules (``cache=True``: the files in __pycache__ beside
    each module) beside the installed modules. numba loads a cached function only where the module's source is
    the one it was compiled from (numba 0.68 keys the cache by a SHA-256 of the source; a numba keying it by the
    file's time, which differs here, compiles afresh) and compiles afresh otherwise: the installed package runs as
    it does after its first use, without compiling the thermosphere's native column again (about 40 s of CPU)."""
    for top, package in (("rcotorch", "rcotorch"), ("scenarios", "rcotorch/scenarios")):
        for cached in (ROOT / top).glob("**/__pycache__/*.nb[ic]"):
            to = purelib / package / cached.relative_to(ROOT / top)
            to.parent.mkdir(exist_ok=True)
            shutil.copy2(cached, to)


@pytest.fixture(scope="module")
def installed(tmp_path_factory) -> tuple[Path, dict]:
    """A virtual environment with the wheel of this checkout installed, reusing this environment's torch and
    other dependencies offline (through a .pth file, added after the install so pip never sees them), and the
    engine and numba code compiled for the checkout where its sources have not changed since."""
    tmp = tmp_path_factory.mktemp("package")
    src = tmp / "src"
    shutil.copytree(ROOT, src, ignore=LEFT_OUT)
    _engine_built_for(src)
    _sh(sys.executable, "-m", "pip", "wheel", "--no-deps", "--no-build-isolation", "--no-index", "-q", src,
        "-w", tmp / "wheels")
    wheel = next((tmp / "wheels").glob("rcotorch-*.whl"))
    venv = tmp / "venv"
    _sh(sys.executable, "-m", "venv", "--without-pip", venv)
    python = venv / "bin" / "python"
    _sh(sys.executable, "-m", "pip", "--python", python, "install", "--no-deps", "--no-index", "-q", wheel)
    purelib = Path(_sh(python, "-c", "import sysconfig; print(sysconfig.get_paths()['purelib'])").stdout.strip())
    (purelib / "_test_dependencies.pth").write_text("\n".join(site.getsitepackages()) + "\n")
    _numba_cache_copied(purelib)
    env = {k: v for k, v in os.environ.items() if k not in ("PYTHONPATH", "RCOTORCH_SCENARIOS")}
    env["MPLBACKEND"] = "Agg"
    elsewhere = tmp / "elsewhere"
    elsewhere.mkdir()
    return venv, dict(env=env, cwd=elsewhere)


ARGS = ["--steps", "20", "--no-figures", "--quiet"]
#: ``python -c RUN_EACH FOLDER NAME...``: ``rcotorch run NAME ARGS --out FOLDER/NAME`` for each name, by the
#: command line's main, each exit code printed on a line of its own.
RUN_EACH = f"""
import sys
from rcotorch.run.cli import main
for name in sys.argv[2:]:
    code = main(["run", name, *{ARGS!r}, "--out", sys.argv[1] + "/" + name])
    print("EXIT", name, code, flush=True)
"""


@pytest.mark.slow
def test_wheel_lists_shows_and_runs_every_scenario_from_another_folder(installed, silverbox_csv):
    venv, kw = installed
    where = _sh(venv / "bin" / "python", "-c", "import rcotorch; print(rcotorch.__file__)", **kw).stdout
    assert str(venv) in where and str(ROOT) not in where            # the installed copy, not the checkout
    engine = _sh(venv / "bin" / "python", "-c", "import rcotorch.engine._engine as e; print(e.__file__)", **kw).stdout
    assert str(venv) in engine                                       # the wheel carries the compiled engine
    listed = _sh(venv / "bin" / "rcotorch", "list", **kw).stdout
    names = sorted(line.split()[0] for line in listed.splitlines())
    assert names == sorted(scenarios.available()) and len(names) >= 7
    card = _sh(venv / "bin" / "rcotorch", "show", "sdof-stiffness", **kw).stdout
    assert "dK*" in card and "N/m" in card and "stiffness change in the truth" in card
    # The first scenario through the console script; the others by the installed command line's main, in one
    # process of the environment's interpreter (the same command line, without a start of Python, torch, scipy
    # and python-control for each: about 4 s of CPU each).
    runs = kw["cwd"] / "runs"
    first = subprocess.run([venv / "bin" / "rcotorch", "run", names[0], *ARGS, "--out", runs / names[0]],
                           capture_output=True, text=True, timeout=600, **kw)
    assert first.returncode in (0, 1), f"{names[0]}: exit {first.returncode}\n{first.stdout}\n{first.stderr}"
    rest = subprocess.run([venv / "bin" / "python", "-c", RUN_EACH, runs, *names[1:]], capture_output=True,
                          text=True, timeout=600, **kw)
    exits = dict(line.split()[1:] for line in rest.stdout.splitlines() if line.startswith("EXIT "))
    assert rest.returncode == 0 and set(exits) == set(names[1:]), f"exit {rest.returncode}\n{rest.stderr}"
    exits[names[0]] = str(first.returncode)
    for name in names:
        assert exits[name] in ("0", "1"), f"{name}: exit {exits[name]}\n{rest.stderr}"
        out = runs / name
        summary = json.loads((out / "summary.json").read_text())
        assert summary["scenario"] == name and summary["steps"] == 20
        assert summary["engine"] == "native", (name, summary["engine_reason"])


def test_every_shipped_setting_is_documented():
    for name, sc in scenarios.available().items():
        for key in sc.settings:
            info = sc.setting(key)
            assert info.meaning, f"{name}: setting {key!r} has no meaning in Scenario.about"
            assert all(isinstance(c, str) for c in info.choices)
        assert not set(sc.about) - set(sc.settings), f"{name}: about names unknown settings"


def test_show_prints_the_card(capsys):
    assert main(["show", "twodof-stiffness"]) == 0
    card = capsys.readouterr().out
    lines = {line.split()[0]: line for line in card.splitlines() if line.strip()}
    assert "dk1" in lines and "0.4" in lines["dk1"] and "N/m" in lines["dk1"]
    assert "one of: midpoint, sampled" in lines["sees"]
    assert "requirements: estimates.dk1 rel err < 0.1" in card and "steps: 20000" in card
    assert main(["show", "twodof-stifness"]) == 2
    assert "did you mean 'twodof-stiffness'" in capsys.readouterr().err


def test_a_choice_outside_the_documented_ones_is_rejected():
    sc = scenarios.get("twodof-stiffness")
    with pytest.raises(scenarios.ConfigError, match=r"sees must be one of \['midpoint', 'sampled'\], got 'middle'"):
        sc.resolve({"sees": "middle"})
    with pytest.raises(scenarios.ConfigError, match=r"sees must be one of"):
        sc.resolve_members({}, [{"sees": "sampled"}, {"sees": "half"}])


def test_user_scenario_folders(tmp_path, monkeypatch):
    """A folder in RCOTORCH_SCENARIOS: its files build on the shipped scenarios and on each other; a file that
    fails to load, and a name defined twice, are errors naming the files."""
    (tmp_path / "base_case.py").write_text(
        "from rcotorch.scenarios.sdof_stiffness import SdofStiffness\n"
        "class Stiffer(SdofStiffness):\n"
        "    name = 'my-stiffer'\n"
        "    settings = dict(SdofStiffness.settings, dK=0.8)\n"
        "SCENARIO = Stiffer()\n")
    (tmp_path / "variant.py").write_text(
        "from base_case import Stiffer\n"
        "class Softer(Stiffer):\n"
        "    name = 'my-softer'\n"
        "    settings = dict(Stiffer.settings, dK=0.1)\n"
        "SCENARIO = Softer()\n")
    monkeypatch.setenv("RCOTORCH_SCENARIOS", str(tmp_path))
    found = scenarios.available()
    assert found["my-stiffer"].settings["dK"] == 0.8 and found["my-softer"].settings["dK"] == 0.1
    assert found["my-softer"].setting("dK").unit == "N/m"            # the documentation is inherited
    (tmp_path / "clash.py").write_text("from variant import Softer\nSCENARIO = Softer()\n")
    clash = r"two scenarios are named 'my-softer': \S*(clash|variant).py and \S*(clash|variant).py"
    with pytest.raises(scenarios.ConfigError, match=clash):
        scenarios.available()
    (tmp_path / "clash.py").write_text("import no_such_module\n")
    with pytest.raises(scenarios.ConfigError, match=r"clash.py \(from RCOTORCH_SCENARIOS\) fails to load: "
                                                    r"ModuleNotFoundError"):
        scenarios.available()


def test_dev_script_parses_and_names_every_command_in_its_usage_and_header():
    dev = ROOT / "dev"
    _sh("bash", "-n", dev)
    text = dev.read_text()
    commands = re.search(r"^ +([a-z|]+)\) ;;$", text, flags=re.M).group(1).split("|")
    assert {"run", "list", "show", "sweep", "tune", "test", "lint"} <= set(commands)
    usage = subprocess.run(["bash", dev], capture_output=True, text=True, timeout=60)       # no command: usage
    assert usage.returncode == 2 and usage.stdout == ""
    listed = set(re.findall(r"^  ([a-z]+) ", usage.stderr, flags=re.M))
    header = set(re.findall(r"^#   \./dev ([a-z]+)", text, flags=re.M))
    assert listed == set(commands) and header == set(commands), (listed, header, commands)
    unknown = subprocess.run(["bash", dev, "frobnicate"], capture_output=True, text=True, timeout=60)
    assert unknown.returncode == 2 and "usage: ./dev COMMAND" in unknown.stderr


@pytest.mark.parametrize("args,ray", [(["c.toml", "--backend", "ray"], True), (["c.toml", "--backend=ray"], True),
                                      (["c.toml", "--backend", "local"], False), (["--out", "ray", "c.toml"], False)])
def test_dev_adds_ray_for_the_ray_backend_only(args, ray):
    """``./dev sweep``/``tune`` install the extra ray when the arguments ask for the ray backend."""
    body = re.search(r"^ray_backend\(\) \{.*?^\}$", (ROOT / "dev").read_text(), flags=re.M | re.S).group(0)
    done = subprocess.run(["bash", "-c", f"{body}\nray_backend \"$@\"", "dev", *args], timeout=60)
    assert (done.returncode == 0) == ray
