"""The wire layer: arrays and files in chunks, the ledger message, and generated code freshness."""

from __future__ import annotations

import re
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from dcrad.errors import ExchangeError
from dcrad.solving.energy import Ledger
from dcrad.v1 import dcrad_pb2 as pb
from dcrad.wire import (
    CHUNK_BYTES,
    FileAssembler,
    array_chunks,
    arrays_to_chunks,
    assemble_arrays,
    file_chunks,
    ledger_from_pb,
    ledger_to_pb,
    safe_relpath,
)

ROOT = Path(__file__).resolve().parents[1]


def test_arrays_round_trip_in_chunks_under_the_grpc_limit(np_rng):
    arrays = {"f8": np_rng.random((500_000, 3)), "f4": np_rng.random(7).astype(np.float32),
              "i8": np.arange(-5, 5), "empty": np.zeros((0, 3)), "b": np.array([True, False]),
              "u1": np.frombuffer(b'{"a": 1}', np.uint8), "big_endian": np.arange(4, dtype=">f8")}
    chunks = list(arrays_to_chunks(arrays))
    assert max(c.ByteSize() for c in chunks) < 4 * 1024 * 1024
    assert all(len(c.data) <= CHUNK_BYTES for c in chunks)
    back = assemble_arrays(chunks)
    for k, v in arrays.items():
        assert np.array_equal(back[k], v) and back[k].shape == v.shape, k
    assert back["big_endian"].dtype.str == "<f8"


def test_bad_chunks_are_refused():
    good = list(array_chunks("x", np.arange(100.0), chunk=64))
    with pytest.raises(ExchangeError, match="offset"):
        assemble_arrays([good[0], good[2]])
    with pytest.raises(ExchangeError, match="got"):
        assemble_arrays(good[:-1])
    bad = pb.ArrayChunk(name="o", dtype="|O", shape=[1], offset=0, total_bytes=8, data=b"\0" * 8)
    with pytest.raises(ExchangeError, match="not allowed"):
        assemble_arrays([bad])
    lie = pb.ArrayChunk(name="s", dtype="<f8", shape=[3], offset=0, total_bytes=16, data=b"\0" * 16)
    with pytest.raises(ExchangeError, match="needs 24 bytes"):
        assemble_arrays([lie])
    with pytest.raises(ExchangeError, match="cannot go on the wire"):
        list(array_chunks("c", np.array([1 + 2j])))


def test_ledger_message_round_trip():
    led = Ledger(emitted=np.array([3.0, 2.0, 1.0]), absorbed=np.array([1.0, 1.0, 0.5]),
                 unshot=np.array([2.0, 1.0, 0.5]))
    back = ledger_from_pb(ledger_to_pb(led))
    for k, v in led.as_arrays().items():
        assert np.array_equal(getattr(back, k), v)
    assert ledger_to_pb(led).closure == led.closure() == 0.0


def test_files_in_chunks_with_a_size_limit():
    data = bytes(range(256)) * 5000
    asm = FileAssembler(max_bytes=10**7)
    for c in file_chunks(data, "scene/room.obj", chunk=10_000):
        asm.add(c)
    assert bytes(asm.files["scene/room.obj"]) == data
    small = FileAssembler(max_bytes=1000)
    with pytest.raises(ExchangeError, match="too large"):
        for c in file_chunks(data, "a.obj", chunk=100):
            small.add(c)
    for bad in ("../etc/passwd", "/abs.obj", "a/../../b", "", "C:/x.obj"):
        with pytest.raises(ExchangeError):
            safe_relpath(bad)


def _code(text: str) -> str:
    """Generated code without the generators' own version stamps: they follow whichever grpcio-tools
    and protobuf release the index serves the day a machine installs (a fresh machine got
    grpcio-tools 1.85.4 against the committed code's 1.85.1), not the proto."""
    text = re.sub(r"GRPC_GENERATED_VERSION = '[^']*'", "GRPC_GENERATED_VERSION = ''", text)
    text = re.sub(r"# Protobuf Python Version: \S+", "# Protobuf Python Version:", text)
    return re.sub(r"ValidateProtobufRuntimeVersion\((?:[^()]|\([^()]*\))*\)", "ValidateProtobufRuntimeVersion()", text)


def test_generated_code_is_fresh(tmp_path):
    """The committed dcrad/v1 code equals what protoc makes of proto/ now (version stamps aside)."""
    subprocess.run([sys.executable, "-m", "grpc_tools.protoc", "-I", str(ROOT / "proto"),
                    f"--python_out={tmp_path}", f"--grpc_python_out={tmp_path}", f"--pyi_out={tmp_path}",
                    str(ROOT / "proto" / "dcrad" / "v1" / "dcrad.proto")], check=True)
    for name in ("dcrad_pb2.py", "dcrad_pb2_grpc.py", "dcrad_pb2.pyi"):
        fresh = (tmp_path / "dcrad" / "v1" / name).read_text()
        committed = (ROOT / "dcrad" / "v1" / name).read_text()
        assert _code(fresh) == _code(committed), f"dcrad/v1/{name} is stale: run `make proto`"


def test_barrier_plan_goal_share_round_trips_and_bad_shares_are_refused():
    """A landing barrier's share (divide.landing_goal) reaches the worker unchanged; a share
    outside [0, 1) is refused by name, and a plan with only a share is still a plan."""
    import math

    from dcrad.division.subscene import BarrierPlan
    from dcrad.solving.stiffness import Stiffness
    from dcrad.wire import plan_fields, plan_from_pb

    plan = BarrierPlan(Stiffness.none(), np.zeros(3), 0.0, 0.179)
    back = plan_from_pb(pb.IterateRequest(batches=4, **plan_fields(plan)))
    assert back is not None and back.goal == 0.179 and not back.stiffness.active
    assert plan_from_pb(pb.IterateRequest(batches=4)) is None  # no plan: plain barriers
    for bad in (1.0, -0.1, math.nan):
        with pytest.raises(ExchangeError, match="goal_share"):
            plan_from_pb(pb.IterateRequest(batches=4, **(plan_fields(plan) | {"goal_share": bad})))


def test_barrier_plan_ray_share_round_trips_and_a_negative_one_is_refused():
    """A subscene's share of the job's ray budget reaches the worker (a plan with only a share is a
    plan: the worker's doIterations must stop at it); a negative share is refused by name."""
    from dcrad.division.subscene import BarrierPlan
    from dcrad.solving.stiffness import Stiffness
    from dcrad.wire import plan_fields, plan_from_pb

    plan = BarrierPlan(Stiffness.none(), np.zeros(3), rays_left=123_456_789_012)
    back = plan_from_pb(pb.IterateRequest(batches=4, **plan_fields(plan)))
    assert back is not None and back.rays_left == 123_456_789_012 and back.goal == 0.0
    with pytest.raises(ExchangeError, match="rays_left"):
        plan_from_pb(pb.IterateRequest(batches=4, **(plan_fields(plan) | {"rays_left": -1})))


def test_share_phases_cross_the_wire_as_the_protos_enum():
    """Every phase a shared run uses has its own SharePhase value, and back; an unknown name is refused
    by name, and an unset or unknown value reads as no phase (the worker refuses it)."""
    from dcrad.wire import SHARE_PHASES, share_phase, share_phase_name

    values = {share_phase(name) for name in ("pilot", "direct", "replica", "gather", "stop")}
    assert len(values) == len(SHARE_PHASES) == 5 and pb.SHARE_PHASE_UNSPECIFIED not in values
    for name in SHARE_PHASES:
        header = pb.ShareHeader.FromString(pb.ShareHeader(phase=share_phase(name)).SerializeToString())
        assert share_phase_name(header.phase) == name
    assert share_phase_name(pb.SHARE_PHASE_UNSPECIFIED) == "" and share_phase_name(99) == ""
    with pytest.raises(ValueError, match="melt"):
        share_phase("melt")
