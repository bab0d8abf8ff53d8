"""The subscene handle interface and the boundary modes, each in one place."""

from __future__ import annotations

import inspect

import pytest

import scenes
from coordinator.remote import RemoteSubscene, WorkerPool
from dcrad.config import BOUNDARY_MODES, DivideConfig, SolverConfig
from dcrad.division.boundary import MODES, boundary_mode
from dcrad.division.divide import build_subscenes
from dcrad.division.subscene import SubsceneHandle
from dcrad.errors import ConfigError
from dcrad.pipeline import prepare


@pytest.fixture(scope="module")
def cornell(tmp_path_factory):
    _, p, _ = prepare(scenes.write_builtin("cornell", tmp_path_factory.mktemp("c")), 0.08)
    return p


def test_the_modes_the_settings_accept_are_the_modes_there_are():
    assert tuple(MODES) == BOUNDARY_MODES
    with pytest.raises(ConfigError, match="binned, exact"):
        boundary_mode("sideways")


@pytest.mark.parametrize("mode", BOUNDARY_MODES)
def test_in_process_and_remote_subscenes_are_handles_with_one_buffer_type(cornell, mode):
    cfg = SolverConfig(tol=0.0, max_rays=50_000, seed=3)
    subs, *_ = build_subscenes(cornell, cfg, DivideConfig(subscenes=2, mode=mode))
    remote = RemoteSubscene("job", subs[0], WorkerPool())
    for h in (subs[0], remote):
        assert isinstance(h, SubsceneHandle)
        for name in ("iterate", "collect", "deliver", "state", "radiosity", "interrupt"):
            want = list(inspect.signature(getattr(SubsceneHandle, name)).parameters)[1:]
            assert list(inspect.signature(getattr(h, name)).parameters)[: len(want)] == want, (type(h), name)
    kind = MODES[mode].buffer
    sub = subs[0]
    assert type(sub.sent) is kind  # one type per mode, from the start
    sub.iterate(3)
    assert len(sub.sent) > 0 and type(sub.collect()) is kind and type(sub.sent) is kind
