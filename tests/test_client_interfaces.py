"""The board clients and every in-process fake of them satisfy the Protocols of
host/links/interfaces.py: each member by name, each method's parameters by name and place. A
method renamed or removed, or a parameter renamed, on a client or a fake fails here."""

import inspect
from typing import Protocol

import pytest
from client_fakes import FakeSensor, FakeStage

from dmdsm.host.links.interfaces import (
    DeviceIdentity,
    Identity,
    Sensor,
    ShotSensor,
    Stage,
    StageMotion,
    StreamSensor,
)
from dmdsm.host.links.sensor import SPEC, SensorClient
from dmdsm.host.links.stage import StageClient
from dmdsm.host.scan.fly import LineMotion
from dmdsm.sim.data.rig_data import DirectRig
from dmdsm.sim.physics.scene import Scene

MOTION = LineMotion(80.0, 140.0, 83.33, 3000.0, 80.0)


def members(proto: type) -> dict[str, object]:
    """name -> function (a method) or property (an attribute) of a Protocol and its bases."""
    out: dict[str, object] = {}
    for cls in reversed(proto.__mro__):
        if cls is Protocol or not getattr(cls, "_is_protocol", False):
            continue
        for name, v in vars(cls).items():
            if not name.startswith("_") and (inspect.isfunction(v) or isinstance(v, property)):
                out[name] = v
    return out


def parameter_problems(want, got) -> list[str]:
    """How the implementation `got` fails to take the calls the Protocol method `want`
    allows: positional parameters by name in the same place, keyword-only ones by name, a
    **kwargs for a **kwargs; any further parameter of `got` must be optional."""
    w = list(inspect.signature(want).parameters.values())[1:]
    g = list(inspect.signature(got).parameters.values())[1:]
    by_name = {p.name: p for p in g}
    kinds = inspect.Parameter
    problems = []
    for i, p in enumerate(w):
        if p.kind is kinds.POSITIONAL_OR_KEYWORD:
            if i >= len(g) or g[i].name != p.name or g[i].kind is not p.kind:
                problems.append(f"no positional parameter {p.name!r} in place {i}")
        elif p.kind is kinds.KEYWORD_ONLY:
            if by_name.get(p.name) is None or by_name[p.name].kind not in (
                    kinds.POSITIONAL_OR_KEYWORD, kinds.KEYWORD_ONLY):
                problems.append(f"no keyword parameter {p.name!r}")
        elif p.kind is kinds.VAR_KEYWORD and not any(q.kind is p.kind for q in g):
            problems.append(f"no **{p.name}")
    named = {p.name for p in w}
    for q in g:
        if q.name not in named and q.default is q.empty and q.kind not in (
                kinds.VAR_POSITIONAL, kinds.VAR_KEYWORD):
            problems.append(f"parameter {q.name!r} is not in the Protocol and not optional")
    return problems


def attribute_holders(cls: type) -> set[str]:
    """Names a client class declares (class attributes and annotations, bases included)."""
    names = set(dir(cls))
    for c in cls.__mro__:
        names |= set(getattr(c, "__annotations__", {}))
    return names


REAL = [(StageClient, Stage), (SensorClient, Sensor)]
FAKES = [  # (what makes one, the Protocols it stands in for)
    (lambda: FakeStage(MOTION), (Stage,)),
    (lambda: FakeSensor(MOTION), (StreamSensor,)),
    (lambda: DirectRig(Scene()), (StageMotion, ShotSensor)),
]


def check(cls: type, proto: type, has_attribute) -> list[str]:
    problems = []
    for name, m in members(proto).items():
        if isinstance(m, property):
            if not has_attribute(name):
                problems.append(f"{name}: missing")
            continue
        impl = getattr(cls, name, None)
        if not inspect.isfunction(impl):
            problems.append(f"{name}(): missing")
            continue
        problems += [f"{name}(): {p}" for p in parameter_problems(m, impl)]
    return [f"{cls.__name__} as {proto.__name__}: {p}" for p in problems]


@pytest.mark.parametrize("cls, proto", REAL, ids=lambda x: x.__name__)
def test_the_real_clients_satisfy_their_protocols(cls, proto):
    names = attribute_holders(cls)
    assert check(cls, proto, names.__contains__) == []


def test_the_sensor_clients_identity_is_the_handshake_reply_with_the_identity_fields():
    reply = {f.name for f in SPEC.by_name[SPEC.by_name["identify"].reply].fields}
    assert set(members(Identity)) <= reply | {"fields"}
    assert "fields" in members(DeviceIdentity)


@pytest.mark.parametrize("make, protos", FAKES, ids=["FakeStage", "FakeSensor", "DirectRig"])
def test_every_fake_satisfies_the_protocols_it_stands_in_for(make, protos):
    fake = make()
    for proto in protos:
        assert check(type(fake), proto, lambda name: hasattr(fake, name)) == []
        if "identity" in members(proto):
            assert all(hasattr(fake.identity, k) for k in members(Identity))


def test_a_renamed_method_or_parameter_is_caught():
    class Renamed:
        def move(self, x=None, y=None, z=None, a=None, feed=None, wait=False):
            pass

        def wait_for(self):
            pass

    problems = check(Renamed, StageMotion, lambda name: False)
    assert any("move(): no positional parameter 'feed_mm_min'" in p for p in problems)
    assert any("wait(): missing" in p for p in problems)


def test_the_protocols_list_what_the_procedures_use():
    assert set(members(StageMotion)) == {"move", "wait"}
    assert set(members(Stage)) == {"move", "wait", "where", "send", "stop", "home"}
    assert set(members(ShotSensor)) == {"identity", "configure", "acquire"}
    assert set(members(StreamSensor)) == {"identity", "motion_syncs", "clock_exchanges",
                                          "stream_start", "stream_take", "stream_stop"}
    assert set(members(Sensor)) == members(ShotSensor).keys() | members(StreamSensor).keys() \
        | {"port_name", "disarm"}
