"""Light sources that are not patches (emitters.py) as arrays, for a run on workers.

A shared run's workers each hold the whole scene: the patch table travels as arrays
(``Patches.table_arrays``) and its light sources beside it, as one array ``sources`` of
UTF-8 JSON: a list of each source's ``to_wire()`` with its kind.  JSON keeps every float
exact (the shortest repr that reads back to the same double), so a worker's copy of a source
lights the scene to the bit as the coordinator's does.  Arrays a source gives in its ``to_wire``
(a divided run's ``Gathered`` light, per patch) travel beside the JSON as arrays of their own.  A new
kind of emitter that should run on workers adds ``to_wire`` / ``from_wire`` and a line to ``KINDS``.
"""

from __future__ import annotations

import json
from typing import Any

import numpy as np

from dcrad.errors import ConfigError
from dcrad.transport.emitters import Gathered, PointSource
from dcrad.transport.luminaires import Luminaire
from dcrad.transport.punctual import PunctualLight, SpotLight
from dcrad.transport.sky import Sky, Sun

__all__ = ["KINDS", "sources_table", "sources_from_table"]

#: the kinds of light source that travel, by the name the wire gives them
KINDS: dict[str, Any] = {"point": PointSource, "luminaire": Luminaire, "gltf_point": PunctualLight,
                          "gltf_spot": SpotLight, "sky": Sky, "sun": Sun, "gathered": Gathered}
_NAMES = {cls: name for name, cls in KINDS.items()}
#: the JSON stand-in for an array that travels beside it (``sources_table``)
_ARRAY = "__array__"


def sources_table(sources) -> dict:
    """{"sources": uint8 JSON, and "source_I_KEY" for each array a source's ``to_wire`` gives} for the
    patch table's arrays ({} when there are none); ConfigError
    naming a source of a kind that cannot travel."""
    if not sources:
        return {}
    out = []
    arrays: dict[str, np.ndarray] = {}
    for i, s in enumerate(sources):
        kind = _NAMES.get(type(s))
        if kind is None:
            raise ConfigError(f"{getattr(s, 'name', type(s).__name__)}: a light source of kind {type(s).__name__} "
                              f"runs in this process only (--workers 0)")
        wire = s.to_wire()
        for key, value in wire.items():  # per-patch arrays (a Gathered source's) travel as arrays, not JSON
            if isinstance(value, np.ndarray):
                arrays[f"source_{i}_{key}"] = value
                wire[key] = {_ARRAY: f"source_{i}_{key}"}
        out.append({"kind": kind, **wire})
    return {"sources": np.frombuffer(json.dumps(out).encode(), np.uint8), **arrays}


def sources_from_table(arrays: dict) -> tuple:
    """The sources of ``sources_table`` (() without them); ValueError for a kind this side does not know."""
    raw = arrays.get("sources")
    if raw is None or len(raw) == 0:
        return ()
    out = []
    for d in json.loads(np.asarray(raw, np.uint8).tobytes().decode()):
        cls = KINDS.get(d.get("kind"))
        if cls is None:
            raise ValueError(f"unknown kind of light source {d.get('kind')!r}")
        for key, value in d.items():
            if isinstance(value, dict) and _ARRAY in value:
                if value[_ARRAY] not in arrays:
                    raise ValueError(f"light source {d.get('name')!r}: its array {value[_ARRAY]!r} is missing")
                d[key] = np.asarray(arrays[value[_ARRAY]])
        out.append(cls.from_wire(d))
    return tuple(out)
