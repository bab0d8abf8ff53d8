"""Inputs that used to go silently wrong, or run away, get the right answer or one clear line.

Each case runs on the in-process path and, where it exists, on the service path (a real
coordinator and worker): coordinates near 1e30 and 1e-30 m solve like the same scene in
metres; a light facing away from everything warns; ``--workers`` and ``--subscenes``
outside what the machine and the scene allow exit 2 with one line (INVALID_ARGUMENT on
the service); ``dcrad scenes`` takes the parameters ``solve`` takes; a worker restarted
on the same address shows its new name.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
import urllib.error
import urllib.request
from pathlib import Path

import grpc
import numpy as np
import pytest
from test_service import fetch, npz, submit, watch

import scenes
from coordinator.embedded import LocalCluster, max_local_workers
from coordinator.remote import WorkerPool
from dcrad.config import DivideConfig, SolverConfig
from dcrad.errors import ExchangeError
from dcrad.pipeline import solve_to
from dcrad.v1 import dcrad_pb2 as pb
from dcrad.wire import FileSink, path_chunks

CORNELL_PATCH = 0.06  #: m: a coarse mesh, for speed


def dcrad(*args, cwd=None) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "dcrad.cli", *args], capture_output=True, text=True,
                          cwd=cwd, timeout=600)


def reflected_mean(b: np.ndarray, e: np.ndarray, area: np.ndarray) -> float:
    """Area-weighted mean reflected radiosity B - E (W/m^2)."""
    return float(((b - e).mean(axis=1) * area).sum() / area.sum())


@pytest.fixture(scope="module")
def cornell(tmp_path_factory) -> Path:
    return scenes.write_builtin("cornell", tmp_path_factory.mktemp("cornell"))


@pytest.fixture(scope="module")
def cornell_metres(cornell, tmp_path_factory) -> float:
    out = tmp_path_factory.mktemp("cornell-1m")
    solve_to(cornell, out, SolverConfig(seed=2, tol=0.01), patch_size=CORNELL_PATCH)
    z = np.load(out / "radiosity.npz")
    return reflected_mean(z["patch_B"], z["patch_emission"], z["patch_area"])


@pytest.fixture(scope="module")
def cluster(tmp_path_factory):
    with LocalCluster(workers=1, data=tmp_path_factory.mktemp("inputs-cluster"), web=False) as c:
        yield c


def _away_scene(folder: Path, facing: str) -> Path:
    """A 2 m floor under a 0.5 m light at 1 m whose front faces ``facing`` ("down" or "up")."""
    folder.mkdir(parents=True, exist_ok=True)
    (folder / "s.mtl").write_text("newmtl grey\nKd 0.5 0.5 0.5\nnewmtl lamp\nKd 0 0 0\nKe 10 10 10\n")
    light = "f 5 6 7\nf 5 7 8\n" if facing == "down" else "f 5 7 6\nf 5 8 7\n"
    (folder / "s.obj").write_text(
        "mtllib s.mtl\n"
        "v -1 0 -1\nv -1 0 1\nv 1 0 1\nv 1 0 -1\n"  # floor, front up
        "v -0.25 1 -0.25\nv 0.25 1 -0.25\nv 0.25 1 0.25\nv -0.25 1 0.25\n"
        "o floor\nusemtl grey\nf 1 2 3\nf 1 3 4\n"
        f"o lamp\nusemtl lamp\n{light}")
    return folder / "s.obj"


@pytest.mark.parametrize("scale", [1e30, 1e-30])
def test_extreme_coordinates_solve_like_metres(cornell, cornell_metres, tmp_path, scale, cluster):
    """Before: B = E everywhere (every ray escaped in float32), exit 0."""
    out = tmp_path / "in-process"
    report = solve_to(cornell, out, SolverConfig(seed=2, tol=0.01), patch_size=CORNELL_PATCH * scale, scale=scale)
    z = np.load(out / "radiosity.npz")
    # B - E scales like E (W/m^2 does not depend on the unit of length)
    got = reflected_mean(z["patch_B"], z["patch_emission"], z["patch_area"])
    assert got == pytest.approx(cornell_metres, rel=0.03)
    assert report["ledger"]["closure"] < 1e-9
    job = submit(cluster.address, cornell.parent, cornell.name, {"seed": 2, "tol": 0.01,
                                                               "patch_size": CORNELL_PATCH * scale,
                                                               "scale": scale}, {"subscenes": 1})
    final = watch(cluster.address, job.job_id)[-1]
    assert final.job.state == "done", final.job.error
    zs = npz(fetch(cluster.address, job.job_id))
    assert reflected_mean(zs["patch_B"], zs["patch_emission"], zs["patch_area"]) == pytest.approx(cornell_metres,
                                                                                                 rel=0.03)


@pytest.mark.parametrize("facing", ["up", "down"])
def test_light_facing_away_warns(tmp_path, facing, cluster):
    path = _away_scene(tmp_path / "scene", facing)
    report = solve_to(path, tmp_path / "out", SolverConfig(seed=1, tol=0.01))
    warned = [w for w in report["warnings"] if "escaped the scene" in w]
    job = submit(cluster.address, path.parent, path.name, {"seed": 1, "tol": 0.01}, {"subscenes": 1})
    final = watch(cluster.address, job.job_id)[-1]
    assert final.job.state == "done", final.job.error
    remote = json.loads(bytes(fetch(cluster.address, job.job_id)["report.json"]))
    remote_warned = [w for w in remote["warnings"] if "escaped the scene" in w]
    if facing == "up":  # nothing above: all of it escapes
        assert warned and "lamp" in warned[0] and warned[0].startswith("100.0%")
        assert remote_warned == warned
    else:  # most of it lands on the floor
        assert not warned and not remote_warned


@pytest.mark.parametrize("flag", [("--workers", "-1"), ("--workers", "100000"), ("--subscenes", "-3")])
def test_bad_worker_and_subscene_counts_are_one_line(tmp_path, flag):
    r = dcrad("solve", "cornell", *flag, "--out", str(tmp_path / "o"), cwd=tmp_path)
    assert r.returncode == 2, r.stderr
    lines = r.stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("dcrad: error: ") and flag[0] in lines[0], r.stderr
    if flag == ("--workers", "100000"):
        assert f"at most {max_local_workers()}" in lines[0]


def test_too_many_subscenes_for_the_scene(tmp_path, cluster):
    """Before: --subscenes 1000 on a 4-triangle scene ran for minutes."""
    path = _away_scene(tmp_path / "scene", "down")
    r = dcrad("solve", str(path), "--workers", "0", "--subscenes", "1000", "--out", str(tmp_path / "o"))
    assert r.returncode == 2 and "1000 subscenes" in r.stderr and "at most" in r.stderr, r.stderr
    assert len(r.stderr.strip().splitlines()) == 1
    with pytest.raises(grpc.RpcError) as e:
        submit(cluster.address, path.parent, path.name, {}, {"subscenes": 1000})
    assert e.value.code() == grpc.StatusCode.INVALID_ARGUMENT and "1000 subscenes" in e.value.details()


ABSURD = {  # flag -> what the one line must name
    ("--patch-size", "-1"): "--patch-size -1",
    ("--patch-size", "nan"): "--patch-size nan",
    ("--patch-size", "0.0001"): "patches",  # about 3e8 patches: it ran out of memory meshing
    ("--width", "0"): "preview width 0",  # it failed naming a camera vector of nan
    ("--height", "100000"): "preview height 100000",  # it rendered a 640 x 100000 preview
    ("--iterations", "-3"): "iterations=-3",  # it printed the whole DivideConfig
    ("--seed", "-1"): "seed=-1",  # a traceback from numpy's random streams
    ("--batch-rays", "1000000000000"): "batch_rays=1000000000000",  # accepted: a batch is held in memory whole
    ("--accuracy", "1e-07"): "--accuracy 1e-07",  # ran on with no end in sight (bias 40% after 120 s)
    ("--rays-per-power", "1e+30"): "rays_per_power=1e+30",  # the same
    ("--workplane", "nan"): "--workplane nan",  # a traceback from the report's JSON
    ("--workplane", "1e+30"): "--workplane 1e+30",  # an empty grid above the scene
}


@pytest.mark.parametrize("flag", sorted(ABSURD))
def test_absurd_flags_are_one_line_on_both_paths(tmp_path, cluster, flag):
    """Each exits 2 before any work with one line naming the flag, in process and through
    the service (the preview size and patch size travel in the job spec, the coordinator checks
    them before meshing; a width of 0 there means the default)."""
    path = _away_scene(tmp_path / "scene", "down")
    extra = ("--subscenes", "2") if flag[0] == "--iterations" else ()
    r = dcrad("solve", str(path), "--workers", "0", *flag, *extra, "--out", str(tmp_path / "o"))
    lines = r.stderr.strip().splitlines()
    assert r.returncode == 2 and len(lines) == 1 and lines[0].startswith("dcrad: error: "), r.stderr
    assert ABSURD[flag] in lines[0], lines[0]
    assert not (tmp_path / "o" / "radiosity.npz").exists()
    if flag[0] in ("--patch-size", "--iterations", "--accuracy", "--rays-per-power", "--workplane"):
        field = flag[0][2:].replace("-", "_")
        solver = {field: float(flag[1])} if flag[0] != "--iterations" else {}
        divide = {"iterations": int(flag[1]), "subscenes": 2} if flag[0] == "--iterations" else {}
        with pytest.raises(grpc.RpcError) as e:
            submit(cluster.address, path.parent, path.name, solver, divide)
    elif flag[0] == "--height":
        from coordinator import client

        with pytest.raises(grpc.RpcError) as e:
            client.submit(cluster.address, path, {}, {}, (640, int(flag[1])))
    else:
        return
    assert e.value.code() == grpc.StatusCode.INVALID_ARGUMENT and ABSURD[flag] in e.value.details()


@pytest.mark.parametrize("args", [
    ("coordinator", "--port", "99999"),  # it listened on another port, silently
    ("worker", "--port", "-2"),  # it listened on 65534
    ("coordinator", "--max-upload", "-1"),
    ("coordinator", "--worker-wait", "-5"),
    ("coordinator", "--web-port", "70000"),
    ("coordinator", "--preview-interval", "-1"),
    ("worker", "--capacity", "0"),  # a worker that could take nothing registered
])
def test_absurd_service_flags_are_one_line(tmp_path, args):
    r = dcrad(*args, cwd=tmp_path)
    lines = r.stderr.strip().splitlines()
    assert r.returncode == 2 and f"argument {args[1]}: {args[2]}: must be" in lines[-1], r.stderr
    assert "Traceback" not in r.stderr and "listening" not in r.stdout


def test_a_bad_port_in_the_environment_is_one_line(tmp_path):
    """The defaults from $DCRAD_PORT and friends went through int() while the parser was built:
    a traceback for every command."""
    r = subprocess.run([sys.executable, "-m", "dcrad.cli", "coordinator"], capture_output=True, text=True,
                       cwd=tmp_path, timeout=60, env={**os.environ, "DCRAD_PORT": "abc"})
    assert r.returncode == 2 and "argument --port: 'abc' is not an integer" in r.stderr, r.stderr
    assert "Traceback" not in r.stderr


def test_scenes_takes_the_parameters_solve_takes(tmp_path):
    r = dcrad("scenes", "office:rows=1,cols=2", "--out", str(tmp_path))
    assert r.returncode == 0, r.stderr
    assert Path(r.stdout.strip()) == tmp_path / "office.obj" and (tmp_path / "office.obj").exists()
    for bad in ("nope", "office:rows=x", "office:colour=2"):
        r = dcrad("scenes", bad, "--out", str(tmp_path))
        assert r.returncode == 2 and r.stderr.startswith("dcrad: error: ") and "Traceback" not in r.stderr


def test_a_worker_restarted_on_the_same_address_shows_its_new_name():
    pool = WorkerPool()
    pool.register("10.0.0.5:50052", 4, "old-container")
    pool.register("10.0.0.5:50052", 2, "new-container")
    (w,) = pool.workers.values()
    assert (w.name, w.capacity) == ("new-container", 2)


def test_time_limit_holds_inside_a_barrier(tmp_path, cluster):
    """A barrier of 2000 batches per subscene would run for minutes; the time limit (1 s)
    ends it after the batch that passes the deadline, in process and on a worker (the
    deadline travels in the barrier plan).  Before: the limit was checked at barriers only."""
    path = scenes.write_builtin("furnace", tmp_path / "furnace", rho=0.99)
    report = solve_to(path, tmp_path / "out", SolverConfig(tol=1e-12, time_limit=1.0), patch_size=0.04,
                      divide=DivideConfig(subscenes=2, iterations=2000, mode="binned"))
    job = submit(cluster.address, path.parent, path.name, {"tol": 1e-12, "time_limit": 1.0, "patch_size": 0.04},
                 {"subscenes": 2, "iterations": 2000, "mode": "binned"})
    final = watch(cluster.address, job.job_id)[-1]
    assert final.job.state == "done", final.job.error
    remote = json.loads(bytes(fetch(cluster.address, job.job_id)["report.json"]))
    for r in (report, remote):
        assert r["stats"]["stopped_by"] == "time_limit"
        assert r["divided"]["barriers"] == 1  # the first barrier ended at the deadline
        assert 2 <= r["stats"]["batches"] < 2 * 2000
        assert r["ledger"]["closure"] < 1e-9


def test_uploads_stream_to_disk_chunk_by_chunk(tmp_path):
    """FileSink writes each chunk where it belongs as it comes (nothing is held), with the
    same checks as the in-memory assembler: order, safe paths, the size limit."""
    src = tmp_path / "src" / "scene.obj"
    src.parent.mkdir()
    src.write_bytes(bytes(range(256)) * 5000)  # 1.28 MB: two chunks of 1 MiB and a tail
    chunks = list(path_chunks(src, "sub/scene.obj"))
    assert len(chunks) == 2 and sum(len(c.data) for c in chunks) == src.stat().st_size
    sink = FileSink(tmp_path / "dst", max_bytes=10 << 20)
    sink.add(chunks[0])
    assert (tmp_path / "dst" / "sub" / "scene.obj").stat().st_size == len(chunks[0].data)  # on disk already
    sink.add(chunks[1])
    sink.close()
    assert (tmp_path / "dst" / "sub" / "scene.obj").read_bytes() == src.read_bytes()
    with pytest.raises(ExchangeError, match="too large"):
        FileSink(tmp_path / "small", max_bytes=1000).add(chunks[0])
    with pytest.raises(ExchangeError, match="offset"):
        FileSink(tmp_path / "order", max_bytes=10 << 20).add(chunks[1])
    with pytest.raises(ExchangeError, match="relative"):
        FileSink(tmp_path / "esc", max_bytes=10 << 20).add(pb.FileChunk(path="../x", total_bytes=1, data=b"x"))
    empty = tmp_path / "src" / "empty.mtl"
    empty.write_bytes(b"")
    sink = FileSink(tmp_path / "dst", max_bytes=10)
    for c in path_chunks(empty, "empty.mtl"):
        sink.add(c)
    sink.close()
    assert (tmp_path / "dst" / "empty.mtl").read_bytes() == b"" and sink.files == {"empty.mtl": 0}


def test_max_upload_is_documented():
    r = dcrad("coordinator", "--help")
    assert "512 MiB" in r.stdout and "DCRAD_MAX_UPLOAD" in r.stdout
    readme = (Path(__file__).resolve().parents[1] / "README.md").read_text()
    assert "512 MiB" in readme


def test_web_long_ids_get_a_clean_404_and_no_traceback(tmp_path):
    """Before: an 8 KB id got aiohttp's 400 with a traceback in the coordinator's log."""
    with LocalCluster(workers=0, data=tmp_path) as c:
        for route in ("/jobs/", "/api/jobs/", "/jobs/x/preview.png?id="):
            with pytest.raises(urllib.error.HTTPError) as e:
                urllib.request.urlopen(c.web_url + route + "y" * 8200, timeout=30)
            body = e.value.read()
            assert e.value.code == 404 and len(body) < 4000, (route, e.value.code)
        with pytest.raises(urllib.error.HTTPError) as e:  # beyond what is read at all: a plain 400
            urllib.request.urlopen(c.web_url + "/jobs/" + "y" * 40000, timeout=30)
        assert e.value.code == 400
    log = "".join(p.read_text() for p in tmp_path.glob("coordinator-*.log"))
    assert "Traceback" not in log and "refused a bad HTTP request (400)" in log


def test_huge_coordinates_are_named_on_every_path(tmp_path, cluster):
    """Before: --scale 1e300 failed as "invalid max_edge=inf"; a vertex at 1e200 m the same way."""
    path = _away_scene(tmp_path / "scene", "down")
    far = tmp_path / "far"
    far.mkdir()
    (far / "s.mtl").write_text((path.parent / "s.mtl").read_text())
    (far / "s.obj").write_text(path.read_text().replace("v 1 0 1\n", "v 1e200 0 1\n"))
    for scene, flags in ((path, ("--scale", "1e300")), (far / "s.obj", ())):
        r = dcrad("solve", str(scene), "--workers", "0", *flags, "--out", str(tmp_path / "o"))
        lines = r.stderr.strip().splitlines()
        assert r.returncode == 2 and len(lines) == 1 and "from the origin" in lines[0], r.stderr
        assert "check --scale" in lines[0] and "s.obj" in lines[0]
        with pytest.raises(grpc.RpcError) as e:
            submit(cluster.address, scene.parent, scene.name, {"scale": float(flags[1]) if flags else 1.0}, {})
        assert e.value.code() == grpc.StatusCode.INVALID_ARGUMENT and "from the origin" in e.value.details()


def test_count_flags_take_whole_numbers_as_people_write_them(capsys):
    """``--max-rays 2e6`` is two million (argparse's int refused it: "invalid int value"); a count
    that is not whole is one line naming it."""
    from dcrad.cli import build_parser

    args = build_parser().parse_args(["solve", "office", "--max-rays", "2e6", "--batch-rays", "65_536",
                                      "--min-rays", "8"])
    assert (args.max_rays, args.batch_rays, args.min_rays) == (2_000_000, 65_536, 8)
    assert all(type(v) is int for v in (args.max_rays, args.batch_rays, args.min_rays))
    for bad in ("1.5", "abc", "nan", "inf"):
        with pytest.raises(SystemExit) as exc:
            build_parser().parse_args(["solve", "office", "--max-rays", bad])
        assert exc.value.code == 2
        assert f"argument --max-rays: '{bad}' is not a whole number" in capsys.readouterr().err


def test_a_folder_named_like_a_built_in_scene_is_not_taken_for_it(tmp_path):
    """`dcrad solve cornell --out cornell`, run twice, leaves a folder `cornell` in the working
    directory: the built-in scene is still what `cornell` means (a file of that name would win).  A
    folder given where a scene file belongs is named as a folder, not as an unknown format ''."""
    (tmp_path / "cornell").mkdir()
    r = dcrad("solve", "cornell", "--patch-size", "0.2", "--accuracy", "0.2", "--workers", "0", "--width", "32",
              "--height", "24", "--out", "cornell", cwd=tmp_path)
    assert r.returncode == 0, r.stderr
    assert json.loads((tmp_path / "cornell" / "report.json").read_text())["scene"]["input_triangles"] > 0
    (tmp_path / "rooms").mkdir()
    r = dcrad("solve", "rooms", "--workers", "0", "--out", "out", cwd=tmp_path)
    assert r.returncode == 2 and r.stderr.strip().splitlines()[-1] == (
        "dcrad: error: rooms is a folder, not a scene file: give the .obj, .gltf or .glb in it"), r.stderr
