"""The pictures (scene.glb, the preview and illuminance images) written by a coordinator's views
process (coordinator/ahead.py, ``ViewsAhead.paint``) while the coordinator writes the npz and PLY
are the files ``write_outputs`` writes alone, bit for bit; if that process fails or dies, the
coordinator writes them itself, with a warning, and the process is gone."""

from __future__ import annotations

import logging
from pathlib import Path

import numpy as np
import pytest

from coordinator.ahead import ViewsAhead
from dcrad.pipeline import prepare, resolve_scene, write_outputs

SIZE = (160, 120)


def _same_files(a: Path, b: Path) -> None:
    """Every file of ``a`` equals ``b``'s: bytes; EXR pixels and size (the header holds a capture
    date); npz arrays and size (the zip holds dates)."""
    import OpenImageIO as oiio

    names = sorted(p.name for p in a.iterdir())
    assert names == sorted(p.name for p in b.iterdir())
    assert {"radiosity.npz", "patches.ply", "scene.glb", "preview.png", "preview.exr", "preview_top.png",
            "preview_top.exr", "illuminance.png"} <= set(names)
    for name in names:
        x, y = a / name, b / name
        if name.endswith(".exr"):
            ix, iy = oiio.ImageInput.open(str(x)), oiio.ImageInput.open(str(y))
            px, py = ix.read_image(oiio.HALF), iy.read_image(oiio.HALF)
            ix.close()
            iy.close()
            assert px.shape == py.shape and px.tobytes() == py.tobytes(), name
            assert x.stat().st_size == y.stat().st_size, name
        elif name.endswith(".npz"):
            with np.load(x) as dx, np.load(y) as dy:
                assert sorted(dx.files) == sorted(dy.files)
                for k in dx.files:
                    assert dx[k].dtype == dy[k].dtype and dx[k].tobytes() == dy[k].tobytes(), (name, k)
            assert x.stat().st_size == y.stat().st_size, name
        else:
            assert x.read_bytes() == y.read_bytes(), name


@pytest.fixture(scope="module")
def floor(tmp_path_factory):
    """The office floor (a floor plan: both views) with a made-up B and unshot radiosity."""
    scene, patches, _ = prepare(resolve_scene("office", tmp_path_factory.mktemp("scene")))
    rng = np.random.default_rng(3)
    patches.radiosity = patches.emission + 3.0 * rng.random((len(patches), 3)) * patches.rho
    patches.unshot = 0.01 * rng.random((len(patches), 3))
    return scene, patches


def _outputs(folder: Path, scene, patches, views, painter=None) -> dict:
    sections: dict = {}
    written = write_outputs(folder, scene, patches, *SIZE, sections, views=views, painter=painter)
    return {"written": written, "photometry": sections["photometry"]}


def test_pictures_written_by_the_views_process_equal_those_written_here(tmp_path, floor, caplog):
    scene, patches = floor
    ahead = ViewsAhead(patches, scene.camera, *SIZE, (32, 24))
    try:
        views = ahead.future.result(timeout=120)
        here = _outputs(tmp_path / "here", scene, patches, views)
        with caplog.at_level(logging.WARNING, logger="dcrad"):
            there = _outputs(tmp_path / "there", scene, patches, views, ahead.paint)
        assert not [r for r in caplog.records if "pictures" in r.getMessage()]
        assert ahead._proc.wait(30) == 0  # done: it ends once it has sent them
    finally:
        ahead.close()
    assert here == there  # the report's outputs (in order) and photometry section
    assert list(there["written"]) == ["radiosity", "patches", "mesh", "preview_png", "preview_exr",
                                      "preview_top_png", "preview_top_exr", "illuminance_png"]
    _same_files(tmp_path / "here", tmp_path / "there")


@pytest.mark.parametrize("how", ["killed", "failed"])
def test_pictures_are_written_here_when_the_views_process_dies_or_fails(tmp_path, floor, caplog, how):
    scene, patches = floor
    ahead = ViewsAhead(patches, scene.camera, *SIZE, (32, 24))
    try:
        views = ahead.future.result(timeout=120)
        here = _outputs(tmp_path / "here", scene, patches, views)
        painter = ahead.paint
        if how == "killed":
            ahead._proc.kill()
            ahead._proc.wait(10)
        else:  # its write_pictures raises (one lux for the whole table), the coordinator's does not
            def painter(out, radiosity, lux, rotation):
                return ahead.paint(out, radiosity, lux[:1], rotation)
        with caplog.at_level(logging.WARNING, logger="dcrad"):
            there = _outputs(tmp_path / "there", scene, patches, views, painter)
        warned = [r.getMessage() for r in caplog.records if "pictures were not written" in r.getMessage()]
        assert len(warned) == 1 and ("Traceback" in warned[0]) == (how == "failed")
        assert ahead._proc.poll() is not None  # ended: it writes nothing more beside these
    finally:
        ahead.close()
    assert here == there
    _same_files(tmp_path / "here", tmp_path / "there")


def test_the_views_process_paints_only_where_the_coordinator_holds_no_corner_pairs(floor):
    """jobs.py hands the pictures to the views process when its own views came without the corner
    pairs (a table above render.KEEP_PAIRS), and writes them itself when they came with them."""
    from types import SimpleNamespace

    from coordinator.jobs import JobManager
    from dcrad.outputs.render import CornerSmoother

    _, patches = floor
    job = SimpleNamespace(ahead=SimpleNamespace(paint="paint"))
    kept, formed = CornerSmoother(patches), CornerSmoother(patches, keep_pairs=0)
    assert kept.kept and not formed.kept
    assert JobManager._painter(job, SimpleNamespace(smoother=formed)) == "paint"
    assert JobManager._painter(job, SimpleNamespace(smoother=kept)) is None
    assert JobManager._painter(job, None) is None
    assert JobManager._painter(SimpleNamespace(ahead=None), SimpleNamespace(smoother=formed)) is None
