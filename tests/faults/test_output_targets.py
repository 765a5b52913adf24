"""An output path is a new file or a regular one (issue 30, item 1): a device node, a FIFO, a
socket, a folder, a link to one of them or to nothing is refused in one line that says what it
is, and is left as it was; a regular file is replaced through a temporary file beside it (a
symbolic link to one is written through and stays a link), so a failed write leaves the old
file or nothing. No test here replaces a real /dev node: devices are nodes made in tmp_path
(as root) and /dev nodes are only checked for refusal."""

import errno
import os
import socket
import stat
import tempfile
from pathlib import Path

import pytest
from hypothesis import given
from hypothesis import strategies as st

from dmdsm.host.commands.cli import main
from dmdsm.host.files import OutputError, atomic_output, check_output

ROOT = os.geteuid() == 0

# kind -> what the refusal says it is ("" for the kinds that may be written)
WHAT = {"new": "", "regular": "", "symlink to regular": "",
        "folder": "a folder", "fifo": "a FIFO", "socket": "a socket",
        "device": "a character device", "dangling symlink": "a symbolic link to nothing",
        "symlink to device": "a symbolic link to a character device",
        "symlink to fifo": "a symbolic link to a FIFO",
        "symlink to folder": "a symbolic link to a folder"}
REFUSED = sorted(k for k, v in WHAT.items() if v)
EARLIER = b"earlier data"


def _device(where: Path) -> Path:
    """A character device node of our own (/dev/null's numbers) when root, so a bug can
    break no system device; else /dev/null itself, which a non-root user cannot replace."""
    node = where / "null-node"
    if ROOT:
        if not node.exists():
            os.mknod(node, stat.S_IFCHR | 0o600, os.makedev(1, 3))
        return node
    return Path("/dev/null")


def make_target(kind: str, where: Path, name: str = "out.h5") -> Path:
    """An output path of this kind in the folder `where`."""
    path = where / name
    if kind == "regular":
        path.write_bytes(EARLIER)
    elif kind == "folder":
        path.mkdir()
    elif kind == "fifo":
        os.mkfifo(path)
    elif kind == "socket":
        s = socket.socket(socket.AF_UNIX)
        s.bind(str(path))
        s.close()
    elif kind == "device":
        if ROOT:
            os.mknod(path, stat.S_IFCHR | 0o600, os.makedev(1, 3))
        else:
            path = Path("/dev/null")
    elif kind == "symlink to regular":
        (where / "real.dat").write_bytes(EARLIER)
        path.symlink_to(where / "real.dat")
    elif kind == "dangling symlink":
        path.symlink_to(where / "nowhere.dat")
    elif kind == "symlink to device":
        path.symlink_to(_device(where))
    elif kind == "symlink to fifo":
        os.mkfifo(where / "pipe")
        path.symlink_to(where / "pipe")
    elif kind == "symlink to folder":
        (where / "sub").mkdir()
        path.symlink_to(where / "sub")
    return path


def snapshot(path: Path) -> tuple:
    """What must not change when an output is refused or fails: the node and its bytes."""
    st_ = os.lstat(path)
    regular = os.path.exists(path) and stat.S_ISREG(os.stat(path).st_mode)
    data = path.read_bytes() if regular else None
    return stat.S_IFMT(st_.st_mode), st_.st_ino, data


def listing(folder: Path) -> list[str]:
    """Every name in the folder (a temporary file left behind shows here)."""
    return sorted(os.listdir(folder))


# ---------------------------------------------------------------- the shared helper


@given(kind=st.sampled_from(sorted(WHAT)), force=st.booleans(),
       data=st.binary(max_size=2000), fail=st.booleans())
def test_atomic_output_writes_a_new_or_regular_file_and_refuses_everything_else(
        kind, force, data, fail):
    with tempfile.TemporaryDirectory() as d:
        where = Path(d)
        path = make_target(kind, where)
        before = snapshot(path) if os.path.lexists(path) else None
        names = listing(where)
        allowed = kind == "new" or (force and kind in ("regular", "symlink to regular"))
        if not allowed:
            with pytest.raises(OutputError) as e:
                with atomic_output(path, force=force, flag="--ply") as tmp:
                    tmp.write_bytes(data)
            text = str(e.value)
            assert "\n" not in text and str(path) in text and "--force" in text \
                if kind in ("regular", "symlink to regular") else WHAT[kind] in text, text
            assert snapshot(path) == before and listing(where) == names
            return
        try:
            with atomic_output(path, force=force, flag="--ply") as tmp:
                assert tmp.parent == Path(os.path.realpath(path)).parent
                with open(tmp, "wb") as f:
                    f.write(data[:len(data) // 2])
                    if fail:  # the disk fills partway
                        raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))
                    f.write(data[len(data) // 2:])
        except OutputError as e:
            assert fail and "no space left on the device holding" in str(e)
            assert str(path) in str(e) and "--ply" in str(e)
            assert listing(where) == names  # no temporary file left
            if before is not None:
                assert snapshot(path) == before  # the old file as it was
            return
        assert not fail
        assert path.read_bytes() == data
        if kind == "symlink to regular":  # written through: the link stays a link
            assert path.is_symlink() and (where / "real.dat").read_bytes() == data
        assert listing(where) == sorted({*names, path.name})


@given(mode=st.sampled_from([0o600, 0o640, 0o644, 0o755]))
def test_a_replaced_file_keeps_its_permissions_and_a_new_one_gets_the_umasks(mode):
    with tempfile.TemporaryDirectory() as d:
        old, new = Path(d) / "old.csv", Path(d) / "new.csv"
        old.write_text("a")
        old.chmod(mode)
        for path in (old, new):
            with atomic_output(path) as tmp:
                tmp.write_text("b")
        assert stat.S_IMODE(old.stat().st_mode) == mode
        umask = os.umask(0)
        os.umask(umask)
        assert stat.S_IMODE(new.stat().st_mode) == 0o666 & ~umask


@pytest.mark.parametrize("path, words", [
    ("/dev/null", "a character device"),
    ("/dev/full", "a character device"),
    ("/dev/stdout", "a symbolic link to a process's open file"),
    ("/dev/fd/1", "a symbolic link to a process's open file"),
    ("/proc/self/fd/2", "a symbolic link to a process's open file"),
])
def test_system_nodes_and_a_process_s_open_files_are_refused(path, words):
    """Only checked, never written: a bug here must not replace a real /dev node."""
    assert os.path.lexists(path), f"{path} exists on every Linux system"
    with pytest.raises(OutputError) as e:
        check_output(Path(path))
    assert words in str(e.value) and "give a new file path" in str(e.value)


def test_a_temporary_file_keeps_the_targets_suffix_for_writers_that_read_it(tmp_path):
    """matplotlib's savefig and numpy's savetxt choose the format from the file name."""
    for name in ("fig.png", "noext", "two.dots.csv.gz"):
        with atomic_output(tmp_path / name) as tmp:
            assert tmp.suffix == Path(name).suffix and tmp.name.startswith(".")
            tmp.write_text("x")
    assert listing(tmp_path) == ["fig.png", "noext", "two.dots.csv.gz"]


def test_an_interrupted_write_leaves_the_old_file_and_no_temporary_file(tmp_path):
    path = tmp_path / "r.json"
    path.write_bytes(EARLIER)
    with pytest.raises(KeyboardInterrupt), atomic_output(path) as tmp:
        tmp.write_text("half")
        raise KeyboardInterrupt
    assert path.read_bytes() == EARLIER and listing(tmp_path) == ["r.json"]


# ---------------------------------------------------------------- through the commands


COMMANDS = {  # argv before the output path, and whether the command has --force
    "acquire --force": ["acquire", "--sensor", "loop://", "--shots", "3", "--force", "-o"],
    "acquire": ["acquire", "--sensor", "loop://", "--shots", "3", "-o"],
    "classify train": ["classify", "train", "--db", "{db}", "-o"],
    "calibrate": ["calibrate", "--from-data", "{rig}", "-o"],
    "calibrate-range": ["calibrate-range", "-x", "235", "-y", "266", "-z", "20",
                        "--start-distance", "7.2", "--sensor", "loop://", "--stage",
                        "loop://", "-o"],
    "reconstruct --ply": ["reconstruct", "{scan}", "--ply"],
    "reconstruct --plot": ["reconstruct", "{scan}", "--plot"],
    "db export --csv": ["db", "export", "{scan_id}", "--db", "{db}", "--csv"],
    "db export --ply": ["db", "export", "{scan_id}", "--db", "{db}", "--ply"],
    "db export --mcap": ["db", "export", "{scan_id}", "--db", "{db}", "--mcap"],
}


@pytest.mark.parametrize("kind", REFUSED)
@pytest.mark.parametrize("command", sorted(COMMANDS))
def test_every_command_refuses_an_output_that_is_not_a_regular_file_and_keeps_it(
        command, kind, inputs, tmp_path, capsys):
    path = make_target(kind, tmp_path)
    before, names = snapshot(path), listing(tmp_path)
    argv = [a.format(**inputs) for a in COMMANDS[command]]
    rc = main([*argv, str(path)])
    err = capsys.readouterr().err
    assert rc == 2, err
    line = err.strip()
    assert "\n" not in line and WHAT[kind] in line and str(path) in line, line
    assert "not a regular file" in line or "is a folder" in line
    assert snapshot(path) == before and listing(tmp_path) == names  # the same node, kept


def test_proc_links_are_refused_by_the_command_before_the_board_is_opened(capsys):
    rc = main(["acquire", "--sensor", "loop://", "--shots", "3", "--force", "-o",
               "/dev/stdout"])
    err = capsys.readouterr().err
    assert rc == 2 and "a process's open file" in err and err.count("\n") == 1


@pytest.mark.parametrize("command", ["reconstruct --ply", "reconstruct --plot",
                                     "db export --csv", "db export --ply",
                                     "db export --mcap"])
@pytest.mark.parametrize("kind", ["new", "regular", "symlink to regular"])
def test_an_export_replaces_a_regular_file_atomically_and_writes_through_a_link(
        command, kind, inputs, tmp_path, capsys):
    suffix = {"--ply": ".ply", "--plot": ".png", "--csv": ".csv",
              "--mcap": ".mcap"}[command.split()[-1]]
    path = make_target(kind, tmp_path, "out" + suffix)
    argv = [a.format(**inputs) for a in COMMANDS[command]]
    rc = main([*argv, str(path)])
    assert rc == 0, capsys.readouterr().err
    data = path.read_bytes()
    assert data != EARLIER and len(data) > 100
    if kind == "symlink to regular":
        assert path.is_symlink() and (tmp_path / "real.dat").read_bytes() == data
    assert listing(tmp_path) == sorted({path.name, *(["real.dat"] if "symlink" in kind
                                                     else [])})


def test_calibrate_keeps_the_earlier_result_and_writes_the_new_one_atomically(
        inputs, tmp_path, capsys):
    path = tmp_path / "calibration.toml"
    path.write_bytes(EARLIER)
    rc = main(["calibrate", "--from-data", str(inputs["rig"]), "-o", str(path)])
    assert rc == 0, capsys.readouterr().err
    assert path.read_text().startswith("# dmdsm scanner calibration")
    (backup,) = [p for p in tmp_path.iterdir() if p != path]
    assert backup.name.startswith("calibration.") and backup.read_bytes() == EARLIER


def test_classify_evaluate_refuses_an_out_that_is_not_a_folder_before_evaluating(
        inputs, tmp_path, capsys):
    path = make_target("regular", tmp_path, "classify")
    rc = main(["classify", "evaluate", "--db", str(inputs["db"]), "--out", str(path)])
    err = capsys.readouterr().err
    assert rc == 2 and "is not a folder" in err and err.count("\n") == 1
    assert path.read_bytes() == EARLIER


def test_a_plot_name_matplotlib_cannot_write_is_refused_before_the_work(inputs, tmp_path,
                                                                         capsys):
    rc = main(["reconstruct", str(inputs["scan"]), "--plot", str(tmp_path / "fig.dat")])
    err = capsys.readouterr().err
    assert rc == 2 and "cannot be written as .dat" in err and err.count("\n") == 1
    assert listing(tmp_path) == []
