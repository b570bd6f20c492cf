"""The command line's contract: exit codes (0 pass, 1 a requirement failed, 2 bad input, 3 internal error, 130
Ctrl-C), output folders that are never clobbered, resume that refuses what it cannot honour. Faults are
reproduced for real: a SIGINT sent to a running process, a second process on the same folder, a killed
process, damaged checkpoints, a read-only folder, a memory limit, a Ray address where nothing answers."""

import contextlib
import json
import os
import re
import resource
import shutil
import signal
import socket
import subprocess
import sys
import time
from pathlib import Path

import pytest
import torch
from conftest import default_signals, wait_for

import rcotorch
from rcotorch.run.cli import Session, main
from rcotorch.run.outputs import MANIFEST, load_checkpoint

QUICK = ["--steps", "300", "--quiet", "--no-figures"]


def _cli(*args, **kw) -> subprocess.Popen:
    env = dict(os.environ, PYTHONUNBUFFERED="1")
    then = kw.pop("preexec_fn", None)

    def start():
        default_signals()
        if then is not None:
            then()
    return subprocess.Popen([sys.executable, "-m", "rcotorch", *args], stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, text=True, env=env, preexec_fn=start, **kw)


def test_version_and_python_m():
    assert main(["--version"]) == 0
    proc = _cli("--version")
    out, _ = proc.communicate(timeout=120)
    assert proc.returncode == 0 and out.strip() == f"rcotorch {rcotorch.__version__}"
    proc = _cli("list")
    out, _ = proc.communicate(timeout=120)
    assert proc.returncode == 0 and "sdof-stiffness " in out


@pytest.mark.parametrize("args, message", [
    (["--checkpoint-every", "-5"], "--checkpoint-every must be a positive integer, got -5"),
    (["--checkpoint-every", "0"], "--checkpoint-every must be a positive integer"),
    (["--set", "p0=nan"], "setting p0 must be a finite number, got 'nan'"),
    (["--set", "p0=inf"], "setting p0 must be a finite number"),
    (["--set", "lam=-Infinity"], "setting lam must be a finite number"),
    (["--set", "nu=1e400"], "setting nu must be a finite number"),
    (["--set", "p0"], "--set expects KEY=VALUE"),
    (["--device", "xyz"], "--device 'xyz' is not a device; valid devices: cpu, cuda, cuda:N"),
    (["--device", "gpu"], "valid devices: cpu, cuda, cuda:N"),
    (["--device", "meta"], "rcotorch runs on cpu or cuda"),
    (["--threads", "-1"], "--threads must be a positive integer, got -1"),
    (["--steps", "0"], "steps must be a positive integer, got 0"),
    (["--batch", "-3"], "batch must be a positive integer, got -3"),
])
def test_bad_values_exit_2_with_the_cause(args, message, tmp_path, capsys):
    start = time.monotonic()
    assert main(["run", "sdof-stiffness", "--out", str(tmp_path / "out"), *QUICK, *args]) == 2
    err = capsys.readouterr().err
    assert message in err and err.count("\n") == 1 and "Traceback" not in err
    assert time.monotonic() - start < 60 and not (tmp_path / "out" / "summary.json").exists()


def test_bad_dtype_and_usage_exit_2_with_the_choices(capsys):
    assert main(["run", "sdof-stiffness", "--dtype", "float16"]) == 2
    assert re.search(r"invalid choice: 'float16' \(choose from '?float64'?, '?float32'?\)", capsys.readouterr().err)
    assert main(["run"]) == 2
    assert "run needs a scenario NAME" in capsys.readouterr().err
    assert main(["frobnicate"]) == 2


def test_out_that_is_a_file_exits_2(tmp_path, capsys):
    f = tmp_path / "file"
    f.write_text("mine")
    assert main(["run", "sdof-stiffness", "--out", str(f), *QUICK]) == 2
    assert "is a file" in capsys.readouterr().err and f.read_text() == "mine"


@contextlib.contextmanager
def _read_only(path: Path):
    """A folder this process cannot write to (chmod, or the immutable attribute when running as root)."""
    path.mkdir()
    path.chmod(0o555)
    immutable = False
    try:
        if os.access(path, os.W_OK) or os.geteuid() == 0:
            if shutil.which("chattr") and subprocess.run(["chattr", "+i", str(path)]).returncode == 0:
                immutable = True
        with contextlib.suppress(OSError):
            (path / "probe").touch()
            (path / "probe").unlink()
            pytest.skip("no way to make a read-only folder on this file system")
        yield path
    finally:
        if immutable:
            subprocess.run(["chattr", "-i", str(path)])
        path.chmod(0o755)


def test_read_only_out_exits_2(tmp_path, capsys):
    with _read_only(tmp_path / "ro") as ro:
        assert main(["run", "sdof-stiffness", "--out", str(ro), *QUICK]) == 2
        assert "cannot write to the output folder" in capsys.readouterr().err
        assert main(["run", "sdof-stiffness", "--out", str(ro / "sub"), *QUICK]) == 2
        assert "cannot create the output folder" in capsys.readouterr().err
        assert os.listdir(ro) == []


def test_a_folder_holding_a_run_is_refused_and_overwrite_keeps_the_users_files(tmp_path, capsys):
    out = tmp_path / "out"
    assert main(["run", "sdof-stiffness", "--out", str(out), "--steps", "300", "--quiet"]) in (0, 1)
    (out / "notes.txt").write_text("my notes")
    (out / "estimates.png").write_bytes(b"keep?")    # replaced below only because the run wrote it
    before = {p.name: p.stat().st_mtime_ns for p in out.iterdir()}
    capsys.readouterr()
    assert main(["run", "sdof-stiffness", "--out", str(out), *QUICK]) == 2
    assert "already holds a run (sdof-stiffness); use --resume" in capsys.readouterr().err
    assert {p.name: p.stat().st_mtime_ns for p in out.iterdir()} == before
    assert main(["run", "sdof-stiffness", "--out", str(out), *QUICK, "--overwrite"]) in (0, 1)
    assert (out / "notes.txt").read_text() == "my notes"
    assert not (out / "estimates.png").exists()                  # --no-figures: the old figure is gone
    events = list(out.glob("events.out.tfevents.*"))
    assert len(events) == 1                                      # the old event file is not mixed in
    manifest = json.loads((out / MANIFEST).read_text())
    assert "notes.txt" not in manifest["files"] and "summary.json" in manifest["files"]


def test_the_default_folder_gets_a_fresh_version(tmp_path, monkeypatch, capsys):
    monkeypatch.chdir(tmp_path)
    assert main(["run", "sdof-stiffness", *QUICK]) in (0, 1)
    assert main(["run", "sdof-stiffness", *QUICK]) in (0, 1)
    assert "-> runs/sdof-stiffness-2" in capsys.readouterr().out
    assert (tmp_path / "runs/sdof-stiffness/summary.json").exists()
    assert (tmp_path / "runs/sdof-stiffness-2/summary.json").exists()


def _long_run(out: Path, *extra) -> subprocess.Popen:
    """A run long enough to be interrupted (the PyTorch engine: about 0.3 ms per step)."""
    proc = _cli("run", "sdof-stiffness", "--steps", "400000", "--out", str(out), "--quiet", "--no-figures",
                "--engine", "torch", *extra)
    wait_for(lambda: any(out.glob("events.out.tfevents.*")) or proc.poll() is not None)
    assert proc.poll() is None, proc.communicate()
    return proc


def test_ctrl_c_saves_a_checkpoint_exits_130_and_the_resume_is_bitwise(tmp_path):
    out = tmp_path / "run"
    proc = _long_run(out)
    time.sleep(1.0)
    proc.send_signal(signal.SIGINT)
    stdout, stderr = proc.communicate(timeout=120)
    assert proc.returncode == 130, stderr
    assert f"resume with: rcotorch run --resume {out}" in stderr and "Traceback" not in stderr
    step = int(re.search(r"stopped at step (\d+)", stderr).group(1))
    assert 0 < step < 400000
    assert "stopped by Ctrl-C" in (out / "rcotorch.log").read_text()
    # Resume to a little further, and compare with an uninterrupted run to that step (each in a fresh process
    # like the interrupted one, so all three use the same kernels).
    target = str(step + 137)
    for args in (["--resume", str(out)], ["sdof-stiffness", "--out", str(tmp_path / "full")]):
        proc = _cli("run", *args, "--steps", target, "--quiet", "--no-figures", "--engine", "torch")
        proc.communicate(timeout=120)
        assert proc.returncode in (0, 1)
    resumed, full = load_checkpoint(out / "checkpoint.pt"), load_checkpoint(tmp_path / "full" / "checkpoint.pt")
    assert resumed["graph"].keys() == full["graph"].keys()
    for key in full["graph"]:
        assert torch.equal(resumed["graph"][key], full["graph"][key]), key


def test_a_second_ctrl_c_stops_at_once(capsys):
    previous = signal.signal(signal.SIGINT, signal.default_int_handler)     # as in a terminal, even under nohup
    try:
        session = Session(["run"])
        with pytest.raises(KeyboardInterrupt), session.interruptible() as stop:
            os.kill(os.getpid(), signal.SIGINT)
            assert stop.is_set()
            os.kill(os.getpid(), signal.SIGINT)
    finally:
        signal.signal(signal.SIGINT, previous)
    assert "Ctrl-C again to quit at once" in capsys.readouterr().err


def test_two_writers_and_a_killed_writer(tmp_path, capsys):
    out = tmp_path / "run"
    proc = _long_run(out, "--checkpoint-every", "2000")
    try:
        for args in (["run", "sdof-stiffness", "--out", str(out), *QUICK],
                     ["run", "sdof-stiffness", "--out", str(out), *QUICK, "--overwrite"],
                     ["run", "--resume", str(out), "--quiet"]):
            start = time.monotonic()
            assert main(args) == 2
            assert "is in use: another rcotorch run is writing to it" in capsys.readouterr().err
            assert time.monotonic() - start < 30
        wait_for(lambda: (out / "checkpoint.pt").exists())
    finally:
        proc.kill()                                   # kill -9: no chance to clean up
        proc.communicate()
    step = int(load_checkpoint(out / "checkpoint.pt")["graph"]["k"])
    assert step > 0 and step % 2000 == 0
    assert main(["run", "--resume", str(out), "--steps", str(step + 100), "--quiet", "--no-figures"]) in (0, 1)
    assert json.loads((out / "summary.json").read_text())["steps"] == step + 100


@pytest.mark.parametrize("damage", ["truncate", "flip", "empty"])
def test_damaged_checkpoints_exit_2_naming_the_file(damage, tmp_path, capsys):
    out = tmp_path / "run"
    assert main(["run", "sdof-stiffness", "--out", str(out), *QUICK]) in (0, 1)
    path = out / "checkpoint.pt"
    data = bytearray(path.read_bytes())
    if damage == "truncate":
        data = data[: len(data) - 100]
    elif damage == "flip":
        data[len(data) // 2] ^= 0x40
    else:
        data = b""
    path.write_bytes(bytes(data))
    capsys.readouterr()
    assert main(["run", "--resume", str(out), "--steps", "400", "--quiet"]) == 2
    err = capsys.readouterr().err
    assert str(path) in err and ("truncated" in err or "corrupted" in err)
    assert path.read_bytes() == bytes(data)            # nothing overwritten


@pytest.mark.parametrize("name, args, message", [
    ("sdof-stiffness-damping", [], "the checkpoint's run has scenario 'sdof-stiffness', not 'sdof-stiffness-damping'"),
    ("sdof-stiffness", ["--batch", "3"], "has --batch 2, not 3"),
    ("sdof-stiffness", ["--seed", "5"], "has --seed 1, not 5"),
    ("sdof-stiffness", ["--dtype", "float32"], "has --dtype 'float64', not 'float32'"),
    ("sdof-stiffness", ["--set", "p0=1e4"], "--set p0=1e4 differs from the checkpoint's p0 = 1000.0"),
    ("sdof-stiffness", ["--set", "p00=1"], "unknown setting 'p00'"),
])
def test_resume_refuses_what_it_cannot_honour(name, args, message, tmp_path, capsys):
    out = tmp_path / "run"
    assert main(["run", "sdof-stiffness", "--batch", "2", "--out", str(out), *QUICK]) in (0, 1)
    before = (out / "checkpoint.pt").read_bytes()
    capsys.readouterr()
    assert main(["run", name, "--resume", str(out), "--steps", "400", "--quiet", *args]) == 2
    assert message in capsys.readouterr().err
    assert (out / "checkpoint.pt").read_bytes() == before
    # What matches the checkpoint is accepted.
    assert main(["run", "sdof-stiffness", "--resume", str(out), "--steps", "400", "--batch", "2", "--seed", "1",
                 "--dtype", "float64", "--set", "p0=1000", "--quiet", "--no-figures"]) in (0, 1)


def test_internal_error_exits_3_with_one_line_and_the_traceback_in_the_log(tmp_path, monkeypatch, capsys):
    import rcotorch.run.runner

    def broken(self):
        raise RuntimeError("something inside broke")
    monkeypatch.setattr(rcotorch.run.runner.Run, "_log", broken)
    out = tmp_path / "run"
    assert main(["run", "sdof-stiffness", "--out", str(out), *QUICK]) == 3
    err = capsys.readouterr().err
    assert err.count("\n") == 1
    assert err.startswith("rcotorch: internal error: RuntimeError: something inside broke (traceback in ")
    log = (out / "rcotorch.log").read_text()
    assert "Traceback (most recent call last)" in log and "something inside broke" in log


def test_out_of_memory_exits_2_before_anything_is_allocated(tmp_path):
    limit = 3 * 2 ** 30

    def cap():
        resource.setrlimit(resource.RLIMIT_AS, (limit, limit))
    proc = _cli("run", "sdof-stiffness", "--batch", "50000000", "--steps", "10", "--out", str(tmp_path / "o"),
                "--quiet", preexec_fn=cap)
    _, err = proc.communicate(timeout=300)
    assert proc.returncode == 2, err
    assert err.startswith("rcotorch: error: --batch 50000000: scenario 'sdof-stiffness' with nu = 15 and batch "
                          "50000000 needs at least") and "ulimit -v" in err and err.count("\n") == 1, err
    assert not (tmp_path / "o").exists()


@pytest.mark.parametrize("listening", [True, False])
def test_a_ray_address_where_nothing_answers_gives_up_within_30_s(listening, tmp_path, capsys, monkeypatch):
    """Nothing answers, so the check waits out its whole timeout: here 2 s instead of the shipped RAY_TIMEOUT
    (20 s), and the time the command takes with the shipped one (the time measured, less 2 s, plus RAY_TIMEOUT)
    must be under 30 s."""
    pytest.importorskip("ray")
    import rcotorch.run.sweep
    shipped, wait = rcotorch.run.sweep.RAY_TIMEOUT, 2.0
    monkeypatch.setattr(rcotorch.run.sweep, "RAY_TIMEOUT", wait)
    sock = socket.socket()
    sock.bind(("127.0.0.1", 0))
    port = sock.getsockname()[1]
    if listening:
        sock.listen(5)              # accepts connections, never answers
    else:
        sock.close()                # nothing there
    cfg = tmp_path / "sweep.toml"
    cfg.write_text('scenario = "sdof-stiffness"\nsteps = 50\n')
    start = time.monotonic()
    try:
        rc = main(["sweep", str(cfg), "--backend", "ray", "--ray-address", f"127.0.0.1:{port}",
                   "--out", str(tmp_path / "out")])
    finally:
        sock.close()
    taken = time.monotonic() - start
    assert rc == 2 and wait <= taken and taken - wait + shipped < 30, taken
    assert f"--ray-address 127.0.0.1:{port}: no Ray cluster answered within 2 s" in capsys.readouterr().err


# --- rcotorch tune NAME: the search space a scenario declares ------------------------------------------------
def test_tune_by_name_searches_the_declared_space_with_the_settings_given(tmp_path, capsys):
    """`rcotorch tune sdof-stiffness --set noise=0.05 --set lam=1 --trials 3`: the scenario's declared space
    (p0, lam, nu) less lam, held at 1 with the noise for every candidate; best.toml holds them as numbers and
    its comment gives a `rcotorch run` command that runs them."""
    import tomllib

    from rcotorch.run import scenario as scenarios
    out = tmp_path / "tune"
    assert main(["tune", "sdof-stiffness", "--set", "noise=0.05", "--set", "lam=1", "--trials", "3", "--seeds", "1",
                 "--steps", "600", "--out", str(out)]) == 0
    printed = capsys.readouterr().out
    assert "sdof-stiffness: 3 candidates x seeds = 3 members" in printed
    header = (out / "tune.csv").read_text().splitlines()[0].split(",")
    assert header[:3] == ["rank", "p0", "nu"] and "lam" not in header       # searched: the declared space less lam
    assert set(scenarios.get("sdof-stiffness").tuning_space) == {"p0", "lam", "nu"}
    text = (out / "best.toml").read_text()
    best = tomllib.loads(text)
    assert best["scenario"] == "sdof-stiffness" and best["settings"]["noise"] == 0.05
    assert best["settings"]["lam"] == 1.0 and set(best["settings"]) == {"noise", "lam", "p0", "nu"}
    [command] = [line[len("# run it: "):] for line in text.splitlines() if line.startswith("# run it: ")]
    assert command == f"rcotorch run sdof-stiffness --config {out / 'best.toml'} --steps 600"   # the steps scored
    argv = command.split()[1:]
    assert main([*argv, "--out", str(tmp_path / "run"), "--quiet", "--no-figures"]) in (0, 1)    # it runs
    summary = json.loads((tmp_path / "run" / "summary.json").read_text())
    assert summary["settings"]["noise"] == 0.05 and summary["steps"] == 600
    assert main(["tune", "sdof-stiffness", "--trials", "2", "--steps", "300", "--out", str(out)]) == 2
    assert "use --resume to continue it, --overwrite to replace it" in capsys.readouterr().err


@pytest.mark.parametrize("args, message", [
    (["silverbox-cubic-stiffness"], "tune: scenario 'silverbox-cubic-stiffness' declares no search space; give one "
                                    "in a tuning config file"),
    (["no-such-scenario"], "tune no-such-scenario: not a tuning config file (.toml or .json), and no scenario named "
                           "'no-such-scenario'"),
    (["sdof-stiffness", "--set", "m=0"], "--set m=0: scenario 'sdof-stiffness': setting m must be positive"),
    (["sdof-stiffness", "--set", "p0=1", "--set", "lam=1", "--set", "nu=3"], "nothing is left to search"),
    (["sdof-stiffness", "--trials", "0"], "--trials must be a positive integer, got 0"),
    (["sdof-stiffness", "--method", "grid", "--trials", "4"], "--trials is the number of candidates of a random or "
                                                              "tpe search"),
])
def test_tune_by_name_refuses_bad_input_with_exit_2(args, message, tmp_path, capsys):
    assert main(["tune", *args, "--out", str(tmp_path / "t")]) == 2
    err = capsys.readouterr().err
    assert message in err and err.count("\n") == 1 and not (tmp_path / "t").exists()


def test_a_stopped_tuning_says_how_to_resume_it_with_the_options_it_was_given():
    from rcotorch.run.cli import _tune_resume
    argv = ["tune", "sdof-stiffness", "--set", "noise=0.05", "--trials", "8", "--out", "runs/t", "--overwrite"]
    assert _tune_resume(argv, Path("runs/t")) == ("rcotorch tune sdof-stiffness --set noise=0.05 --trials 8 "
                                                  "--out runs/t --resume")
    assert _tune_resume(["tune", "my tune.toml", "--out=x"], Path("x")) == \
        "rcotorch tune 'my tune.toml' --out x --resume"
