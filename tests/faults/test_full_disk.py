"""A full disk while an output is written (issue 30, item 2): one line that names the path
and what to do, exit 2, no temporary file left, the old file unchanged (and calibrate's
earlier result not moved aside). The disk fills by injection (the file's fsync, or the
writer partway), and, where this runs as root and may mount, on a real 64 KiB tmpfs."""

import errno
import os
import subprocess
import uuid
from pathlib import Path

import pytest

from dmdsm.host.commands import db as db_command
from dmdsm.host.commands.cli import main

EARLIER = b"the earlier file\n"


COMMANDS = {  # argv before the output path, the flag named in the message
    "reconstruct --ply": (["reconstruct", "{scan}", "--ply"], "--ply"),
    "reconstruct --plot": (["reconstruct", "{scan}", "--plot"], "--plot"),
    "db export --csv": (["db", "export", "{scan_id}", "--db", "{db}", "--csv"], "--csv"),
    "db export --ply": (["db", "export", "{scan_id}", "--db", "{db}", "--ply"], "--ply"),
    "calibrate -o": (["calibrate", "--from-data", "{rig}", "-o"], "-o"),
}
SUFFIX = {"--ply": ".ply", "--plot": ".png", "--csv": ".csv", "-o": ".toml"}


def _no_space(*args, **kwargs):
    raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))


def _run_full(command, inputs, folder, capsys):
    """Run the command with an earlier output in `folder`; its exit code, stderr, output."""
    argv, flag = COMMANDS[command]
    path = folder / ("out" + SUFFIX[flag])
    path.write_bytes(EARLIER)
    rc = main([*[a.format(**inputs) for a in argv], str(path)])
    return rc, capsys.readouterr().err, path, flag


def _assert_one_line_and_nothing_changed(rc, err, path, flag):
    assert rc == 2, err
    line = err.strip()
    assert "\n" not in line and "Traceback" not in err, err
    assert f"no space left on the device holding {path}" in line and flag in line, line
    assert path.read_bytes() == EARLIER
    assert sorted(os.listdir(path.parent)) == [path.name]  # no temporary file, no backup


@pytest.mark.parametrize("command", sorted(COMMANDS))
def test_a_disk_that_fills_at_the_files_fsync_leaves_the_old_file(command, inputs, tmp_path,
                                                                   capsys, monkeypatch):
    """The write went into the page cache and the file system found no room at fsync (as
    NFS and delayed allocation do)."""
    monkeypatch.setattr(os, "fsync", _no_space)
    _assert_one_line_and_nothing_changed(*_run_full(command, inputs, tmp_path, capsys))


@pytest.mark.parametrize("command, writer", [("db export --csv", "write_points_csv"),
                                             ("reconstruct --ply", "write_ply")])
def test_a_disk_that_fills_partway_through_the_writer_leaves_the_old_file(
        command, writer, inputs, tmp_path, capsys, monkeypatch):
    def half_then_full(path, pts):
        Path(path).write_text("point_index,modality\n" * 50)
        raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))
    monkeypatch.setattr(db_command, writer, half_then_full)
    _assert_one_line_and_nothing_changed(*_run_full(command, inputs, tmp_path, capsys))


@pytest.mark.parametrize("code, words", [(errno.EDQUOT, "disk quota"),
                                         (errno.EIO, "input/output error"),
                                         (errno.EROFS, "read-only file system"),
                                         (errno.EFBIG, "larger than its file system allows")])
def test_other_write_failures_are_one_line_with_their_meaning(code, words, inputs, tmp_path,
                                                              capsys, monkeypatch):
    monkeypatch.setattr(os, "fsync", lambda fd: (_ for _ in ()).throw(
        OSError(code, os.strerror(code))))
    rc, err, path, _ = _run_full("db export --ply", inputs, tmp_path, capsys)
    assert rc == 2 and words in err and str(path) in err and err.count("\n") == 1, err
    assert path.read_bytes() == EARLIER and os.listdir(tmp_path) == [path.name]


@pytest.fixture
def full_tmpfs(tmp_path):
    """A 64 KiB tmpfs (the suite runs as root, as `make test` does: it installs packages),
    with an earlier output in it and every other byte taken."""
    assert os.geteuid() == 0, "mounting a tmpfs needs root: run the suite as root"
    mnt = tmp_path / f"tmpfs-{uuid.uuid4().hex[:6]}"
    mnt.mkdir()
    r = subprocess.run(["mount", "-t", "tmpfs", "-o", "size=64k", "tmpfs", str(mnt)],
                       capture_output=True, text=True)
    if r.returncode != 0:
        pytest.fail(f"cannot mount a tmpfs here: {r.stderr.strip()}")
    try:
        yield mnt
    finally:
        subprocess.run(["umount", str(mnt)], check=True)


def _fill(folder: Path) -> Path:
    """Take every free byte of the file system holding `folder`; the filler's path."""
    filler = folder / "filler"
    fd = os.open(filler, os.O_WRONLY | os.O_CREAT)
    try:
        for size in (4096, 1):  # pages, then the last bytes
            while True:
                try:
                    os.write(fd, b"\0" * size)
                except OSError as e:
                    assert e.errno == errno.ENOSPC
                    break
    finally:
        os.close(fd)
    return filler


@pytest.mark.parametrize("command", sorted(COMMANDS))
def test_a_real_full_disk_leaves_the_old_file(command, inputs, full_tmpfs, capsys):
    argv, flag = COMMANDS[command]
    path = full_tmpfs / ("out" + SUFFIX[flag])
    path.write_bytes(EARLIER)
    filler = _fill(full_tmpfs)
    rc = main([*[a.format(**inputs) for a in argv], str(path)])
    err = capsys.readouterr().err
    filler.unlink()
    _assert_one_line_and_nothing_changed(rc, err, path, flag)
