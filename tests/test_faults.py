"""Fault injection: each fault the command line must survive, with its exit code and message shape (the table
"Faults and exit codes" in docs/cli.md). Signals are real (a subprocess is stopped by SIGTERM or SIGHUP); faults
of the file system are injected into an in-process ``main`` (a full disk by writes that raise ENOSPC, a folder
deleted or replaced under a running run).

Covered elsewhere, not repeated here: Ctrl-C with a bitwise resume, two writers on one folder and a writer killed
by SIGKILL then resumed (tests/test_cli.py); a second process refused by the folder's lock and a writer killed
mid-checkpoint (tests/test_outputs.py); truncated, emptied and flipped-byte checkpoints (both); a diverging
member frozen while the healthy ones stay bitwise those of a clean run (tests/test_runner.py)."""

import errno
import json
import os
import shlex
import shutil
import signal
import subprocess
import sys
import time
import types
from pathlib import Path

import pytest
import torch
from conftest import at_step, default_signals, wait_for

import rcotorch.run.runner
from rcotorch.errors import OutputError
from rcotorch.run.cli import Session, main
from rcotorch.run.outputs import LOCK, MANIFEST, OutputFolder, load_checkpoint, save_checkpoint

QUICK = ["--steps", "300", "--quiet", "--no-figures"]
ENOSPC = OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))


def _cli(*args) -> subprocess.Popen:
    env = dict(os.environ, PYTHONUNBUFFERED="1")
    return subprocess.Popen([sys.executable, "-m", "rcotorch", *args], stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, text=True, env=env, preexec_fn=default_signals)


def _stepping(proc: subprocess.Popen, folder: Path) -> None:
    """Wait until the run writing ``folder`` has started stepping (its TensorBoard file exists)."""
    wait_for(lambda: any(folder.glob("events.out.tfevents.*")) or proc.poll() is not None)
    assert proc.poll() is None, proc.communicate()


def _one_line(err: str) -> str:
    assert err.count("\n") == 1 and "Traceback" not in err and "Exception in thread" not in err, err
    return err


def _last_log_line(folder: Path) -> str:
    return (folder / "rcotorch.log").read_text().strip().splitlines()[-1]


def _estimates(folder: Path) -> dict:
    return json.loads((folder / "summary.json").read_text())["estimates"]


# --- signals ------------------------------------------------------------------------------------------------
@pytest.mark.parametrize("sig, code", [(signal.SIGTERM, 143), (signal.SIGHUP, 129)])
def test_sigterm_and_sighup_stop_a_run_like_ctrl_c(sig, code, tmp_path, monkeypatch):
    out = tmp_path / "run"
    proc = _cli("run", "sdof-stiffness", "--steps", "400000", "--out", str(out), "--quiet", "--no-figures",
                "--engine", "torch")
    _stepping(proc, out)
    proc.send_signal(sig)
    _, err = proc.communicate(timeout=120)
    assert proc.returncode == code, err
    assert f"resume with: rcotorch run --resume {out}" in err and "Traceback" not in err
    step = int(load_checkpoint(out / "checkpoint.pt")["graph"]["k"])
    assert 0 < step < 400000 and f"stopped at step {step} of 400000" in err
    name = signal.Signals(sig).name
    assert _last_log_line(out).endswith(f"stopped by {name} at step {step}; resume with: rcotorch run --resume {out}")
    if sig != signal.SIGTERM:
        return
    # The resume completes and equals a run that was never stopped (bitwise), both taken a little further.
    monkeypatch.setenv("RCOTORCH_ENGINE", "torch")         # main sets it from --engine; restored afterwards
    target = ["--steps", str(step + 137), "--quiet", "--no-figures", "--engine", "torch"]
    assert main(["run", "--resume", str(out), *target]) in (0, 1)
    assert main(["run", "sdof-stiffness", "--out", str(tmp_path / "full"), *target]) in (0, 1)
    assert _estimates(out) == _estimates(tmp_path / "full")
    resumed, full = load_checkpoint(out / "checkpoint.pt"), load_checkpoint(tmp_path / "full" / "checkpoint.pt")
    assert all(torch.equal(resumed["graph"][k], v) for k, v in full["graph"].items())


def test_a_signal_while_the_summary_is_written_stops_it_at_once(tmp_path, monkeypatch):
    """The summary's replays (intervals, held-out validation, a scenario's test sets) can take minutes on a GPU:
    a SIGTERM then stops the run at once with its final state saved, and the resume writes the summary that
    an uninterrupted run writes."""
    plain = rcotorch.run.runner.Run.summary
    calls = []

    def slow_summary(self):
        calls.append(self.k)
        if len(calls) == 1:
            os.kill(os.getpid(), signal.SIGTERM)
            deadline = time.monotonic() + 30
            while time.monotonic() < deadline:          # a long replay; the signal stops it
                time.sleep(0.01)
            raise AssertionError("the signal did not stop the summary")
        return plain(self)

    monkeypatch.setattr(rcotorch.run.runner.Run, "summary", slow_summary)
    out, full = tmp_path / "run", tmp_path / "full"
    previous = signal.getsignal(signal.SIGTERM)
    assert main(["run", "sdof-stiffness", "--out", str(out), *QUICK]) == 143
    assert signal.getsignal(signal.SIGTERM) is previous
    assert int(load_checkpoint(out / "checkpoint.pt")["graph"]["k"]) == 300 and not (out / "summary.json").exists()
    assert "stopped by SIGTERM while writing the summary at step 300" in _last_log_line(out)
    assert main(["run", "--resume", str(out), "--quiet", "--no-figures"]) in (0, 1)
    assert main(["run", "sdof-stiffness", "--out", str(full), *QUICK]) in (0, 1)
    assert _estimates(out) == _estimates(full) and calls == [300, 300, 300]


def test_an_ignored_signal_stays_ignored():
    """Under nohup SIGHUP is ignored: closing the terminal must not stop the run."""
    previous, term = signal.signal(signal.SIGHUP, signal.SIG_IGN), signal.getsignal(signal.SIGTERM)
    try:
        with Session(["run"]).interruptible():
            assert signal.getsignal(signal.SIGHUP) is signal.SIG_IGN
            assert signal.getsignal(signal.SIGTERM) not in (term, signal.SIG_IGN)
        assert signal.getsignal(signal.SIGTERM) is term
    finally:
        signal.signal(signal.SIGHUP, previous)


@pytest.mark.parametrize("config, workers, running, unstarted", [
    ("seeds = 2\n", [], ["shard_0000"], []),
    ("seeds = 4\nshard_size = 1\n", ["--workers", "2"], ["shard_0000", "shard_0001"], ["shard_0002", "shard_0003"]),
], ids=["in-process", "workers"])
def test_sigterm_stops_a_sweep_and_its_resume_equals_an_uninterrupted_sweep(config, workers, running, unstarted,
                                                                             tmp_path, monkeypatch):
    """One shard in the sweep's process, or two at once in worker processes (the signal forwarded to each): the
    running shards save their checkpoints, the sweep exits 143 saying so once, and the resume finishes them."""
    cfg = tmp_path / "sweep.toml"
    # On PyTorch about 4 s of steps; the signal, sent when the shards' TensorBoard files appear, stops them
    # within their first 10 steps (measured).
    cfg.write_text(f'scenario = "sdof-stiffness"\nsteps = 1500\n{config}')
    out = tmp_path / "sweep"
    flags = ["--threads", "1", "--engine", "torch"]
    monkeypatch.setenv("RCOTORCH_ENGINE", "torch")         # main sets it from --engine; restored afterwards
    proc = _cli("sweep", str(cfg), "--out", str(out), *workers, *flags)
    for shard in running:
        _stepping(proc, out / shard)
    proc.send_signal(signal.SIGTERM)
    _, err = proc.communicate(timeout=120)
    assert proc.returncode == 143, err
    resume = f"rcotorch sweep {cfg} --out {out} --resume"
    assert f"resume with: {resume}" in err and "Traceback" not in err
    assert err.count("SIGTERM received") == 1, err
    for shard in running:
        assert 0 < load_checkpoint(out / shard / "checkpoint.pt")["graph"]["k"] < 1500
        assert not (out / shard / "summary.json").exists()
    assert not any((out / shard).exists() for shard in unstarted)
    assert _last_log_line(out).endswith(f"stopped by SIGTERM; resume with: {resume}")
    assert main(["sweep", str(cfg), "--out", str(out), "--resume", *workers, *flags]) == 0
    assert main(["sweep", str(cfg), "--out", str(tmp_path / "full"), "--workers", "1", *flags]) == 0

    def estimates(folder):
        return [{k: v for k, v in row.items() if k.startswith("est_")}
                for row in json.loads((folder / "sweep.json").read_text())]
    assert estimates(out) == estimates(tmp_path / "full")


# --- a full disk --------------------------------------------------------------------------------------------
def test_a_full_disk_under_the_event_writer_exits_2_with_one_line(tmp_path, monkeypatch, capsys):
    """The TensorBoard event file meets the full disk first: one line on stderr, the traceback in the log."""
    from rcotorch.run.event_file import EventFile
    out = tmp_path / "run"
    write = EventFile._write

    def full(self, event):
        if self.path.parent == out:
            raise ENOSPC
        return write(self, event)
    monkeypatch.setattr(EventFile, "_write", full)
    assert main(["run", "sdof-stiffness", "--out", str(out), *QUICK]) == 2
    err = _one_line(capsys.readouterr().err)
    assert err.startswith(f"rcotorch: error: cannot write to the output folder {out}: No space left on device; "
                          f"free space on its disk or choose another --out (traceback in {out / 'rcotorch.log'})")
    log = (out / "rcotorch.log").read_text()
    assert "Traceback" in log and "No space left on device" in log
    OutputFolder(out, "run").check_free()                    # the lock is released
    monkeypatch.undo()                                       # space freed: the run can be replaced
    assert main(["run", "sdof-stiffness", "--out", str(out), *QUICK, "--overwrite"]) in (0, 1)


def test_a_disk_that_fills_at_a_checkpoint_keeps_the_last_one_and_the_run_resumes(tmp_path, monkeypatch, capsys):
    out = tmp_path / "run"
    save, calls = torch.save, []

    def filling(obj, f, *args, **kw):
        calls.append(1)
        if len(calls) == 2:
            f.write(b"half a checkpoint")
            raise ENOSPC
        return save(obj, f, *args, **kw)
    monkeypatch.setattr(torch, "save", filling)
    assert main(["run", "sdof-stiffness", "--out", str(out), *QUICK, "--checkpoint-every", "100"]) == 2
    err = _one_line(capsys.readouterr().err)
    assert err.startswith(f"rcotorch: error: cannot write {out / 'checkpoint.pt'}: No space left on device; free "
                          f"space on its disk or choose another --out; then resume with: rcotorch run --resume {out} "
                          "--checkpoint-every 100 (traceback in ")
    assert load_checkpoint(out / "checkpoint.pt")["graph"]["k"] == 100
    assert sorted(p.name for p in out.iterdir() if p.name.startswith(".rcotorch-tmp")) == []
    monkeypatch.undo()
    assert main(["run", "--resume", str(out), "--quiet", "--no-figures"]) in (0, 1)
    assert json.loads((out / "summary.json").read_text())["steps"] == 300


def test_a_full_disk_when_the_folder_is_opened_leaves_nothing_behind(tmp_path, monkeypatch, capsys):
    out = tmp_path / "new" / "run"

    def full(fd):
        raise ENOSPC
    monkeypatch.setattr(os, "fsync", full)
    assert main(["run", "sdof-stiffness", "--out", str(out), *QUICK]) == 2
    err = _one_line(capsys.readouterr().err)
    assert f"cannot write {out / MANIFEST}: No space left on device; free space on its disk" in err
    assert not out.exists()                                  # no folder, lock file or manifest left
    monkeypatch.undo()
    assert main(["run", "sdof-stiffness", "--out", str(out), *QUICK]) in (0, 1)


# --- the output folder --------------------------------------------------------------------------------------
def test_the_output_folder_deleted_during_a_run_exits_2(tmp_path, monkeypatch, capsys):
    out = tmp_path / "run"
    at_step(monkeypatch, 100, shutil.rmtree)
    assert main(["run", "sdof-stiffness", "--out", str(out), *QUICK]) == 2
    err = _one_line(capsys.readouterr().err)
    assert f"the output folder {out} was deleted while rcotorch was writing to it" in err and "run again" in err
    # nothing of the run is there again but what TensorBoard's writer, which writes by path, may have recreated
    assert not out.exists() or all(p.name.startswith("events.out.tfevents") for p in out.rglob("*") if p.is_file())


def test_the_output_folder_replaced_during_a_run_exits_2_and_the_new_one_is_not_written(tmp_path, monkeypatch,
                                                                                        capsys):
    out = tmp_path / "run"

    def replace(folder):
        folder.rename(tmp_path / "moved")
        folder.mkdir()
        (folder / "summary.json").write_text("the user's")
    at_step(monkeypatch, 100, replace)
    assert main(["run", "sdof-stiffness", "--out", str(out), *QUICK, "--checkpoint-every", "50"]) == 2
    err = _one_line(capsys.readouterr().err)
    assert f"the output folder {out} was replaced by another folder while rcotorch was writing to it" in err
    assert (out / "summary.json").read_text() == "the user's" and not (out / "checkpoint.pt").exists()
    assert load_checkpoint(tmp_path / "moved" / "checkpoint.pt")["graph"]["k"] == 50   # none at step 100


@pytest.mark.parametrize("filename, code", [("inside", 2), ("elsewhere", 3)])
def test_an_oserror_is_exit_2_when_it_names_the_output_folder_and_exit_3_otherwise(filename, code, tmp_path,
                                                                                    monkeypatch, capsys):
    out = tmp_path / "run"
    path = out / "estimates.png" if filename == "inside" else tmp_path / "somewhere" / "cache.bin"

    def broken(self):
        raise PermissionError(errno.EACCES, "Permission denied", str(path))
    monkeypatch.setattr(rcotorch.run.runner.Run, "_log", broken)
    assert main(["run", "sdof-stiffness", "--out", str(out), *QUICK]) == code
    err = _one_line(capsys.readouterr().err)
    if code == 2:
        assert err.startswith(f"rcotorch: error: cannot write {path}: Permission denied; choose a folder you may "
                              "write to with --out")
    else:
        assert err.startswith("rcotorch: internal error: PermissionError")


@pytest.mark.parametrize("link, message", [
    ("loop", "is a symbolic link loop (following it leads back to it); fix the link or choose another --out"),
    ("missing", "is a symbolic link to"),
])
def test_an_out_that_is_a_broken_symbolic_link_says_so(link, message, tmp_path, capsys):
    out = tmp_path / "out"
    out.symlink_to(out if link == "loop" else tmp_path / "nowhere")
    assert main(["run", "sdof-stiffness", "--out", str(out), *QUICK]) == 2
    err = _one_line(capsys.readouterr().err)
    assert f"{out} {message}" in err and "File exists" not in err
    assert main(["run", "sdof-stiffness", "--out", str(out / "sub"), *QUICK]) == 2
    assert "symbolic link" in _one_line(capsys.readouterr().err)


def test_a_folder_held_by_another_writer_is_refused_and_free_once_released(tmp_path, capsys):
    out = tmp_path / "run"
    holder = OutputFolder(out, "run").open("new", info={"scenario": "sdof-stiffness"})
    before = (out / MANIFEST).read_bytes()
    assert main(["run", "sdof-stiffness", "--out", str(out), *QUICK, "--overwrite"]) == 2
    assert "is in use: another rcotorch run is writing to it" in _one_line(capsys.readouterr().err)
    assert (out / MANIFEST).read_bytes() == before
    holder.close()
    assert main(["run", "sdof-stiffness", "--out", str(out), *QUICK, "--overwrite"]) in (0, 1)


# --- checkpoints --------------------------------------------------------------------------------------------
@pytest.fixture
def finished_run(tmp_path) -> Path:
    out = tmp_path / "run"
    assert main(["run", "sdof-stiffness", "--out", str(out), *QUICK]) in (0, 1)
    return out


class _Code:
    """Unpickling it would make a folder: what a hostile checkpoint's payload could do instead."""

    def __init__(self, path: Path):
        self.path = path

    def __reduce__(self):
        return os.mkdir, (str(self.path),)


def test_a_hostile_checkpoint_is_refused_in_one_line_and_never_run(finished_run, tmp_path, capsys):
    path = finished_run / "checkpoint.pt"
    state = load_checkpoint(path)
    state["settings"] = _Code(tmp_path / "ran")
    save_checkpoint(path, state)                             # its hash is right
    before = path.read_bytes()
    capsys.readouterr()
    assert main(["run", "--resume", str(finished_run), "--steps", "400", "--quiet"]) == 2
    err = _one_line(capsys.readouterr().err)
    assert err.startswith(f"rcotorch: error: {path}: refused: the checkpoint holds posix.mkdir, and loading it "
                          "could run code")
    assert "weights_only" not in err and not (tmp_path / "ran").exists() and path.read_bytes() == before


@pytest.mark.parametrize("damage, message", [
    ("shape", "size mismatch for blocks.identified.theta"),
    ("missing", "missing 'health'"),
    ("sums", "sums: z has shape (5,), not (1,)"),
    ("unknown", "graph: unknown blocks.extra"),
    ("not a table", "graph: a list, not a table"),
])
def test_a_checkpoint_with_a_valid_hash_but_another_layout_exits_2(damage, message, finished_run, capsys):
    path = finished_run / "checkpoint.pt"
    state = load_checkpoint(path)
    if damage == "shape":
        state["graph"]["blocks.identified.theta"] = torch.zeros(3, 7, dtype=torch.float64)
    elif damage == "missing":
        del state["health"]
    elif damage == "sums":
        state["sums"]["z"] = torch.zeros(5, dtype=torch.float64)
    elif damage == "unknown":
        state["graph"]["blocks.extra"] = torch.zeros(1)
    else:
        state["graph"] = [1, 2]
    save_checkpoint(path, state)
    before = path.read_bytes()
    capsys.readouterr()
    assert main(["run", "--resume", str(finished_run), "--steps", "400", "--quiet"]) == 2
    err = _one_line(capsys.readouterr().err)
    assert err.startswith(f"rcotorch: error: {path}: the checkpoint does not hold a run this version can continue (")
    assert message in err and err.rstrip().endswith("; start the run again")
    assert path.read_bytes() == before


# --- sweeps -------------------------------------------------------------------------------------------------
def test_a_sweep_config_that_is_not_utf8_exits_2_naming_it(tmp_path, capsys):
    cfg = tmp_path / "sweep.toml"
    cfg.write_bytes('scenario = "sdof-stiffness"\n# r\xe9sum\xe9\n'.encode("latin-1"))
    assert main(["sweep", str(cfg), "--out", str(tmp_path / "out")]) == 2
    err = _one_line(capsys.readouterr().err)
    assert f"{cfg}: not UTF-8 text (byte 0xe9 at offset 31); save the config as UTF-8" in err
    assert not (tmp_path / "out").exists()


def _no_ray(monkeypatch):
    monkeypatch.setitem(sys.modules, "ray", None)            # `import ray` fails, installed or not


def _ray_that_cannot_start(monkeypatch):
    def init(**kw):
        raise ConnectionError("no Ray here")
    monkeypatch.setitem(sys.modules, "ray", types.SimpleNamespace(is_initialized=lambda: False, init=init))


@pytest.mark.parametrize("ray, message", [(_no_ray, "the ray backend needs Ray: pip install"),
                                          (_ray_that_cannot_start, "cannot start Ray here: no Ray here")])
def test_a_sweep_refused_for_ray_leaves_no_manifest_or_lock(ray, message, tmp_path, monkeypatch, capsys):
    cfg = tmp_path / "sweep.toml"
    cfg.write_text('scenario = "sdof-stiffness"\nsteps = 50\n')
    out = tmp_path / "out"
    out.mkdir()
    (out / "notes.txt").write_text("mine")
    ray(monkeypatch)
    assert main(["sweep", str(cfg), "--backend", "ray", "--out", str(out)]) == 2
    assert message in _one_line(capsys.readouterr().err)
    assert sorted(os.listdir(out)) == ["notes.txt"]
    assert main(["sweep", str(cfg), "--backend", "ray", "--out", str(tmp_path / "fresh")]) == 2
    assert not (tmp_path / "fresh").exists()
    assert main(["sweep", str(cfg), "--out", str(out)]) == 0           # the plain re-run
    assert (out / "notes.txt").read_text() == "mine" and (out / LOCK).exists()


def test_a_reader_that_stops_reading_stdout_is_no_internal_error():
    """`rcotorch show NAME | true`: the pipe is closed before rcotorch writes; it exits 0, with no traceback."""
    cmd = f"set -o pipefail; {shlex.quote(sys.executable)} -m rcotorch show sdof-stiffness | true"
    out = subprocess.run(["bash", "-c", cmd], capture_output=True, text=True, timeout=120)
    assert out.returncode == 0, (out.returncode, out.stderr)
    assert "Traceback" not in out.stderr and "BrokenPipeError" not in out.stderr


def test_a_deleted_folder_that_tensorboards_writer_made_again_is_reported_as_deleted(tmp_path):
    """TensorBoard's writer writes by path and may make the deleted folder again for its event file: that is
    still a deleted folder (the results are lost), not one a user put in its place."""
    folder = OutputFolder(tmp_path / "run", "run")
    folder.open("new", info={"scenario": "x"})
    shutil.rmtree(tmp_path / "run")
    (tmp_path / "run").mkdir()
    (tmp_path / "run" / "events.out.tfevents.1.host").write_bytes(b"")
    with pytest.raises(OutputError, match="was deleted while rcotorch was writing to it"):
        folder.check()
    (tmp_path / "run" / "notes.txt").write_text("the user's")
    with pytest.raises(OutputError, match="was replaced by another folder"):
        folder.check()
