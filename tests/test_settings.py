"""One source for settings: every SolverConfig/DivideConfig field reaches the flags, the wire and back.

The values are derived from the fields themselves (not listed here), so a field
added to config.py is covered at once, and the test fails until it travels.
"""

from __future__ import annotations

import dataclasses

import pytest

from dcrad.cli import build_parser
from dcrad.config import BOUNDARY_MODES, DivideConfig, SolverConfig
from dcrad.errors import ConfigError
from dcrad.settings import divide_from_args, from_args, from_pb, missing_on_wire, to_argv, to_pb
from dcrad.v1 import dcrad_pb2 as pb

CASES = [(SolverConfig, pb.SolverSettings), (DivideConfig, pb.DivideSettings)]


def _other_value(cls, f: dataclasses.Field):
    """A valid value of field ``f`` different from its default (tries a few)."""
    d = getattr(cls(), f.name)
    if isinstance(d, bool):
        tries = [not d]
    elif isinstance(d, int):
        tries = [d + 1, d * 2, max(d - 1, 0)]
    elif isinstance(d, float):
        tries = [d * 1.5 + 0.25, d * 0.5, 0.0]
    elif isinstance(d, str):
        tries = [*BOUNDARY_MODES, d + "x"]
    else:
        raise AssertionError(f"{cls.__name__}.{f.name}: settings must be bool, int, float or str, not {type(d)}")
    for v in tries:
        if v == d:
            continue
        try:
            cls(**{f.name: v})
        except ConfigError:
            continue
        return v
    raise AssertionError(f"{cls.__name__}.{f.name}: found no valid non-default value to test with")


def _variants(cls):
    """One instance per field with that field off its default, and one with all of them off."""
    one = {f.name: _other_value(cls, f) for f in dataclasses.fields(cls)}
    out = [cls(**{k: v}) for k, v in one.items()]
    try:
        out.append(cls(**one))
    except ConfigError:
        pass  # some combinations are invalid together; each field alone still travels
    return out


@pytest.mark.parametrize("cls,message", CASES, ids=["solver", "divide"])
def test_every_field_has_a_twin_with_presence_on_the_wire(cls, message):
    assert missing_on_wire(cls, message) == []
    for f in dataclasses.fields(cls):
        default = getattr(cls(), f.name)
        assert type(default).__name__ == f.type, f"{f.name}: the default's type must be the annotated one"
        assert f.metadata.get("help"), f"{f.name}: give it a help line with config.setting(default, help)"


@pytest.mark.parametrize("cls,message", CASES, ids=["solver", "divide"])
def test_every_field_round_trips_through_the_proto_bytes(cls, message):
    for cfg in _variants(cls):
        raw = to_pb(cfg, message).SerializeToString()
        assert from_pb(cls, message.FromString(raw)) == cfg


def test_an_empty_message_means_the_defaults_and_explicit_zero_stays_zero():
    assert from_pb(SolverConfig, pb.SolverSettings()) == SolverConfig()
    assert from_pb(DivideConfig, pb.DivideSettings()) == DivideConfig()
    # the old `s.tol or d.tol` turned tol 0 into 0.01 on the service path
    zero = SolverConfig(tol=0.0)
    raw = to_pb(zero, pb.SolverSettings).SerializeToString()
    assert from_pb(SolverConfig, pb.SolverSettings.FromString(raw)).tol == 0.0
    # as the client sends it: a dict of field names
    assert from_pb(SolverConfig, pb.SolverSettings(tol=0.0, seed=0)) == zero


def test_a_dataclass_field_without_a_proto_twin_is_refused_by_name():
    @dataclasses.dataclass(frozen=True)
    class Grown(SolverConfig):
        new_knob: float = 0.1

    with pytest.raises(ConfigError, match="lacks new_knob"):
        to_pb(Grown(), pb.SolverSettings)
    assert missing_on_wire(Grown, pb.SolverSettings) == ["new_knob"]


def test_invalid_values_from_the_wire_name_the_setting():
    with pytest.raises(ConfigError, match="tol=2"):
        from_pb(SolverConfig, pb.SolverSettings(tol=2.0))
    with pytest.raises(ConfigError, match="divide setting"):
        from_pb(DivideConfig, pb.DivideSettings(mode="sideways"))


@pytest.mark.parametrize("command", ["solve", "submit", "compare"])
def test_every_solver_field_round_trips_through_the_command_line(command):
    parser = build_parser()
    assert from_args(SolverConfig, parser.parse_args([command, "x"])) == SolverConfig()
    for cfg in _variants(SolverConfig):
        args = parser.parse_args([command, "x", *to_argv(cfg)])
        assert from_args(SolverConfig, args) == cfg


@pytest.mark.parametrize("command", ["solve", "submit"])
def test_every_divide_field_round_trips_through_the_command_line(command):
    parser = build_parser()
    for cfg in _variants(DivideConfig):
        argv = [a.replace("--mode", "--boundary") for a in to_argv(cfg)]
        args = parser.parse_args([command, "x", *argv])
        assert divide_from_args(args, args.subscenes) == cfg
