"""The coordinator's web status endpoint, against a real two-worker cluster.

The browser tests drive Debian's ``chromium`` through Playwright for Python (the
system browser, never a downloaded one: ``.ci/install-browser.sh`` installs it).
Without it they fail, naming the fix.  Screenshots of the job page go to
``test-artifacts/`` (git-ignored): ``job-page.png`` (a finished job; the user's
guide shows a copy, ``docs/job-page.png``), ``job-page-running.png`` and
``job-page-cancelled.png``.
"""

from __future__ import annotations

import contextlib
import json
import os
import re
import shutil
import subprocess
import sys
import time
import urllib.error
import urllib.request
from pathlib import Path

import numpy as np
import pytest

import scenes
from coordinator import client
from coordinator.display import ErrorCurve, LivePreview
from coordinator.embedded import LocalCluster
from dcrad.v1 import dcrad_pb2 as pb

ROOT = Path(__file__).resolve().parents[1]
ARTIFACTS = ROOT / "test-artifacts"
ACCOUNTS = ("emitted", "absorbed", "escaped", "back_faces", "unshot", "in_flight", "imported", "exported")
METRIC_LINE = re.compile(r'^[a-zA-Z_:][a-zA-Z0-9_:]*'
                         r'(\{[a-zA-Z_][a-zA-Z0-9_]*="[^"]*"(,[a-zA-Z_][a-zA-Z0-9_]*="[^"]*")*\})? '
                         r'[-+]?(\d+(\.\d*)?([eE][-+]?\d+)?|Inf|NaN)$')


# == helpers ======================================================================
def http(url: str, method: str = "GET", headers: dict | None = None):
    """(status, content type, body bytes); HTTP errors are returned, not raised."""
    req = urllib.request.Request(url, method=method, headers=headers or {}, data=b"" if method == "POST" else None)
    try:
        with urllib.request.urlopen(req, timeout=30) as r:
            return r.status, r.headers.get("Content-Type", ""), r.read()
    except urllib.error.HTTPError as e:
        return e.code, e.headers.get("Content-Type", ""), e.read()


def api(cluster, path: str):
    status, ctype, body = http(cluster.web_url + path)
    assert status == 200 and ctype.startswith("application/json"), (path, status, body[:200])
    return json.loads(body)


def metrics(cluster) -> dict:
    status, ctype, body = http(cluster.web_url + "/metrics")
    assert status == 200 and ctype.startswith("text/plain") and "version=0.0.4" in ctype
    out = {}
    for line in body.decode().splitlines():
        if line.startswith("#"):
            assert line.startswith(("# HELP ", "# TYPE ")), line
            continue
        assert METRIC_LINE.match(line), f"not Prometheus text format: {line!r}"
        name, value = line.rsplit(" ", 1)
        out[name] = float(value)
    return out


@contextlib.contextmanager
def chromium():
    """Headless Debian chromium via Playwright; fails (never skips) when it is missing."""
    exe = shutil.which("chromium")
    if exe is None:
        pytest.fail("the browser tests need Debian's `chromium` on PATH: run .ci/install-browser.sh "
                    "(apt-get install chromium); Playwright's own browser downloads are not used", pytrace=False)
    from playwright.sync_api import sync_playwright

    with sync_playwright() as pw:
        browser = pw.chromium.launch(executable_path=exe, args=["--no-sandbox"])
        try:
            yield browser
        finally:
            browser.close()


def wait_js(page, expr: str, timeout_s: float = 90.0):
    return page.wait_for_function(f"() => {expr}", timeout=timeout_s * 1000).json_value()


#: the preview shown now: its version and a checksum of its decoded pixels (None while loading)
PREVIEW_PIXELS = """() => {
  const i = document.querySelector('#preview');
  if (Number(i.dataset.version) < 1 || !i.complete || !i.naturalWidth) return null;
  const c = document.createElement('canvas');
  c.width = i.naturalWidth; c.height = i.naturalHeight;
  const x = c.getContext('2d'); x.drawImage(i, 0, 0);
  const d = x.getImageData(0, 0, c.width, c.height).data;
  let h = 0;
  for (let k = 0; k < d.length; k++) h = (Math.imul(h, 31) + d[k]) >>> 0;
  return [Number(i.dataset.version), h, c.width, c.height];
}"""


def preview_after(page, version: int, timeout_s: float = 90.0):
    """Wait until the page shows a preview newer than ``version``; (version, checksum, w, h)."""
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        got = page.evaluate(PREVIEW_PIXELS)
        if got is not None and got[0] > version:
            return got
        time.sleep(0.1)
    raise AssertionError(f"the preview did not pass version {version} within {timeout_s:.0f} s")


def points(page, series: str) -> int:
    return int(page.get_attribute("#chart", f"data-{series}-points"))


@pytest.fixture(scope="module")
def cluster(tmp_path_factory):
    with LocalCluster(workers=2, data=tmp_path_factory.mktemp("web-cluster")) as c:
        assert c.web_url.startswith("http://127.0.0.1:"), c.web_url  # loopback in embedded mode
        yield c


@pytest.fixture(scope="module")
def office(tmp_path_factory):
    return scenes.write_builtin("office", tmp_path_factory.mktemp("office"), rows=2, cols=3, seed=0)


# == the browser ==================================================================
@pytest.mark.browser
def test_job_page_grows_live_and_cancels_in_a_browser(cluster, office):
    # a tolerance it never reaches and a ray density that keeps it from converging to round-off
    # (at 2e5 rays per power it ran out of shots worth a ray after 19 barriers and stopped by
    # itself; at 2e8, in 40-80 s, sometimes before the page had seen two previews): the job runs
    # until the page cancels it (time limit as a safety net)
    job = client.submit(cluster.address, office, {"tol": 1e-30, "rays_per_power": 2e10, "time_limit": 180},
                        {"subscenes": 2})
    ARTIFACTS.mkdir(exist_ok=True)
    with chromium() as browser:
        page = browser.new_page(viewport={"width": 1280, "height": 900})
        errors = []
        page.on("pageerror", lambda e: errors.append(str(e)))
        page.goto(f"{cluster.web_url}/jobs/{job.job_id}")

        # the chart gains points, barrier after barrier
        wait_js(page, "Number(document.querySelector('#chart').dataset.estimatePoints) >= 1")
        n0 = points(page, "estimate")
        wait_js(page, f"Number(document.querySelector('#chart').dataset.estimatePoints) >= {n0 + 2}")
        assert page.locator("#chart circle.estimate").count() >= n0 + 2
        assert "estimated error" in page.inner_text("#legend")

        # the preview is re-rendered at a later barrier and swapped in without a reload
        v1, pixels1, w, h = preview_after(page, 0)
        v2, pixels2, *_ = preview_after(page, v1)
        assert (w, h) == (320, 240) and v2 > v1 and pixels2 != pixels1
        assert page.evaluate("performance.getEntriesByType('navigation').length") == 1  # no reload

        job_state = api(cluster, f"/api/jobs/{job.job_id}")
        assert job_state["state"] == "running" and job_state["preview"]["version"] >= v2
        status, _, body = http(f"{cluster.web_url}/api/jobs/{job.job_id}/report")
        assert status == 409 and "running" in json.loads(body)["error"]  # no report before the end

        page.screenshot(path=str(ARTIFACTS / "job-page-running.png"), full_page=True)

        # cancel from the page
        assert page.is_enabled("#cancel")
        page.click("#cancel")
        wait_js(page, "document.querySelector('#state').textContent === 'cancelled'", 120)
        wait_js(page, "Number(document.querySelector('#chart').dataset.measuredPoints) >= 1", 30)
        legend = page.inner_text("#legend")
        assert "estimated error" in legend and "measured against the state when cancelled" in legend
        assert page.is_hidden("#cancel")  # nothing left to cancel
        page.screenshot(path=str(ARTIFACTS / "job-page-cancelled.png"), full_page=True)
        assert not errors, errors

    final = client.watch(cluster.address, job.job_id)
    assert final.job.state == "cancelled" and final.barrier >= 3
    report = api(cluster, f"/api/jobs/{job.job_id}/report")
    assert report["stats"]["stopped_by"] == "stopped"


# == JSON API = watch stream ======================================================
@pytest.mark.browser  # its last part reads the finished page in chromium
def test_json_api_agrees_with_the_watch_stream(cluster, office, tmp_path):
    before = metrics(cluster)
    job = client.submit(cluster.address, office, {"tol": 1e-4, "seed": 3}, {"subscenes": 2})
    stream: list[pb.Progress] = []
    last = client.watch(cluster.address, job.job_id, stream.append)  # what `dcrad watch` follows
    assert last is stream[-1] and last.job.state == "done", last.job.error
    # and the real CLI's final line
    cli = subprocess.run([sys.executable, "-m", "dcrad.cli", "watch", job.job_id, "--coordinator", cluster.address],
                         capture_output=True, text=True, timeout=60)
    assert cli.returncode == 0, cli.stderr

    d = api(cluster, f"/api/jobs/{job.job_id}")
    p = d["progress"]
    assert (d["id"], d["state"], d["scene"], d["subscenes"]) == (job.job_id, "done", "office.obj", 2)
    assert d["workers"] == list(last.job.workers) and len(d["workers"]) == 2
    assert d["residual"] == last.job.residual and d["elapsed_s"] == pytest.approx(last.job.elapsed_s, abs=1e-6)
    assert (p["barrier"], p["shots"], p["rays"], p["bytes_relayed"]) == (last.barrier, last.shots, last.rays,
                                                                         last.bytes_relayed)
    assert p["rms_estimate"] == last.rms_estimate
    for k in ACCOUNTS:
        assert p["ledger"][k] == list(getattr(last.ledger, k)), k
    assert (p["ledger"]["closure"], p["ledger"]["residual"]) == (last.ledger.closure, last.ledger.residual)
    assert p["subscenes"] == [{"cell": s.cell, "worker": s.worker, "shots": s.shots, "rays": s.rays,
                               "residual": s.residual, "twin_bytes": s.twin_bytes, "reassigned": s.reassigned}
                              for s in last.subscenes]
    assert (f"{last.barrier} barriers" in cli.stdout and f"residual {p['ledger']['residual']:.2e}" in cli.stdout
            and f"{p['rays']:,} rays" in cli.stdout and "done" in cli.stdout), cli.stdout

    # the live curve is the stream's rms estimate, one point per barrier
    firsts = {}
    for m in stream:
        if m.barrier > 0:
            firsts.setdefault(m.barrier, [m.job.elapsed_s, m.rms_estimate, m.barrier])
    assert d["curve"]["estimate"]["points"] == list(firsts.values())
    assert len(firsts) == last.barrier >= 3
    measured = d["curve"]["measured"]
    assert "converged to the residual tol 0.0001" in measured["label"]
    rms = [q[1] for q in measured["points"]]  # every barrier but the last, which is the reference itself
    assert [q[2] for q in measured["points"]] == list(range(1, last.barrier)) and rms[0] > 10 * rms[-1] > 0

    # the list, the report (the same as the fetched report.json), the preview
    listed = {j["id"]: j for j in api(cluster, "/api/jobs")["jobs"]}
    assert listed[job.job_id]["state"] == "done" and listed[job.job_id]["barrier"] == last.barrier
    report = api(cluster, f"/api/jobs/{job.job_id}/report")
    client.fetch(cluster.address, job.job_id, tmp_path / "out")
    assert report == json.loads((tmp_path / "out" / "report.json").read_text())
    assert report == api(cluster, f"/jobs/{job.job_id}/report.json")
    assert report["residual"] == last.ledger.residual and report["divided"]["barriers"] == last.barrier
    assert report["error_curve"]["measured"] == measured
    status, ctype, png = http(cluster.web_url + d["preview"]["url"])
    assert status == 200 and ctype == "image/png" and png[:8] == b"\x89PNG\r\n\x1a\n"
    # the final state is always shown: the result's own preview (the top-down one of a floor plan)
    out = tmp_path / "out"
    assert png == (out / "preview_top.png" if (out / "preview_top.png").is_file() else out / "preview.png").read_bytes()
    assert d["preview"]["barrier"] == last.barrier

    # the metrics counted this job
    after = metrics(cluster)
    assert after["dcrad_barriers_total"] - before["dcrad_barriers_total"] == last.barrier
    assert after["dcrad_rays_total"] - before["dcrad_rays_total"] == last.rays
    assert after["dcrad_bytes_relayed_total"] - before["dcrad_bytes_relayed_total"] == last.bytes_relayed > 0
    assert after['dcrad_jobs{state="done"}'] == before['dcrad_jobs{state="done"}'] + 1
    assert after['dcrad_workers{state="alive"}'] == 2 and after['dcrad_jobs{state="running"}'] == 0

    # the finished page shows the measured curve, labelled
    with chromium() as browser:
        page = browser.new_page(viewport={"width": 1280, "height": 900})
        page.goto(f"{cluster.web_url}/jobs/{job.job_id}")
        wait_js(page, "Number(document.querySelector('#chart').dataset.measuredPoints) >= 1", 30)
        assert "measured against the final solution (converged" in page.inner_text("#legend")
        assert page.text_content("#state") == "done" and page.is_hidden("#cancel")
        ARTIFACTS.mkdir(exist_ok=True)
        page.screenshot(path=str(ARTIFACTS / "job-page.png"), full_page=True)  # docs/job-page.png is a copy
        page.goto(cluster.web_url + "/")
        page.wait_for_selector(f"tr[data-job='{job.job_id}']")
        assert "done" in page.text_content(f"tr[data-job='{job.job_id}']")


# == errors, health, metrics ======================================================
def test_unknown_jobs_are_404_pages_not_tracebacks(cluster):
    base = cluster.web_url
    for path in ("/jobs/nope", "/jobs/nope/preview.png", "/no/such/page", "/jobs/%3Cscript%3Ex%3C%2Fscript%3E"):
        status, ctype, body = http(base + path)
        text = body.decode()
        assert status == 404 and ctype.startswith("text/html"), (path, status)
        assert "Traceback" not in text and "<script>x" not in text, path
    assert "job &#x27;nope&#x27; not found" in http(base + "/jobs/nope")[2].decode()
    for method, path in (("GET", "/api/jobs/nope"), ("GET", "/api/jobs/nope/report"),
                         ("POST", "/api/jobs/nope/cancel"), ("GET", "/jobs/nope/report.json")):
        status, ctype, body = http(base + path, method)
        assert status == 404 and ctype.startswith("application/json"), (path, status)
        assert json.loads(body) == {"error": "job 'nope' not found"}
    status, _, body = http(base + "/api/jobs/nope/cancel", "POST", {"Origin": "http://elsewhere.example"})
    assert status == 403 and "cross-site" in json.loads(body)["error"]


def test_health_metrics_and_static_files(cluster):
    status, _, body = http(cluster.web_url + "/healthz")
    assert status == 200 and body == b"ok\n"
    m = metrics(cluster)
    assert {f'dcrad_jobs{{state="{s}"}}' for s in ("queued", "running", "done", "failed", "cancelled")} <= set(m)
    assert {"dcrad_rays_total", "dcrad_barriers_total", "dcrad_bytes_relayed_total"} <= set(m)
    assert m['dcrad_workers{state="alive"}'] == 2
    for path in ("/", "/static/style.css", "/static/common.js", "/static/chart.js", "/static/job.js",
                 "/static/jobs.js"):
        assert http(cluster.web_url + path)[0] == 200, path
    assert api(cluster, "/api/workers")["workers"][0]["alive"]


# == pieces without a network =====================================================
def test_error_curve_keeps_geometric_times_and_measures():
    curve, rng = ErrorCurve(ratio=1.5), np.random.default_rng(0)
    final = rng.random((50, 3))
    ts = np.arange(1, 1001) * 0.01  # 1000 barriers, 10 s
    for k, t in enumerate(ts, 1):
        curve.record(float(t), k, final + rng.normal(0, 1.0 / k, final.shape))
    kept = [t for t, _, _ in curve.kept]
    assert len(kept) < 30 and kept[0] == pytest.approx(0.01) and kept[-1] == pytest.approx(10.0)
    assert all(b >= a * 1.5 - 1e-12 for a, b in zip(kept[:-2], kept[1:-1]))  # geometric, plus the latest
    curve.measure(final, np.ones(50), "label")
    rms = [r for _, r, _ in curve.measured]
    assert curve.kept == [] and rms == sorted(rms, reverse=True) and rms[-1] < 0.01


def test_preview_is_throttled(tmp_path):
    from dcrad.pipeline import prepare

    scene, patches, _ = prepare(scenes.write_builtin("cornell", tmp_path / "c"))
    prev = LivePreview(scene, patches, tmp_path / "live", size=(64, 48), interval=60.0)
    assert prev.due() and prev.current[0] == 0
    prev.render(np.ones((len(patches), 3)), 1)
    version, barrier, png = prev.current
    assert (version, barrier) == (1, 1) and png[:4] == b"\x89PNG" and not prev.due()


def test_coordinator_web_flags(monkeypatch):
    from dcrad.cli import build_parser

    args = build_parser().parse_args(["coordinator"])
    assert args.web_port == 8080 and args.web_host is None  # None: the gRPC --host
    monkeypatch.setenv("DCRAD_WEB_PORT", "9001")
    monkeypatch.setenv("DCRAD_WEB_HOST", "0.0.0.0")
    args = build_parser().parse_args(["coordinator"])
    assert (args.web_port, args.web_host) == (9001, "0.0.0.0")
    args = build_parser().parse_args(["coordinator", "--web-port", "-1"])
    assert args.web_port == -1  # off


def test_solve_prints_the_status_page_address(tmp_path):
    env = dict(os.environ, PYTHONUNBUFFERED="1")
    r = subprocess.run([sys.executable, "-m", "dcrad.cli", "solve", "cornell", "--workers", "2", "--tol", "0.05",
                        "--width", "64", "--height", "48", "--out", str(tmp_path / "out")],
                       capture_output=True, text=True, timeout=300, env=env, cwd=tmp_path)
    assert r.returncode == 0, r.stderr
    assert re.search(r"dcrad: status page http://127\.0\.0\.1:\d+/jobs/[0-9a-f]{12}", r.stderr), r.stderr


def test_display_never_blocks_the_barrier_and_bounds_preview_cost(tmp_path):
    """Barriers hand their state to the display thread and go on; while it is busy, later
    states queue: every one reaches the error curve, the latest only is previewed.  A preview
    that took c seconds is not due again for c / PREVIEW_SHARE seconds, however short the
    interval."""
    import threading

    from coordinator.display import PREVIEW_SHARE, BarrierDisplay
    from dcrad.pipeline import prepare

    scene, patches, _ = prepare(scenes.write_builtin("cornell", tmp_path / "c"))
    prev = LivePreview(scene, patches, tmp_path / "live", size=(32, 24), interval=0.0)
    gate, busy, seen = threading.Event(), threading.Event(), []

    def assemble_b(values):
        seen.append(float(values[0, 0]))
        busy.set()
        gate.wait()  # the display is busy for as long as the test wants
        return values

    curve = ErrorCurve(ratio=1.0001)
    display = BarrierDisplay(assemble_b, curve, prev, lambda **kw: None)
    display.offer(1.0, 1, np.full((len(patches), 3), 1.0))
    busy.wait()
    for k in range(2, 6):  # four more barriers while the display is stuck on the first
        display.offer(float(k), k, np.full((len(patches), 3), float(k)))
    gate.set()
    deadline = __import__("time").monotonic() + 60
    while len(curve.kept) < 5 and __import__("time").monotonic() < deadline:
        __import__("time").sleep(0.01)  # state 1's preview came before states 2-5 reached the curve
    display.close()
    assert seen == [1.0, 2.0, 3.0, 4.0, 5.0]  # every state, in order: none lost from the curve
    assert [k for _, k, _ in curve.kept] == [int(v) for v in seen]
    assert prev.current[0] >= 1 and prev._cost > 0
    # a display closed while it works on a state: the state reaches the curve, but no preview is
    # rendered, though one is due (the outputs make the final state's)
    fresh = LivePreview(scene, patches, tmp_path / "live2", size=(32, 24), interval=0.0)
    curve2 = ErrorCurve(ratio=1.0001)
    gate.clear()
    busy.clear()
    last = BarrierDisplay(assemble_b, curve2, fresh, lambda **kw: None)
    last.offer(7.0, 7, np.full((len(patches), 3), 7.0))
    busy.wait()
    closing = threading.Thread(target=last.close)
    closing.start()
    while not last._closed:
        __import__("time").sleep(0.001)
    gate.set()
    closing.join(60)
    assert [k for _, k, _ in curve2.kept] == [7]
    assert fresh.due() and fresh.current[0] == 0
    prev._cost = 10.0  # a 10 s render: the next one waits 10 / PREVIEW_SHARE s
    prev._last = __import__("time").monotonic() - 10.0 / PREVIEW_SHARE + 60.0
    assert not prev.due()
    prev._last -= 120.0
    assert prev.due()
