"""Nothing outside an output folder is ever deleted, replaced or appended to, whatever its manifest says: the
faults of an edited manifest (``..``, absolute paths, a child folder that is another run, links inside the folder
that point out) and of a log that is a link, each reproduced through the command line and ``OutputFolder``."""

import json
import os

import pytest

from rcotorch.errors import OutputError
from rcotorch.run.cli import main
from rcotorch.run.outputs import LOCK, MANIFEST, OutputFolder, inside

QUICK = ["--steps", "300", "--quiet", "--no-figures"]


def _edit(folder, **changes):
    path = folder / MANIFEST
    manifest = json.loads(path.read_text())
    for key, more in changes.items():
        manifest[key] = manifest.get(key, []) + more
    path.write_text(json.dumps(manifest))


@pytest.fixture(scope="module")
def first_run(tmp_path_factory):
    """A finished run's folder, copied afresh for every test that edits it."""
    out = tmp_path_factory.mktemp("first") / "X"
    assert main(["run", "sdof-stiffness", *QUICK, "--out", str(out)]) in (0, 1)   # 300 steps: dK short of its tolerance
    return out


@pytest.fixture
def run(first_run, tmp_path):
    import shutil
    out = tmp_path / "X"
    shutil.copytree(first_run, out)
    return out


def _victims(tmp_path):
    victim = tmp_path / "victim.txt"
    victim.write_text("the user's")
    absolute = tmp_path / "elsewhere" / "precious.txt"
    absolute.parent.mkdir()
    absolute.write_text("also the user's")
    return victim, absolute


@pytest.mark.parametrize("entry", ["../victim.txt", "ABSOLUTE", "a/../../victim.txt", "./../victim.txt",
                                   "linked/precious.txt"])
def test_overwrite_refuses_a_manifest_entry_outside_the_folder_and_deletes_nothing(entry, run, tmp_path, capsys):
    victim, absolute = _victims(tmp_path)
    (run / "linked").symlink_to(absolute.parent)          # a link inside the folder that points out
    entry = str(absolute) if entry == "ABSOLUTE" else entry
    _edit(run, files=[entry])
    before = sorted(p.name for p in run.iterdir())
    assert main(["run", "sdof-stiffness", *QUICK, "--out", str(run), "--overwrite"]) == 2
    err = capsys.readouterr().err
    assert repr(entry) in err and "refused" in err, err
    assert victim.read_text() == "the user's" and absolute.read_text() == "also the user's"
    assert sorted(p.name for p in run.iterdir()) == before             # nothing of the earlier run deleted either


@pytest.mark.parametrize("child", ["../other-run", "OTHER_ABSOLUTE", "inner/../../other-run", "link-to-other"])
def test_overwrite_refuses_a_child_that_is_another_runs_folder(child, run, first_run, tmp_path, capsys):
    import shutil
    other = tmp_path / "other-run"
    shutil.copytree(first_run, other)
    kept = sorted(str(p.relative_to(other)) for p in other.rglob("*"))
    (run / "link-to-other").symlink_to(other)
    child = str(other) if child == "OTHER_ABSOLUTE" else child
    _edit(run, children=[child])
    assert main(["run", "sdof-stiffness", *QUICK, "--out", str(run), "--overwrite"]) == 2
    assert repr(child) in capsys.readouterr().err
    assert sorted(str(p.relative_to(other)) for p in other.rglob("*")) == kept


def test_a_clean_manifest_is_still_overwritten(run, capsys):
    (run / "notes.txt").write_text("mine")
    assert main(["run", "sdof-stiffness", *QUICK, "--out", str(run), "--overwrite"]) in (0, 1)
    assert (run / "notes.txt").read_text() == "mine" and (run / "summary.json").is_file()


def test_resume_does_not_append_to_a_log_that_links_outside(tmp_path, capsys):
    out = tmp_path / "X"
    assert main(["run", "sdof-stiffness", "--steps", "300", "--quiet", "--no-figures", "--out", str(out)]) in (0, 1)
    outside = tmp_path / "outside.log"
    outside.write_text("the user's log\n")
    (out / "rcotorch.log").unlink()
    (out / "rcotorch.log").symlink_to(outside)
    code = main(["run", "--resume", str(out), "--steps", "400", "--quiet", "--no-figures"])
    assert code == 2 and "rcotorch.log is a symbolic link" in capsys.readouterr().err
    assert outside.read_text() == "the user's log\n"


@pytest.mark.parametrize("name", [LOCK, MANIFEST, "summary.json", "hparams", "shard_0001"])
def test_a_folder_whose_written_names_are_links_is_refused_before_anything_is_written(name, tmp_path):
    target = tmp_path / "target"
    target.mkdir()
    (target / "f").write_text("the user's")
    out = tmp_path / "X"
    out.mkdir()
    (out / name).symlink_to(target / "f" if name in (LOCK, MANIFEST, "summary.json") else target)
    for mode in ("new", "overwrite", "resume"):
        with pytest.raises(OutputError, match="is a symbolic link .* where rcotorch writes"):
            OutputFolder(out, "run").open(mode)
    assert (target / "f").read_text() == "the user's" and sorted(os.listdir(target)) == ["f"]


def test_inside_names_what_it_refuses(tmp_path):
    (tmp_path / "real").mkdir()
    assert inside(tmp_path, "real/x.png", "e") == tmp_path / "real" / "x.png"
    assert inside(tmp_path, "./a.png", "e") == tmp_path / "a.png"
    for rel, why in [("", "not a file name"), (3, "not a file name"), ("/etc/passwd", "absolute"),
                     ("a/../../x", "'..'"), ("..", "'..'")]:
        with pytest.raises(OutputError, match=why):
            inside(tmp_path, rel, "the entry")


def test_a_sweep_and_a_tune_folder_follow_the_same_rule(tmp_path):
    """A sweep's root lists its shards as children: an edited child that leads out is refused the same way."""
    from rcotorch.run.outputs import OutputFolder as F
    root = tmp_path / "sweep"
    folder = F(root, "sweep").open("new")
    (root / "shard_0000").mkdir()
    shard = F(root / "shard_0000", "run").open("new")
    (root / "shard_0000" / "summary.json").write_text("{}")
    shard.close()
    folder.add_child("shard_0000")
    folder.close()
    victim = tmp_path / "victim.txt"
    victim.write_text("v")
    _edit(root / "shard_0000", files=["../../victim.txt"])
    with pytest.raises(OutputError, match=r"refused: .*'\.\./\.\./victim\.txt' climbs out"):
        F(root, "sweep").open("overwrite")
    assert victim.read_text() == "v" and (root / "shard_0000" / "summary.json").exists()
