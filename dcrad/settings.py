"""Settings dataclasses <-> command-line flags and protobuf messages, by field name.

One source for settings: the fields of ``SolverConfig`` (and ``DivideConfig``)
with their defaults and help (``config.setting``) drive

* ``add_flags``: one ``--flag`` per field (``--time-limit`` for ``time_limit``;
  ``--x/--no-x`` for a bool), default and help from the field;
* ``from_args``: the dataclass back from the parsed namespace;
* ``to_pb`` / ``from_pb``: the message field of the same name
  (``dcrad.v1.SolverSettings``, ``DivideSettings``); message fields have
  presence, so an unset field is the default and an explicit 0 stays 0;
* the report's ``settings`` (``SolverConfig.as_dict``).

``missing_on_wire`` names fields that have no twin in the message; ``to_pb`` and
``from_pb`` refuse such a dataclass, and tests/test_settings.py checks every field
travels.  They take the message class from their caller and use it by name
(``Message`` below): the core does not import protobuf (tests/test_layers.py).
"""

from __future__ import annotations

import argparse
import dataclasses
import datetime
import math
from typing import TYPE_CHECKING, Any, Protocol, TypeVar

from dcrad.config import BOUNDARY_MODES, DivideConfig
from dcrad.errors import ConfigError

__all__ = ["add_flags", "add_scene_flags", "add_daylight_flags", "daylight_from_args", "scene_values",
           "add_divide_flags", "divide_from_args", "from_args",
           "to_argv", "to_pb", "from_pb", "missing_on_wire", "flag_name"]

if TYPE_CHECKING:
    from _typeshed import DataclassInstance

T = TypeVar("T", bound="DataclassInstance")  # a settings dataclass


class Message(Protocol):
    """What ``to_pb`` / ``from_pb`` use of a protobuf message (``google.protobuf.message.Message``):
    its descriptor and field presence; its fields are set and read by name."""

    DESCRIPTOR: Any

    def HasField(self, field_name: str, /) -> bool: ...


M = TypeVar("M", bound=Message)  # a protobuf message type


def flag_name(name: str) -> str:
    return "--" + name.replace("_", "-")


def whole(text: str) -> int:
    """argparse type of a count flag: a whole number, written ``2000000``, ``2_000_000`` or ``2e6``."""
    try:
        return int(text)
    except ValueError:
        pass
    try:
        x = float(text)
    except ValueError:
        x = math.nan
    if not (math.isfinite(x) and x == int(x)):
        raise argparse.ArgumentTypeError(f"{text!r} is not a whole number")
    return int(x)


def _flagged(cls) -> list[dataclasses.Field]:
    return [f for f in dataclasses.fields(cls) if f.metadata.get("flag", True)]


def add_flags(parser: argparse.ArgumentParser, cls, skip: tuple[str, ...] = (),
              only: tuple[str, ...] | None = None) -> None:
    """One ``--flag`` per field of the settings dataclass ``cls`` (except ``skip``; only ``only``)."""
    d = cls()
    for f in _flagged(cls):
        if f.name in skip or (only is not None and f.name not in only):
            continue
        default = getattr(d, f.name)
        help = f"{f.metadata.get('help', f.name)} (default {default:g})" if isinstance(default, float) \
            else f"{f.metadata.get('help', f.name)} (default {default})"
        if isinstance(default, bool):
            parser.add_argument(flag_name(f.name), dest=f.name, action=argparse.BooleanOptionalAction,
                                default=default, help=help)
        else:
            kind = whole if isinstance(default, int) else type(default)
            parser.add_argument(flag_name(f.name), dest=f.name, type=kind, default=default, help=help)


def add_scene_flags(parser: argparse.ArgumentParser) -> None:
    """``--patch-size`` and ``--scale``: how a scene file becomes patches (not solver settings)."""
    parser.add_argument("--patch-size", type=float, default=0.0,
                        help="element size in metres: larger triangles are split to it (default 0: automatic, "
                             "the rays' mean free path / 6; see docs/design.md, The mesh follows the light)")
    parser.add_argument("--scale", type=float, default=1.0,
                        help="multiply scene coordinates by this (unit conversion to metres)")
    parser.add_argument("--up", default="auto", choices=("auto", "x", "y", "z", "-x", "-y", "-z"),
                        help="the scene's up axis (default auto: detected; see docs/guide.md, Units and conventions)")
    parser.add_argument("--two-sided", action="store_true",
                        help="every surface receives and reflects light on both sides")
    parser.add_argument("--workplane", type=float, default=0.0,
                        help="height in metres above the floor of a work-plane illuminance grid (default 0: none)")
    parser.add_argument("--luminaires", default=None, metavar="SCHEDULE.json",
                        help="luminaires from photometric files (.ies, .ldt) placed by a JSON schedule, in the "
                             "scene file's coordinates (see docs/guide.md, Luminaires); in this process only")
    add_daylight_flags(parser)


def add_daylight_flags(parser: argparse.ArgumentParser) -> None:
    """``--sky`` and its companions (transport/sky.py; ``daylight_from_args`` reads them back)."""
    g = parser.add_argument_group("daylight (see docs/guide.md, Daylight)")
    g.add_argument("--sky", default=None, metavar="NAME",
                   help="light the model from outside: uniform, cie-overcast, clear (with sun) or iso:1 .. iso:15 "
                        "(the CIE standard general skies); rays that leave the model read the sky or the ground")
    g.add_argument("--sky-illuminance", type=float, default=None, metavar="LUX",
                   help="the sky's horizontal diffuse illuminance, unobstructed (default 10000 lx): the daylight "
                        "factor's denominator")
    g.add_argument("--sun-altitude", type=float, default=None, metavar="DEG", help="the sun's altitude, degrees")
    g.add_argument("--sun-azimuth", type=float, default=None, metavar="DEG",
                   help="the sun's compass azimuth, degrees from north clockwise (east 90); north is the file's "
                        "+Y for a Z-up file, -Z for a Y-up one")
    g.add_argument("--site", default=None, metavar="LAT,LON",
                   help="the site's latitude and longitude, degrees (north and east positive), with --time")
    g.add_argument("--time", default=None, metavar="ISO8601",
                   help="local date and time with its UTC offset, e.g. 2026-06-21T12:00+01:00, with --site")
    g.add_argument("--sun-illuminance", type=float, default=None, metavar="LUX",
                   help="the sun's direct normal illuminance (default 80000 lx with --sky clear, else no sun)")
    g.add_argument("--ground-reflectance", type=float, default=None,
                   help="reflectance of the ground outside, lit by the sky and sun (default 0.2)")


#: the daylight flags that mean nothing without --sky
DAYLIGHT_COMPANIONS = ("sky_illuminance", "sun_altitude", "sun_azimuth", "site", "time", "sun_illuminance",
                       "ground_reflectance")


def daylight_from_args(args: argparse.Namespace):
    """The ``DaylightSpec`` (transport/sky.py) of the flags, or None without ``--sky``; ConfigError
    for a companion flag without ``--sky`` or a value that cannot be read."""
    from dcrad.transport.sky import DaylightSpec  # noqa: PLC0415  (the settings module stays light)

    sky = getattr(args, "sky", None)
    given = [name for name in DAYLIGHT_COMPANIONS if getattr(args, name, None) is not None]
    if sky is None:
        if given:
            raise ConfigError(f"{flag_name(given[0])} applies to a daylit run only: give --sky too")
        return None
    site = None
    if args.site is not None:
        try:
            lat, lon = (float(x) for x in str(args.site).split(","))
        except ValueError:
            raise ConfigError(f"--site {args.site!r}: expected LAT,LON in degrees, e.g. 51.5,-0.12") from None
        if not (math.isfinite(lat) and math.isfinite(lon)):
            raise ConfigError(f"--site {args.site!r}: not finite")
        site = (lat, lon)
    when = None
    if args.time is not None:
        try:
            when = datetime.datetime.fromisoformat(str(args.time))
        except ValueError:
            raise ConfigError(f"--time {args.time!r}: expected an ISO 8601 date and time with its UTC offset, "
                              f"e.g. 2026-06-21T12:00+01:00") from None
        if when.tzinfo is None:
            raise ConfigError(f"--time {args.time!r}: give its UTC offset, e.g. 2026-06-21T12:00+01:00")
    kw: dict[str, Any] = {"sky": sky, "sun_altitude": args.sun_altitude, "sun_azimuth": args.sun_azimuth,
                          "site": site, "time": when, "sun_lux": args.sun_illuminance}
    if args.sky_illuminance is not None:
        kw["diffuse_lux"] = float(args.sky_illuminance)
    if args.ground_reflectance is not None:
        kw["ground"] = float(args.ground_reflectance)
    spec = DaylightSpec(**kw)
    spec.check()
    return spec


def scene_values(args: argparse.Namespace) -> dict:
    """The scene flags of ``add_scene_flags`` as SolverSettings fields (patch_size, scale, up, ...)."""
    return {"patch_size": args.patch_size, "scale": args.scale, "up": "" if args.up == "auto" else args.up,
            "two_sided": bool(args.two_sided), "workplane": float(args.workplane)}


def add_divide_flags(parser: argparse.ArgumentParser, subscenes_help: str) -> None:
    """``--subscenes`` (0: the caller's default), ``--boundary`` (DivideConfig.mode) and the
    other DivideConfig fields as flags; ``divide_from_args`` reads them back."""
    d = DivideConfig()
    mode = next(f for f in dataclasses.fields(DivideConfig) if f.name == "mode")
    parser.add_argument("--subscenes", type=int, default=0, help=subscenes_help)
    parser.add_argument("--boundary", dest="mode", choices=BOUNDARY_MODES, default=d.mode,
                        help=f"{mode.metadata['help']} (default {d.mode})")
    add_flags(parser, DivideConfig, skip=("subscenes", "mode"))


def divide_from_args(args: argparse.Namespace, subscenes: int) -> DivideConfig:
    """The DivideConfig of ``add_divide_flags`` with ``subscenes`` cells."""
    return from_args(DivideConfig, args, subscenes=subscenes)


def from_args(cls: type[T], args: argparse.Namespace, **override: Any) -> T:
    """The settings dataclass from parsed flags (fields without a flag keep their default)."""
    kwargs = {f.name: getattr(args, f.name) for f in dataclasses.fields(cls) if hasattr(args, f.name)}
    return cls(**(kwargs | override))


def to_argv(obj) -> list[str]:
    """The flags that ``add_flags``/``from_args`` read back as ``obj``."""
    argv = []
    for f in _flagged(type(obj)):
        value = getattr(obj, f.name)
        if isinstance(value, bool):
            argv.append(flag_name(f.name) if value else "--no-" + flag_name(f.name)[2:])
        else:
            argv += [flag_name(f.name), repr(value) if isinstance(value, float) else str(value)]
    return argv


def missing_on_wire(cls, message_cls: type[Message]) -> list[str]:
    """Fields of ``cls`` with no field of the same name (and presence) in ``message_cls``."""
    by_name = message_cls.DESCRIPTOR.fields_by_name
    return [f.name for f in dataclasses.fields(cls) if f.name not in by_name or not by_name[f.name].has_presence]


def _check(cls, message_cls) -> None:
    missing = missing_on_wire(cls, message_cls)
    if missing:
        raise ConfigError(f"{message_cls.DESCRIPTOR.full_name} lacks {', '.join(missing)} of {cls.__name__}: "
                          f"add them to proto/dcrad/v1/dcrad.proto as optional fields and run `make proto`")


def to_pb(obj, message_cls: type[M], **extra: Any) -> M:
    """A ``message_cls`` with every field of the dataclass ``obj`` set (plus ``extra`` fields)."""
    _check(type(obj), message_cls)
    msg = message_cls(**extra)
    for f in dataclasses.fields(obj):
        setattr(msg, f.name, getattr(obj, f.name))
    return msg


def from_pb(cls: type[T], msg: Message, **override: Any) -> T:
    """The dataclass from a message: fields the message sets, defaults for the others, then ``override``.

    Invalid values raise the dataclass's own ConfigError.
    """
    _check(cls, type(msg))
    kwargs = {f.name: getattr(msg, f.name) for f in dataclasses.fields(cls) if msg.HasField(f.name)}
    return cls(**(kwargs | override))
