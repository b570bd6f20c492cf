"""Output folders: nothing deleted that a run did not write, one writer at a time, atomic files, checkpoints
with a checksum. Each fault is reproduced: a second writer (another process), a killed writer, truncated and
flipped-byte checkpoints, files that are not ours."""

import json
import os
import subprocess
import sys
import textwrap

import pytest
import torch

from rcotorch.errors import CheckpointError, OutputError
from rcotorch.run.outputs import LOCK, MANIFEST, OutputFolder, atomic_write, load_checkpoint, save_checkpoint


def _files(path):
    return sorted(str(p.relative_to(path)) for p in path.rglob("*") if p.is_file())


def test_new_folder_lists_only_what_it_wrote(tmp_path):
    (tmp_path / "notes.txt").write_text("mine")
    folder = OutputFolder(tmp_path, "run").open("new", info={"scenario": "x"})
    (tmp_path / "a.png").write_bytes(b"png")
    (tmp_path / "sub").mkdir()
    (tmp_path / "sub" / "b.txt").write_text("b")
    folder.close()
    manifest = json.loads((tmp_path / MANIFEST).read_text())
    assert manifest["files"] == ["a.png", "sub/b.txt"] and manifest["scenario"] == "x"


def test_a_folder_with_a_run_is_refused_and_overwrite_deletes_only_its_files(tmp_path):
    first = OutputFolder(tmp_path, "run").open("new")
    (tmp_path / "summary.json").write_text("{}")
    (tmp_path / "hparams").mkdir()
    (tmp_path / "hparams" / "events.out.tfevents.1").write_text("e")
    first.close()
    (tmp_path / "notes.txt").write_text("the user's")        # added after the run, by the user
    with pytest.raises(OutputError, match="already holds a run.*--resume.*--overwrite"):
        OutputFolder(tmp_path, "run").open("new")
    assert (tmp_path / "summary.json").exists()
    second = OutputFolder(tmp_path, "run").open("overwrite")
    assert not (tmp_path / "summary.json").exists() and not (tmp_path / "hparams").exists()
    assert (tmp_path / "notes.txt").read_text() == "the user's"
    second.close()
    assert json.loads((tmp_path / MANIFEST).read_text())["files"] == []


def test_results_without_a_manifest_are_never_touched(tmp_path):
    for name in ("summary.json", "checkpoint.pt", "estimates.png"):
        (tmp_path / name).write_text("old")
    for mode in ("new", "overwrite", "resume"):
        with pytest.raises(OutputError, match="no rcotorch manifest lists"):
            OutputFolder(tmp_path, "run").open(mode)
    assert all((tmp_path / n).read_text() == "old" for n in ("summary.json", "checkpoint.pt", "estimates.png"))


def test_unrelated_files_may_stay_beside_a_run(tmp_path):
    (tmp_path / "notes.txt").write_text("mine")
    OutputFolder(tmp_path, "run").open("new").close()
    assert (tmp_path / "notes.txt").read_text() == "mine"


def test_out_that_is_a_file_is_refused(tmp_path):
    f = tmp_path / "file"
    f.write_text("x")
    with pytest.raises(OutputError, match="is a file"):
        OutputFolder(f, "run").open()
    assert f.read_text() == "x"


HOLD = textwrap.dedent("""
    import sys, time
    from rcotorch.run.outputs import OutputFolder
    folder = OutputFolder(sys.argv[1], "run").open("new")
    print("locked", flush=True)
    time.sleep(60)
""")


def test_a_second_writer_fails_at_once_while_another_process_holds_the_folder(tmp_path):
    holder = subprocess.Popen([sys.executable, "-c", HOLD, str(tmp_path)], stdout=subprocess.PIPE, text=True)
    try:
        assert holder.stdout.readline().strip() == "locked"
        with pytest.raises(OutputError, match="is in use"):
            OutputFolder(tmp_path, "run").open("overwrite")
    finally:
        holder.kill()
        holder.wait()
    # A killed holder leaves its lock file, but not the lock: the folder can be resumed at once.
    assert (tmp_path / LOCK).exists()
    OutputFolder(tmp_path, "run").open("resume").close()


def test_atomic_write_keeps_the_old_file_when_writing_fails(tmp_path):
    target = tmp_path / "summary.json"
    target.write_text("old")

    def fail(f):
        f.write(b"half")
        raise RuntimeError("disk full")
    with pytest.raises(RuntimeError):
        atomic_write(target, fail)
    assert target.read_text() == "old" and _files(tmp_path) == ["summary.json"]


def test_checkpoint_round_trip_and_every_damage_is_named(tmp_path):
    path = tmp_path / "checkpoint.pt"
    state = {"x": torch.arange(1000, dtype=torch.float64), "settings": {"p0": 1e3, "seed": [1, 2]}}
    save_checkpoint(path, state)
    back = load_checkpoint(path)
    assert torch.equal(back["x"], state["x"]) and back["settings"] == state["settings"]
    data = path.read_bytes()
    path.write_bytes(data[: len(data) // 2])
    with pytest.raises(CheckpointError, match=r"checkpoint.pt: the checkpoint is truncated: \d+ of \d+ bytes"):
        load_checkpoint(path)
    path.write_bytes(b"")
    with pytest.raises(CheckpointError, match="truncated: 0 bytes"):
        load_checkpoint(path)
    for position in (len(data) // 3, len(data) - 1):     # inside the payload, at its very end
        flipped = bytearray(data)
        flipped[position] ^= 0x01
        path.write_bytes(bytes(flipped))
        with pytest.raises(CheckpointError, match="checkpoint.pt: the checkpoint is corrupted"):
            load_checkpoint(path)
    flipped = bytearray(data)
    flipped[30] ^= 0x01                                    # inside the header's hash
    path.write_bytes(bytes(flipped))
    with pytest.raises(CheckpointError, match="checkpoint.pt"):
        load_checkpoint(path)
    torch.save(state, path)                                # a plain torch file, not ours
    with pytest.raises(CheckpointError, match="not an rcotorch checkpoint"):
        load_checkpoint(path)


KILLED_WRITER = textwrap.dedent("""
    import os, sys, torch
    from rcotorch.run.outputs import save_checkpoint
    class Boom:
        def __reduce__(self):   # runs in the middle of torch.save, after part of the file is written
            os._exit(9)
    save_checkpoint(sys.argv[1], {"x": torch.zeros(100000), "boom": Boom()})
""")


def test_a_writer_killed_mid_checkpoint_leaves_the_previous_checkpoint(tmp_path):
    path = tmp_path / "checkpoint.pt"
    folder = OutputFolder(tmp_path, "run").open("new")
    save_checkpoint(path, {"step": 7})
    folder.close()
    res = subprocess.run([sys.executable, "-c", KILLED_WRITER, str(path)])
    assert res.returncode == 9
    assert load_checkpoint(path) == {"step": 7}
    leftovers = [f for f in os.listdir(tmp_path) if f not in ("checkpoint.pt", LOCK, MANIFEST)]
    assert len(leftovers) == 1 and leftovers[0].startswith(".rcotorch-tmp-checkpoint.pt.")
    # Opening the folder again (resume or overwrite) clears such temporaries of its own writer.
    folder = OutputFolder(tmp_path, "run").open("resume")
    folder.close()
    assert sorted(os.listdir(tmp_path)) == sorted(["checkpoint.pt", LOCK, MANIFEST])
