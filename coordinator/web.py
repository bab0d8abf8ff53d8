"""The coordinator's web status endpoint: pages, a JSON API, PNG previews, metrics.

It runs in the coordinator's process, on the same asyncio loop as the gRPC
server (``start_web`` in ``coordinator.server.serve``).  Handlers only read
``JobManager`` state and return plain dicts (as dask's distributed/http does);
the one write is the cancel button's POST.  No build step: the pages are the
plain HTML, CSS and JavaScript files in ``coordinator/static/``.

====  ==========================  ==============================================
GET   /                           jobs page
GET   /jobs/{id}                  job page (chart, ledger, subscenes, preview, cancel)
GET   /jobs/{id}/preview.png      latest preview image (``?v=`` only busts caches)
GET   /jobs/{id}/report.json      the final report (as ``/api/jobs/{id}/report``)
GET   /api/jobs                   {"jobs": [summary, ...]}
GET   /api/jobs/{id}              summary, last progress, ledger, subscenes, curves, preview
GET   /api/jobs/{id}/report       the final report; 409 while the job has none
POST  /api/jobs/{id}/cancel       stop after the current barrier; the summary
GET   /api/workers                {"workers": [...]}
GET   /healthz                    "ok"
GET   /metrics                    Prometheus text format
====  ==========================  ==============================================

Unknown jobs and paths are 404: an HTML page, or ``{"error": ...}`` under
``/api/`` and for ``.json``; never a traceback.
"""

from __future__ import annotations

import html
import json
import logging
import math
from pathlib import Path
from urllib.parse import urlsplit

import numpy as np
from aiohttp import web
from aiohttp.http_exceptions import HttpProcessingError

from dcrad.config import DivideConfig
from dcrad.v1 import dcrad_pb2 as pb

from .jobs import STATES, TERMINAL, Job, JobManager, solver_config

log = logging.getLogger("dcrad.coordinator")

STATIC = Path(__file__).with_name("static")
ACCOUNTS = ("emitted", "absorbed", "escaped", "back_faces", "unshot", "in_flight", "imported", "exported")
MAX_POINTS = 1000  #: curve points per series in the JSON (thinned evenly beyond)
MANAGER = web.AppKey("manager", JobManager)


# == plain dicts ==================================================================
def summary_dict(s: pb.JobSummary) -> dict:
    return {"id": s.job_id, "state": s.state, "scene": s.scene, "subscenes": s.subscenes,
            "elapsed_s": s.elapsed_s, "residual": s.residual, "workers": list(s.workers), "error": s.error}


def ledger_dict(led: pb.Ledger) -> dict:
    """Accounts in W per channel (RGB), their totals, closure and residual."""
    accounts = {k: list(getattr(led, k)) for k in ACCOUNTS}
    return accounts | {"total": {k: sum(v) for k, v in accounts.items()}, "closure": led.closure,
                       "residual": led.residual}


def progress_dict(p: pb.Progress) -> dict:
    error = None
    if p.HasField("error"):
        e = p.error
        error = {"rms": e.rms, "rms_norm": e.rms_norm, "rms_refl": e.rms_refl, "noise_refl": e.noise_refl,
                 "bias_refl": e.bias_refl, "method": e.method}
    return {"barrier": p.barrier, "shots": p.shots, "rays": p.rays, "rms_estimate": p.rms_estimate,
            "error": error, "accuracy": p.accuracy,
            "bytes_relayed": p.bytes_relayed, "ledger": ledger_dict(p.ledger),
            "subscenes": [{"cell": s.cell, "worker": s.worker, "shots": s.shots, "rays": s.rays,
                           "residual": s.residual, "twin_bytes": s.twin_bytes, "reassigned": s.reassigned}
                          for s in p.subscenes]}


def _thin(points: list, n: int = MAX_POINTS) -> list:
    if len(points) <= n:
        return points
    step = math.ceil(len(points) / n)
    return points[:-1:step] + points[-1:]


def job_list_dict(job: Job) -> dict:
    d = summary_dict(job.summary())
    last = job.updates[-1] if job.updates else None
    d["barrier"], d["rays"] = (last.barrier, last.rays) if last is not None else (0, 0)
    d["url"] = f"/jobs/{job.id}"
    return d


def job_dict(job: Job) -> dict:
    """Everything the job page shows."""
    d = job_list_dict(job)
    last = job.updates[-1] if job.updates else None
    d["progress"] = progress_dict(last) if last is not None else None
    s, dv = job.spec, job.spec.divide
    d["settings"] = {"tol": solver_config(s.solver).tol, "time_limit_s": s.solver.time_limit,
                     "max_rays": s.solver.max_rays, "subscenes_asked": dv.subscenes,
                     "mode": dv.mode or DivideConfig().mode, "iterations": dv.iterations}
    curve = JobManager.curve_dict(job)
    for key in ("estimate", "measured"):
        if curve[key] is not None:
            curve[key]["points"] = _thin(curve[key]["points"])
    d["curve"] = curve
    version, barrier, _ = job.preview.current if job.preview is not None else (0, -1, b"")
    d["preview"] = ({"version": version, "barrier": barrier, "url": f"/jobs/{job.id}/preview.png?v={version}"}
                    if version else None)
    d["report_url"] = f"/api/jobs/{job.id}/report" if job.report is not None else None
    return d


def metrics_text(manager: JobManager) -> str:
    """Prometheus text exposition format 0.0.4."""
    m = manager.counters()
    states = {s: 0 for s in STATES}
    for job in list(manager.jobs.values()):
        states[job.state] = states.get(job.state, 0) + 1
    workers = list(manager.pool.workers.values())
    alive = sum(w.alive for w in workers)
    out = []

    def metric(name, kind, text, samples):
        out.extend([f"# HELP {name} {text}", f"# TYPE {name} {kind}"])
        out.extend(f"{name}{labels} {value}" for labels, value in samples)

    metric("dcrad_jobs", "gauge", "Jobs by state.", [(f'{{state="{s}"}}', n) for s, n in states.items()])
    metric("dcrad_rays_total", "counter", "Rays traced by all jobs.", [("", m["rays"])])
    metric("dcrad_barriers_total", "counter", "Sync barriers completed by all jobs.", [("", m["barriers"])])
    metric("dcrad_bytes_relayed_total", "counter", "Twin-buffer bytes relayed between subscenes.",
           [("", m["bytes_relayed"])])
    metric("dcrad_previews_total", "counter", "Preview images rendered.", [("", m["previews"])])
    metric("dcrad_workers", "gauge", "Registered workers by state.",
           [('{state="alive"}', alive), ('{state="lost"}', len(workers) - alive)])
    return "\n".join(out) + "\n"


# == responses ====================================================================
def _finite(o):
    """JSON-ready: numpy to Python, non-finite floats to null (JSON has no NaN)."""
    if isinstance(o, np.ndarray):
        o = o.tolist()
    elif isinstance(o, np.generic):
        o = o.item()
    if isinstance(o, float) and not math.isfinite(o):
        return None
    if isinstance(o, dict):
        return {k: _finite(v) for k, v in o.items()}
    if isinstance(o, (list, tuple)):
        return [_finite(v) for v in o]
    return o


def _json(data, status: int = 200) -> web.Response:
    return web.Response(text=json.dumps(_finite(data)), status=status, content_type="application/json",
                        headers={"Cache-Control": "no-store"})


class _Problem(Exception):
    def __init__(self, status: int, message: str):
        super().__init__(message)
        self.status, self.message = status, message


def _wants_json(request: web.Request) -> bool:
    return request.path.startswith("/api/") or request.path.endswith(".json")


def _error(request: web.Request, status: int, message: str) -> web.Response:
    if _wants_json(request):
        return _json({"error": message}, status)
    title = {404: "Not found", 409: "Not yet", 405: "Method not allowed"}.get(status, "Error")
    page = (f'<!doctype html><html lang="en"><head><meta charset="utf-8"><title>dcrad: {title}</title>'
            f'<link rel="stylesheet" href="/static/style.css"></head><body><header><a href="/">dcrad</a></header>'
            f'<main><h1>{status} {title}</h1><p class="error">{html.escape(message)}</p>'
            f'<p><a href="/">All jobs</a></p></main></body></html>')
    return web.Response(text=page, status=status, content_type="text/html")


@web.middleware
async def _errors(request: web.Request, handler):
    try:
        return await handler(request)
    except _Problem as exc:
        return _error(request, exc.status, exc.message)
    except web.HTTPException as exc:
        if exc.status < 400:
            raise
        return _error(request, exc.status, f"{exc.reason}: {request.method} {request.path}")
    except Exception:
        log.exception("web handler failed for %s %s", request.method, request.path)
        return _error(request, 500, "internal error; the coordinator's log has the details")


def _job(request: web.Request) -> Job:
    job_id = request.match_info["job_id"]
    job = request.app[MANAGER].get(job_id)
    if job is None:
        shown = job_id if len(job_id) <= 64 else f"{job_id[:32]}...({len(job_id)} characters)"
        raise _Problem(404, f"job '{shown}' not found")
    return job


# == handlers =====================================================================
def _page(name: str) -> web.FileResponse:
    path = STATIC / name
    if not path.is_file():
        raise _Problem(500, f"this install lacks the status pages' files ({path})")
    return web.FileResponse(path, headers={"Cache-Control": "no-cache"})


async def jobs_page(request):
    return _page("jobs.html")


async def job_page(request):
    _job(request)
    return _page("job.html")


async def api_jobs(request):
    jobs = sorted(request.app[MANAGER].jobs.values(), key=lambda j: j.created, reverse=True)
    return _json({"jobs": [job_list_dict(j) for j in jobs]})


async def api_job(request):
    return _json(job_dict(_job(request)))


async def api_report(request):
    job = _job(request)
    if job.report is None and job.state == "failed":
        raise _Problem(404, f"job '{job.id}' failed and has no report: {job.error}")
    if job.report is None:
        raise _Problem(409, f"job '{job.id}' is {job.state}; the report is written when it ends")
    return _json(job.report)


async def api_cancel(request):
    origin = request.headers.get("Origin")
    if origin and urlsplit(origin).netloc != request.host:
        raise _Problem(403, "cross-site cancel refused")
    job = _job(request)
    if job.state not in TERMINAL:
        job.request_cancel()
        log.info("job %s: cancel asked from the web page", job.id)
    return _json(summary_dict(job.summary()))


async def preview_png(request):
    job = _job(request)
    version, _, png = job.preview.current if job.preview is not None else (0, -1, b"")
    if not version:
        raise _Problem(404, f"job '{job.id}' has no preview yet (the first comes after the first barrier)")
    return web.Response(body=png, content_type="image/png",
                        headers={"Cache-Control": "no-store", "X-Preview-Version": str(version)})


async def api_workers(request):
    pool = request.app[MANAGER].pool
    return _json({"workers": [{"address": w.address, "name": w.name, "capacity": w.capacity,
                               "alive": w.alive, "load": w.load} for w in list(pool.workers.values())]})


async def healthz(request):
    return web.Response(text="ok\n")


async def metrics(request):
    return web.Response(body=metrics_text(request.app[MANAGER]).encode(),
                        headers={"Content-Type": "text/plain; version=0.0.4; charset=utf-8"})


def make_app(manager: JobManager) -> web.Application:
    app = web.Application(middlewares=[_errors])
    app[MANAGER] = manager
    r = app.router
    r.add_get("/", jobs_page)
    r.add_get("/jobs/{job_id}", job_page)
    r.add_get("/jobs/{job_id}/preview.png", preview_png)
    r.add_get("/jobs/{job_id}/report.json", api_report)
    r.add_get("/api/jobs", api_jobs)
    r.add_get("/api/jobs/{job_id}", api_job)
    r.add_get("/api/jobs/{job_id}/report", api_report)
    r.add_post("/api/jobs/{job_id}/cancel", api_cancel)
    r.add_get("/api/workers", api_workers)
    r.add_get("/healthz", healthz)
    r.add_get("/metrics", metrics)
    r.add_static("/static", STATIC)
    return app


def url(host: str, port: int) -> str:
    return f"http://[{host}]:{port}" if ":" in host else f"http://{host}:{port}"


MAX_LINE = 32 * 1024  #: bytes of a request line or header the web endpoint reads


def _one_line_bad_requests(record: logging.LogRecord) -> bool:
    """aiohttp logs a malformed request (a line too long, bad syntax) with a traceback: one line."""
    exc = record.exc_info[1] if record.exc_info else None
    if isinstance(exc, HttpProcessingError):
        first = (exc.message.splitlines() or [""])[0][:120]
        record.msg, record.args = "web: refused a bad HTTP request (%d): %s", (exc.code, first)
        record.exc_info, record.exc_text, record.levelno, record.levelname = None, None, logging.INFO, "INFO"
    return True


async def start_web(manager: JobManager, host: str = "127.0.0.1", port: int = 0) -> tuple[web.AppRunner, str]:
    """Serve the status pages on ``host:port`` (0: any free port); (runner, base URL).

    Call ``await runner.cleanup()`` to stop.
    """
    # ids up to 32 KB reach the routes (and get a 404); a longer request line gets aiohttp's 400,
    # logged as one line instead of a traceback
    runner = web.AppRunner(make_app(manager), access_log=None, shutdown_timeout=2.0, max_line_size=MAX_LINE,
                           max_field_size=MAX_LINE)
    logging.getLogger("aiohttp.server").addFilter(_one_line_bad_requests)
    await runner.setup()
    await web.TCPSite(runner, host, port).start()
    bound = runner.addresses[0][1]
    return runner, url(host, bound)
