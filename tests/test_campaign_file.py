"""Campaign files (host/scan/campaign_file.py, issue 33): a good file read as written, every kind
of bad input refused with one line that names the object, the key and the fix, and random
valid campaigns written and read back unchanged."""

import string
from pathlib import Path

import pytest
from hypothesis import given
from hypothesis import strategies as st

from dmdsm.host.scan.campaign_file import (
    MAX_BYTES,
    Campaign,
    CampaignError,
    CampaignObject,
    load_campaign,
    parse_campaign,
)
from dmdsm.host.scan.plan import MODALITIES, MODES

GOOD = """
[campaign]
classifier = "models/household.joblib"
modality = "oa"

[[object]]
id = "soda_can"
material = "aluminium"
size_mm = [66.0, 66, 122.0]
round = true
notes = "empty, ring pull away"
levels_mm = [40.0, 42]

[[object]]
id = "tissue_box"
material = "paper"
size_mm = [120.0, 60.0, 90.0]
scene = "tissue_box_slot"
"""

OBJ = '[[object]]\nid = "cup"\nmaterial = "paper"\nsize_mm = [80.0, 80.0, 95.0]\n'


def test_a_good_file_is_read_as_written(tmp_path):
    (tmp_path / "c.toml").write_text(GOOD)
    c = load_campaign(tmp_path / "c.toml")
    assert c.mode == "auto" and c.modality == "oa"
    assert c.classifier == tmp_path / "models" / "household.joblib"  # beside the file
    can, box = c.objects
    assert can == CampaignObject("soda_can", "aluminium", (66.0, 66.0, 122.0), True,
                                 "empty, ring pull away", "", (40.0, 42.0))
    assert can.scene_name == "soda_can" and box.scene_name == "tissue_box_slot"
    assert box.round is False and box.levels_mm == () and box.notes == ""
    plan = c.plan(can)
    assert plan.mode == "auto" and plan.modality == "oa" and plan.material == "aluminium"
    assert plan.levels_mm == [40.0, 42.0] and plan.notes == "empty, ring pull away"
    assert plan.radius_mm == 34.0 and plan.height_mm == 122.0
    assert len(c.plan(box).levels_mm) > 20  # the auto plan's own: every 2 mm
    assert parse_campaign(c.to_toml(), tmp_path / "c.toml") == c


def test_an_object_may_have_its_own_modality(tmp_path):
    text = "[campaign]\nmodality = \"both\"\n" + OBJ + "modality = \"us\"\n"
    c = parse_campaign(text, tmp_path / "c.toml")
    assert c.objects[0].modality == "us" and c.plan(c.objects[0]).modality == "us"
    with pytest.raises(CampaignError, match="modality must be one of"):
        parse_campaign(OBJ + "modality = \"sonar\"\n", tmp_path / "c.toml")


def test_an_object_off_its_footprints_centre_gives_its_reach(tmp_path):
    """A mug stands centred by its body, its handle farther from the table axis than its
    footprint's half-diagonal: reach_mm makes the bounding cylinder (the first look's
    keep-out) the handle's, not the footprint's."""
    mug = OBJ.replace("[80.0, 80.0, 95.0]", "[117.0, 80.0, 95.0]")
    plain = parse_campaign(mug, tmp_path / "c.toml")
    assert plain.objects[0].reach_mm is None
    assert plain.plan(plain.objects[0]).radius_mm == 71.9  # half the diagonal, + 1
    c = parse_campaign(mug + "reach_mm = 73.5\n", tmp_path / "c.toml")
    assert c.objects[0].reach_mm == 73.5 and c.plan(c.objects[0]).radius_mm == 74.5
    assert parse_campaign(c.to_toml(), tmp_path / "c.toml") == c


def test_the_defaults_and_the_campaign_table_is_optional():
    c = parse_campaign(OBJ)
    assert (c.mode, c.modality, c.classifier) == ("auto", "both", None)
    assert c.objects[0].round is False  # a box's bounding cylinder: the larger keep-out


BAD = [
    # (text, what the one line must say)
    ("x = 1\n" + OBJ, "unknown key 'x' at the top"),
    ("campaign = 3\n" + OBJ, "campaign must be a table"),
    ("[campaign]\nclasifier = \"m\"\n" + OBJ, "unknown key 'clasifier' in [campaign]"),
    ("[campaign]\nmode = \"slow\"\n" + OBJ, "mode must be one of 'step', 'fly', 'auto'"),
    ("[campaign]\nmodality = 2\n" + OBJ, "modality must be one of"),
    ("[campaign]\nclassifier = 3\n" + OBJ, "classifier must be text in quotes"),
    ("[campaign]\nclassifier = \" \"\n" + OBJ, "classifier is empty"),
    ("[campaign]\nclassifier = \"a\\u0000b\"\n" + OBJ, "NUL"),
    ("[campaign]\nmode = \"auto\"\n", "no objects: add one [[object]] table"),
    ("object = []\n", "no objects"),
    ("[object]\nid = \"cup\"\n", "write [[object]] (two brackets)"),
    ("object = [1, 2]\n", "object must be a list of tables"),
    (OBJ + "colour = \"red\"\n", "object 1 (cup): unknown key 'colour'"),
    ('[[object]]\nmaterial = "paper"\nsize_mm = [1.0, 1.0, 1.0]\n', "id is missing"),
    ('[[object]]\nid = "cup"\nsize_mm = [1.0, 1.0, 1.0]\n', "cup): material is missing"),
    ('[[object]]\nid = "cup"\nmaterial = "paper"\n', "size_mm is missing: add e.g. size_mm"),
    (OBJ.replace('"cup"', "12"), "id must be text in quotes"),
    (OBJ.replace('"cup"', '""'), "id is empty"),
    (OBJ.replace('"cup"', '"my cup"'), "cannot name a scan: use letters, digits"),
    (OBJ.replace('"cup"', '"a/b"'), "cannot name a scan"),
    (OBJ.replace('"cup"', '"../cup"'), "cannot name a scan"),
    (OBJ.replace('"cup"', '".cup"'), "cannot name a scan"),
    (OBJ.replace('"cup"', '"tasse_\u00e9"'), "cannot name a scan"),
    (OBJ.replace('"cup"', '"' + "c" * 91 + '"'), "at most 90"),
    (OBJ.replace('"cup"', '"cup\\u001b[31m"'), "holds a control or other unprintable"),
    (OBJ + OBJ, "object 2: id cup is object 1's too: give each object its own id"),
    (OBJ.replace('"paper"', "7"), "material must be text in quotes"),
    (OBJ.replace('"paper"', '""'), "material is empty"),
    (OBJ.replace('"paper"', '"pa\\u0007per"'), "material = "),
    (OBJ.replace("[80.0, 80.0, 95.0]", '["80", 80.0, 95.0]'),
     "size_mm[0] is text ('80'): write the number without quotes"),
    (OBJ.replace("[80.0, 80.0, 95.0]", "[80.0, 95.0]"), "size_mm must be three numbers"),
    (OBJ.replace("[80.0, 80.0, 95.0]", '"80 80 95"'), "size_mm must be three numbers"),
    (OBJ.replace("[80.0, 80.0, 95.0]", "[80.0, 0, 95.0]"),
     "size_mm[1] must be a positive finite number of mm (got 0)"),
    (OBJ.replace("[80.0, 80.0, 95.0]", "[80.0, -1.0, 95.0]"), "size_mm[1] must be a positive"),
    (OBJ.replace("[80.0, 80.0, 95.0]", "[80.0, 80.0, inf]"), "size_mm[2] must be a positive"),
    (OBJ.replace("[80.0, 80.0, 95.0]", "[80.0, 80.0, nan]"), "size_mm[2] must be a positive"),
    (OBJ.replace("[80.0, 80.0, 95.0]", "[80.0, true, 95.0]"), "size_mm[1] must be a number"),
    (OBJ.replace("[80.0, 80.0, 95.0]", "[80.0, 80.0, 1e6]"),
     "more than the machine's longest travel"),
    (OBJ + 'round = "yes"\n', "round must be true or false, without quotes"),
    (OBJ + "round = 1\n", "round must be true or false"),
    (OBJ + "notes = 5\n", "notes must be text in quotes"),
    (OBJ + 'notes = "' + "n" * 1001 + '"\n', "notes is 1001 characters long, at most 1000"),
    (OBJ + 'scene = ""\n', "scene is empty"),
    (OBJ + 'scene = "a\\tb"\n', "scene = "),
    (OBJ + "levels_mm = []\n", "levels_mm must be a list of 1 to 200 heights"),
    (OBJ + "levels_mm = 20.0\n", "levels_mm must be a list"),
    (OBJ + 'levels_mm = ["20"]\n', "levels_mm[0] is text ('20'): write the number without"),
    (OBJ + "levels_mm = [20.0, 120.0]\n", "above the object's height (95 mm"),
    (OBJ + "levels_mm = [-2.0]\n", "levels_mm[0] must be a positive"),
    (OBJ + 'reach_mm = "50"\n', "reach_mm is text ('50'): write the number without quotes"),
    (OBJ + "reach_mm = 30.0\n", "is less than half the object's width or depth (40 mm)"),
    (OBJ + "reach_mm = 1e6\n", "reach_mm = 1e+06 mm is more than the machine's longest"),
    ("[[object]\nid = 1\n", "is not valid TOML"),
    ("x = " + "[" * 100_000, "nests arrays or tables too deeply"),
    ("x = " + "{a=" * 100_000, "nests arrays or tables too deeply"),
    (OBJ + 'id = "again"\n', "is not valid TOML"),
]


@pytest.mark.parametrize("text, says", BAD)
def test_bad_input_is_refused_with_one_line_naming_the_fix(text, says):
    with pytest.raises(CampaignError) as e:
        parse_campaign(text, Path("c.toml"))
    msg = str(e.value)
    assert "\n" not in msg and len(msg) < 400, msg
    assert says in msg, msg
    assert msg.startswith("c.toml")


def test_bad_files_are_refused_with_one_line(tmp_path):
    f = tmp_path / "c.toml"
    f.write_bytes(OBJ.encode("utf-16"))
    with pytest.raises(CampaignError, match="is UTF-16 text: save the campaign file as UTF-8"):
        load_campaign(f)
    f.write_bytes(OBJ.replace("paper", "papier \xe9").encode("latin-1"))
    with pytest.raises(CampaignError, match="is not UTF-8 text"):
        load_campaign(f)
    f.write_bytes(b"#" * (MAX_BYTES + 1))
    with pytest.raises(CampaignError, match="larger than 1024 KiB: .* split it"):
        load_campaign(f)
    with pytest.raises(CampaignError, match="is a folder"):
        load_campaign(tmp_path)
    with pytest.raises(CampaignError, match="cannot read campaign file .*: No such file"):
        load_campaign(tmp_path / "none.toml")
    many = "".join(OBJ.replace('"cup"', f'"cup{i}"') for i in range(1001))
    with pytest.raises(CampaignError, match="1001 objects, at most 1000"):
        parse_campaign(many)


ID = st.text(string.ascii_letters + string.digits, min_size=1, max_size=1).flatmap(
    lambda first: st.text(string.ascii_letters + string.digits + "._-", max_size=20).map(
        lambda rest: first + rest)).filter(lambda s: ".." not in s)
PRINTABLE = st.text(min_size=1, max_size=30).filter(lambda s: s.isprintable() and s.strip())


@st.composite
def campaigns(draw):
    ids = draw(st.lists(ID, min_size=1, max_size=4, unique=True))
    objs = []
    for oid in ids:
        size = tuple(draw(st.floats(5.0, 150.0)) for _ in range(3))
        levels = draw(st.one_of(st.just(()), st.lists(
            st.floats(0.5, size[2]), min_size=1, max_size=4).map(tuple)))
        objs.append(CampaignObject(oid, draw(PRINTABLE), size, draw(st.booleans()),
                                   draw(st.text(max_size=40)),
                                   draw(st.one_of(st.just(""), PRINTABLE)), levels,
                                   draw(st.sampled_from(("",) + MODALITIES)),
                                   draw(st.one_of(st.none(), st.floats(
                                       max(size[:2]) / 2, max(size[:2]) / 2 + 80)))))
    classifier = draw(st.one_of(st.none(), PRINTABLE.filter(lambda s: "\x00" not in s).map(
        lambda s: Path("/models") / s.strip())))
    return Campaign(tuple(objs), classifier, draw(st.sampled_from(MODES)),
                    draw(st.sampled_from(MODALITIES)))


@given(campaigns())
def test_random_valid_campaigns_round_trip(c):
    back = parse_campaign(c.to_toml(), Path("/anywhere/c.toml"))
    assert back == c
    for o in back.objects:
        assert back.plan(o).object_id == o.object_id


def test_the_command_refuses_a_bad_file_with_one_line_and_exit_2(tmp_path, capsys):
    from dmdsm.host.commands.cli import main

    (tmp_path / "c.toml").write_text(OBJ.replace("[80.0, 80.0, 95.0]", '["80", 80, 95]'))
    code = main(["campaign", str(tmp_path / "c.toml"), "--db", str(tmp_path / "db")])
    err = capsys.readouterr().err
    assert code == 2 and err.count("\n") == 1, err
    assert err.startswith("dmdsm: error: ") and "size_mm[0] is text ('80')" in err
    assert not (tmp_path / "db").exists()
