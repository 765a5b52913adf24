"""The command line is one consistent tool (issue 19, item 9): every command has its own
options and help, takes --json, names its outputs the same way, and says what to fix when
given a file where a port belongs."""

import argparse

import pytest
from hypothesis import given
from hypothesis import strategies as st

from dmdsm.host.entry import build_parser, main  # every command, `dmdsm demo` too


def leaves(parser, path=()):
    """(command path, parser) of every runnable command."""
    subs = [a for a in parser._actions if isinstance(a, argparse._SubParsersAction)]
    if not subs:
        yield path, parser
        return
    for name, p in subs[0].choices.items():
        yield from leaves(p, (*path, name))


LEAVES = dict(leaves(build_parser()))


def test_there_are_commands_to_check():
    assert {("stage", "move"), ("db", "list"), ("classify", "predict"), ("demo",),
            ("flash", "stm32"), ("protocol", "encode"), ("scan",)} <= set(LEAVES)


@pytest.mark.parametrize("path", sorted(LEAVES), ids=" ".join)
def test_every_command_takes_json_and_explains_every_option(path):
    p = LEAVES[path]
    opts = {s for a in p._actions for s in a.option_strings}
    assert "--json" in opts, path
    for a in p._actions:
        if a.help != argparse.SUPPRESS and not isinstance(a, argparse._HelpAction):
            assert a.help, f"{' '.join(path)} {a.option_strings or a.dest} has no help"
    out = {s for a in p._actions for s in a.option_strings if s in ("-o", "--output")}
    assert not out or {"-o", "--output"} <= out or path == ("scan",), path  # -o is --output


@pytest.mark.parametrize("argv", [
    ["stage", "home", "-x", "5"],         # a move's option on home
    ["db", "list", "--csv", "x.csv"],     # export's option on list
    ["classify", "predict", "--scan", "s.h5"],  # no --model: nothing loaded unasked
    ["classify", "train", "--db", "db"],  # no -o: where would the model go?
    ["db", "show", "--db", "db"],         # no scan id
    ["stage"],                            # no action
])
def test_options_of_another_action_are_refused(argv, capsys):
    with pytest.raises(SystemExit) as e:
        main(argv)
    assert e.value.code == 2 and "usage:" in capsys.readouterr().err


def test_a_group_action_has_its_own_help(capsys):
    with pytest.raises(SystemExit):
        main(["db", "list", "--help"])
    text = capsys.readouterr().out
    assert "--material" in text and "--csv" not in text and "rebuild" not in text


@pytest.mark.parametrize("kind", ["file", "folder"])
def test_a_file_or_folder_given_as_a_port_is_named(tmp_path, capsys, kind):
    port = tmp_path / "port"
    port.mkdir() if kind == "folder" else port.write_text("hello")
    assert main(["info", "--sensor", str(port)]) == 2
    err = capsys.readouterr().err
    assert f"is a {'plain file' if kind == 'file' else 'folder'}, not a serial port" in err
    assert "Inappropriate ioctl" not in err and len(err.strip().splitlines()) == 1


def test_a_device_that_is_not_a_serial_port_is_named(capsys):
    """/dev/null is a character device, as a port is, but it takes no line settings."""
    assert main(["info", "--sensor", "/dev/null"]) == 2
    err = capsys.readouterr().err
    assert "/dev/null is a device but not a serial port" in err and "dmdsm ports" in err
    assert "Inappropriate ioctl" not in err and len(err.strip().splitlines()) == 1


@pytest.mark.parametrize("flag, value, limits", [("--samples", "999999", "16..8192"),
                                                 ("--samples", "8", "16..8192"),
                                                 ("--average", "100000", "1..4096")])
def test_acquire_settings_outside_the_spec_are_named_before_connecting(tmp_path, capsys, flag,
                                                                       value, limits):
    """Checked against the protocol spec's range before the port is opened (it may not
    exist): a u16 overflow once ended in a traceback."""
    rc = main(["acquire", "--sensor", str(tmp_path / "ttyACM9"), "--shots", "3", flag, value,
               "-o", str(tmp_path / "a.h5")])
    err = capsys.readouterr().err
    assert rc == 2 and f"{flag} {value} is outside {limits}" in err
    assert len(err.strip().splitlines()) == 1 and not (tmp_path / "a.h5").exists()


@pytest.mark.parametrize("args, words", [
    (["--at", "9999", "200", "20"], "would leave the machine envelope: X9999 is "
                                    "outside the machine envelope (-10..410 mm)"),
    (["--at", "200", "5", "20", "--steps", "40"], "Y-14.5 is outside"),
    (["--at", "200", "200", "20", "--steps", "1"], "--steps must be 2..1000"),
    (["--at", "nan", "200", "20"], "--at X must be a finite number"),
    (["-x", "nan", "-y", "200", "-z", "20"], "--at X must be a finite number"),  # old spelling
    (["--at", "200", "200", "20", "--average", "0"], "--average 0 is outside 1..4096"),
])
def test_calibrate_range_refuses_a_bad_procedure_before_touching_a_board(tmp_path, capsys,
                                                                         args, words):
    """Every position the procedure would visit is checked first: the ports here do not
    even exist, so reaching them would be a different error."""
    rc = main(["calibrate-range", "--sensor", str(tmp_path / "s"), "--stage",
               str(tmp_path / "t"), "--start-distance", "20", *args, "-o",
               str(tmp_path / "r.json")])
    err = capsys.readouterr().err
    assert rc == 2 and words in err, err
    assert len(err.strip().splitlines()) == 1 and not (tmp_path / "r.json").exists()


@pytest.mark.parametrize("text, words", [
    ("[ports]\nsensor = 5\n", "[ports] takes sensor = \"/dev/...\""),
    ("[ports]\nsenser = \"/dev/ttyACM0\"\n", "(got senser = "),
    ("ports = 3\n", "[ports] must be a table"),
    ("[calibration]\nv = \"x\"\n", "[calibration] v must be three finite numbers"),
    ("[calibration]\nX_R = [1, 2]\n", "[calibration] X_R must be three finite numbers"),
    ("[calibration]\nn = [0, 0, 0]\n", "[calibration] n is a direction and cannot be [0, 0, 0]"),
    ("[calibration]\nv = [0, nan, 1]\n", "[calibration] v must be three finite numbers"),
])
def test_a_config_file_with_a_wrong_value_is_named_before_a_board_is_touched(tmp_path, capsys,
                                                                            text, words):
    """A config value of the wrong kind (a port as a number) once ended in a TypeError."""
    cfg = tmp_path / "dmdsm.toml"
    cfg.write_text(text)
    assert main(["stage", "where", "--config", str(cfg), "--stage", str(tmp_path / "s")]) == 2
    err = capsys.readouterr().err
    assert f"{cfg}: " in err and words in err, err
    assert len(err.strip().splitlines()) == 1


@pytest.mark.parametrize("text, words", [
    ("[calibration]\nv = [0, 1]\nn = [0, 0, 1]\nX_R = [1, 2, 3]\n", "v must be three finite"),
    ("[calibration]\nv = [0, 0, 0]\nn = [0, 0, 1]\nX_R = [1, 2, 3]\n", "v is a direction"),
])
def test_a_calibration_with_a_wrong_vector_is_one_line(tmp_path, text, words):
    from dmdsm.host.calibration.result import load_calibration
    from dmdsm.host.calibration.solver import CalibrationError

    path = tmp_path / "cal.toml"
    path.write_text(text)
    with pytest.raises(CalibrationError, match=words):
        load_calibration(path)


@pytest.mark.parametrize("flag, value", [("--rep-rate", "0"), ("--rep-rate", "nan"),
                                         ("--temperature", "2000"), ("--sensor-link", "-1")])
def test_sim_settings_outside_the_emulators_physics_are_one_line(capsys, flag, value):
    """--rep-rate 0 once ended in a ZeroDivisionError."""
    assert main(["sim", flag, value]) == 2
    err = capsys.readouterr().err
    assert f"{flag} (" in err and "must be within" in err and len(err.strip().splitlines()) == 1


@pytest.mark.parametrize("args, words", [
    (["train", "-o", "m.model", "--window", "99999999"], "--window must be 16..8192 samples"),
    (["evaluate", "--trials", "0"], "--trials must be at least 1 (got 0)"),
    (["evaluate", "--boss-trials", "-3"], "--boss-trials must be at least 1 (got -3)"),
])
def test_classify_numbers_out_of_range_are_one_line_before_any_work(tmp_path, capsys, args,
                                                                    words):
    """--window 99999999 once ran the machine out of memory; --trials 0 printed empty tables."""
    assert main(["classify", args[0], "--db", str(tmp_path), *args[1:]]) == 2
    err = capsys.readouterr().err
    assert words in err and len(err.strip().splitlines()) == 1, err


def test_leave_one_object_out_without_a_second_object_is_untested_not_nan(tmp_path, capsys):
    """A material with one object cannot be tested by leaving it out: the text says so and
    the JSON holds null (NaN is not JSON)."""
    import json

    from dmdsm.sim.data.dataset import make_database

    make_database(tmp_path / "db", points=12, seed=1, objects=["soda_can", "foam_block"])
    common = ["classify", "evaluate", "--db", str(tmp_path / "db"), "--classifiers",
              "minirocket", "--trials", "1", "--out", str(tmp_path / "out")]
    assert main([*common, "--json"]) == 0
    res = json.loads(capsys.readouterr().out)["classifiers"]["minirocket"]
    assert res["loo"] == {"aluminium": None, "foam": None}
    assert all(0 <= a <= 1 for a in res["random"].values())
    assert main(common) == 0
    assert "aluminium untested (no other object of it)" in capsys.readouterr().out


@pytest.mark.parametrize("at, extra, words", [
    (["9999", "266", "20"], [], "--at: X9999 is outside the machine envelope"),
    (["nan", "266", "20"], [], "--at: X nan is not a position"),
    (["235", "266", "20"], ["--average", "0"], "--average 0 is outside 1..4096"),
])
def test_a_calibration_step_refuses_a_bad_start_before_touching_a_board(tmp_path, capsys, at,
                                                                        extra, words):
    """`--at nan` once scanned the whole tip step at X nan; the ports here do not exist."""
    from dmdsm.host.ranging.calibrate import RangeCal, RangingSetup
    from dmdsm.host.ranging.matched_filter import gaussian_pulse

    fs = 240e6 / 72
    RangingSetup(fs, {"oa": gaussian_pulse(fs, 1e6, 0.8)}, {"oa": (0, 1024)},
                 {"oa": RangeCal("oa", 2e-6, 343e3, 0, 0, 0, 3)}).save(tmp_path / "r.json")
    data = tmp_path / "d.csv"
    rc = main(["calibrate", "--step", "tip", "--at", *at, *extra, "--sensor",
               str(tmp_path / "s"), "--stage", str(tmp_path / "t"), "--ranging",
               str(tmp_path / "r.json"), "--data", str(data)])
    err = capsys.readouterr().err
    assert rc == 2 and words in err and len(err.strip().splitlines()) == 1, err
    assert not data.exists()


@pytest.mark.parametrize("size, words", [
    ("[-5, 30, 40]", "size_mm must be three lengths in 0..1000 mm"),
    ("[nan, 30, 40]", "size_mm must be three finite numbers"),
    ("[1e308, 1e308, 1e308]", "size_mm must be three lengths in 0..1000 mm"),
    ("[50, 30]", "size_mm must be three finite numbers"),
])
def test_a_truth_file_with_impossible_sizes_is_one_line(tmp_path, capsys, size, words):
    """A NaN size once ended in scipy's 'Residuals are not finite' traceback; a negative one
    gave a confident, meaningless error figure."""
    from dmdsm.host.commands.db import load_truth
    from dmdsm.host.commands.errors import CliError

    truth = tmp_path / "block.toml"
    truth.write_text(f'shape = "box"\nsize_mm = {size}\n')
    with pytest.raises(CliError, match=words.replace(".", r"\.")):
        load_truth(truth)
    truth.write_text('shape = "box"\nsize_mm = [50, 30, 40]\n')
    assert load_truth(truth) == (50.0, 30.0)


@pytest.mark.parametrize("encoding, words", [
    ("utf-16", "is UTF-16 text: save the config file as UTF-8"),
    ("latin-1", "is not UTF-8 text: save")])
def test_a_config_file_not_in_utf8_is_named_in_one_line(tmp_path, capsys, encoding, words):
    """Issue 30: a UTF-16 dmdsm.toml (a Windows editor's default) was a UnicodeDecodeError."""
    cfg = tmp_path / "dmdsm.toml"
    cfg.write_bytes('[ports]\nstage = "/dev/ttyUSB0"  # für den Tisch\n'.encode(encoding))
    assert main(["stage", "where", "--config", str(cfg), "--stage", str(tmp_path / "s")]) == 2
    err = capsys.readouterr().err
    assert f"{cfg} {words}" in err and "Traceback" not in err, err
    assert len(err.strip().splitlines()) == 1


def test_stage_options_may_come_before_the_action(tmp_path, capsys):
    """Issue 30: `dmdsm stage --stage P where` was "invalid choice: P"."""
    missing = tmp_path / "nothing"
    for argv in (["stage", "--stage", str(missing), "where"],
                 ["stage", "--stage", str(missing), "--json", "stop"],
                 ["stage", "where", "--stage", str(missing)]):
        assert main(argv) == 2
        err = capsys.readouterr().err
        assert f"{missing} does not exist" in err and "invalid choice" not in err, err


HOSTILE = "al\x1b[31mRED\x07\x00\u200b"


def test_names_from_a_database_are_escaped_for_the_terminal(tmp_path, capsys):
    """Issue 30: a material with an escape sequence and a bell, stored by another program or
    an older version, recoloured the terminal and rang its bell in `dmdsm db list`."""
    from dmdsm.host.scan.catalogue import COLUMNS, connect

    con = connect(tmp_path / "db", create=True)
    row = {c: "" for c in COLUMNS} | {"scan_id": "cup-1", "object_id": "cup" + HOSTILE,
                                      "material": HOSTILE, "status": "complete",
                                      "path": "scans/cup-1.h5", "n_points": 3, "n_planned": 3}
    with con:
        con.execute(f"INSERT INTO scans ({', '.join(COLUMNS)}) VALUES "
                    f"({', '.join('?' * len(COLUMNS))})", [row[c] for c in COLUMNS])
    con.close()
    assert main(["db", "list", "--db", str(tmp_path / "db")]) == 0
    out = capsys.readouterr().out
    assert "\x1b" not in out and "\x07" not in out and "\x00" not in out, repr(out)
    assert "al\\x1b[31mRED\\x07\\x00\\u200b" in out


def test_control_characters_in_a_plans_names_are_refused_by_name():
    from dmdsm.host.scan.plan import PlanError, ScanPlan
    for key in ("object_id", "material"):
        kw = {"object_id": "cup", key: ("cup" if key == "object_id" else "") + HOSTILE}
        with pytest.raises(PlanError, match=f"sample.{key} = .* holds a control character"):
            ScanPlan(**kw).validate()


@given(st.text())
def test_shown_text_is_printable_and_printable_text_is_unchanged(text):
    from dmdsm.host.files import shown
    s = shown(text)
    assert s.isprintable()
    if text.isprintable():
        assert s == text


@pytest.mark.parametrize("url, words", [
    ("rfc2217://nohost", "give the host and the TCP port, e.g. rfc2217://localhost:5000"),
    ("socket://localhost", "give the host and the TCP port"),
    ("socket://localhost:99999", "give the host and the TCP port"),
    ("foo://bar", "unknown port URL scheme 'foo'"),
])
def test_a_port_url_pyserial_cannot_open_is_one_line_saying_what_to_give(capsys, url, words):
    """Issue 30: an rfc2217:// port without a TCP port showed pySerial's "'<=' not supported",
    and an unknown scheme was a traceback."""
    assert main(["stage", "where", "--stage", url]) == 2
    err = capsys.readouterr().err
    assert words in err and "Traceback" not in err and len(err.strip().splitlines()) == 1, err
