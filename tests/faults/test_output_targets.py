"""An output path is a new file or a regular one: a device node, a FIFO, a socket or a
symbolic link is refused in one line that says what it is, and is left as it was (issue 30)."""

import os
import socket
import stat

import pytest

from dmdsm.host.commands.cli import main


def _target(kind, tmp_path):
    path = tmp_path / "out.h5"
    if kind == "fifo":
        os.mkfifo(path)
    elif kind == "symlink":
        (tmp_path / "real.h5").write_bytes(b"earlier data")
        path.symlink_to(tmp_path / "real.h5")
    elif kind == "dangling symlink":
        path.symlink_to(tmp_path / "nowhere.h5")
    elif kind == "socket":
        s = socket.socket(socket.AF_UNIX)
        s.bind(str(path))
        s.close()
    elif kind == "device":  # a node of its own (as root, which CI is), so a bug breaks no
        try:                # system device; without root /dev/null cannot be replaced anyway
            os.mknod(path, stat.S_IFCHR | 0o600, os.makedev(1, 3))
        except PermissionError:
            path = "/dev/null"
    return path


WHAT = {"fifo": "a FIFO", "symlink": "a symbolic link", "dangling symlink": "a symbolic link",
        "socket": "a socket", "device": "a character device"}


@pytest.mark.parametrize("kind", sorted(WHAT))
@pytest.mark.parametrize("argv", [
    ["acquire", "--sensor", "loop://", "--shots", "3", "--force", "-o"],
    ["acquire", "--sensor", "loop://", "--shots", "3", "-o"],
    ["classify", "train", "--db", "nowhere", "-o"],
])
def test_an_output_that_is_not_a_regular_file_is_refused_and_kept(kind, argv, tmp_path, capsys):
    path = _target(kind, tmp_path)
    before = os.lstat(path)
    rc = main([*argv, str(path)])
    err = capsys.readouterr().err
    assert rc == 2, err
    line = err.strip()
    assert "\n" not in line and WHAT[kind] in line and "not a regular file" in line
    after = os.lstat(path)
    assert stat.S_IFMT(after.st_mode) == stat.S_IFMT(before.st_mode)
    assert after.st_ino == before.st_ino  # the same node, not replaced
    if kind == "symlink":
        assert (tmp_path / "real.h5").read_bytes() == b"earlier data"
