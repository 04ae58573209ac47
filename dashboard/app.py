"""The dashboard's web side: a Starlette (ASGI) app over one :class:`~dashboard.view.FleetView`.

Routes: ``/`` (the fleet by host), ``/drive/<host>/<axis>`` (one drive: live plots, events),
``/recording/<host>`` (the flight-recording viewer), ``/api/fleet``, ``/api/drive/<host>/<axis>``, ``/api/recording/<host>``
(``?what=last&last_s=S``, JSON columns), ``/api/stream`` (server-sent events: what changed since
the page's version, at most every :data:`STREAM_PERIOD_S`), ``/metrics`` (Prometheus), and
``POST /api/command/<op>`` only when commands are enabled (otherwise 403). Page scripts and
styles are ours (``dashboard/static``); nothing is fetched from the internet.
"""

from __future__ import annotations

import asyncio
import json
from pathlib import Path
from typing import Any, AsyncIterator, Callable, Mapping
from urllib.parse import urlsplit

from starlette.applications import Starlette
from starlette.requests import Request
from starlette.responses import FileResponse, JSONResponse, Response, StreamingResponse
from starlette.routing import Mount, Route
from starlette.staticfiles import StaticFiles

from bus_agent.cia402.states import decode_statusword
from schemas.keys import is_name
from schemas.messages import DRIVE_OPS, RECORDING_CHANNELS, RECORDING_MAX_S, RECORDING_WHAT, Recording

from .metrics import CONTENT_TYPE, registry_for, render
from .view import FleetView, display_of

STATIC = Path(__file__).with_name("static")
#: How often a live page is sent what changed (a change reaches the browser within this plus transit).
STREAM_PERIOD_S = 0.1
#: A comment line this often keeps proxies from closing an idle stream.
KEEPALIVE_S = 15.0
#: Ops the page may send when commands are enabled (never lease/release: the page holds none).
PAGE_OPS = tuple(op for op in DRIVE_OPS if op not in ("lease", "release"))

RecordingFetch = Callable[[str, str, float], Recording]
CommandRun = Callable[[str, str, dict], dict]


def state_runs(statuswords: list[int]) -> list[list[Any]]:
    """The CiA 402 states of a statusword column as runs ``[first index, state name, colour
    class]`` (the class as on the fleet page, :data:`~dashboard.view.DISPLAY_OF_STATE`). Pure."""
    runs: list[list[Any]] = []
    for i, sw in enumerate(statuswords):
        name = decode_statusword(sw).value
        if not runs or runs[-1][1] != name:
            runs.append([i, name, display_of(name, False, True)])
    return runs


def recording_json(rec: Recording, axis: str | None = None) -> dict[str, Any]:
    """A recording as JSON columns for the page's plot; ``axis`` keeps one axis. Pure.

    ``t``: seconds since the first cycle (the agent's monotonic cycle clock); ``t0_ms``: the
    agent's wall clock at the first cycle (ms since the epoch), so ``t0_ms + 1000 t`` is the
    agent's time of each cycle. Per drive, its channels and ``states`` (runs of CiA 402 states
    decoded from the statusword); ``cycle_channels``: period and working counter per cycle."""
    n = len(rec.axes)
    t0 = rec.channels["time_ns"][0] if rec.channels.get("time_ns") else 0
    out: dict[str, Any] = {"host": rec.host, "reason": rec.reason, "axis": rec.axis, "detail": rec.detail,
                           "trigger_cycle": rec.trigger_cycle, "first_cycle": rec.first_cycle,
                           "n_cycles": rec.n_cycles, "cycle_us": rec.cycle_us, "axes": rec.axes,
                           "t0_ms": rec.time_origin_ns / 1e6,
                           "t": [(t - t0) / 1e9 for t in rec.channels.get("time_ns", [])]}
    cols = {}
    for j, a in enumerate(rec.axes):
        if axis is not None and a != axis:
            continue
        cols[a] = {k: v[j::n] for k, v in rec.channels.items() if len(v) == rec.n_cycles * n and n}
        if "statusword" in cols[a]:
            cols[a]["states"] = state_runs(cols[a]["statusword"])
    out["drives"] = cols
    out["cycle_channels"] = {k: v for k, v in rec.channels.items()
                             if RECORDING_CHANNELS.get(k, ("",))[0] == "cycle" and k != "time_ns"}
    return out


def cross_site_refusal(headers: Mapping[str, str]) -> str:
    """Why a command request may come from another site's page, '' when it cannot. Pure.

    A browser sends another site's form or ``text/plain`` POST without asking (no CORS
    preflight), and with the operator's reach to this port: a command must be JSON (which makes a
    cross-site browser ask first, and this server never allows it) and, where the browser names
    its origin, come from this page's own."""
    if headers.get("content-type", "").split(";")[0].strip().lower() != "application/json":
        return "a command must be sent as application/json"
    origin = headers.get("origin")
    if origin is not None and urlsplit(origin).netloc != headers.get("host", ""):
        return f"origin {origin} is not this dashboard's: refused"
    return ""


def build_app(view: FleetView, *, fetch_recording: RecordingFetch | None = None,
              run_command: CommandRun | None = None, identity: str = "",
              stopping: Callable[[], bool] = lambda: False) -> Starlette:
    """The ASGI app. ``run_command`` None: read-only (commands answer 403); ``identity``: the
    principal commands go out under (shown on the page). ``stopping``: true
    once the server is asked to stop; every open ``/api/stream`` then ends within
    :data:`STREAM_PERIOD_S`, so an open page never holds a shutdown (the server waits for open
    responses to complete)."""
    registry = registry_for(view)

    async def index(_: Request) -> Response:
        return FileResponse(STATIC / "index.html")

    async def drive_page(request: Request) -> Response:
        if view.drive(request.path_params["host"], request.path_params["axis"]) is None:
            return JSONResponse({"error": "unknown drive"}, status_code=404)
        return FileResponse(STATIC / "drive.html")

    async def recording_page(request: Request) -> Response:
        if not is_name(request.path_params["host"]):
            return JSONResponse({"error": "bad host name"}, status_code=400)
        return FileResponse(STATIC / "recording.html")

    async def api_fleet(_: Request) -> Response:
        body = view.snapshot()
        body["commands_enabled"] = run_command is not None
        body["identity"] = identity
        return JSONResponse(body)

    async def api_drive(request: Request) -> Response:
        d = view.drive(request.path_params["host"], request.path_params["axis"])
        if d is None:
            return JSONResponse({"error": f"no drive {request.path_params['host']}/{request.path_params['axis']}"},
                                status_code=404)
        return JSONResponse(d)

    async def api_recording(request: Request) -> Response:
        host = request.path_params["host"]
        if fetch_recording is None:
            return JSONResponse({"error": "recordings are not available"}, status_code=503)
        what = request.query_params.get("what", "last")
        axis = request.query_params.get("axis")
        try:
            last_s = float(request.query_params.get("last_s", "10"))
        except ValueError:
            return JSONResponse({"error": "last_s: not a number"}, status_code=400)
        if not is_name(host) or not 0 < last_s <= RECORDING_MAX_S:
            return JSONResponse({"error": f"bad host or last_s (0 < last_s <= {RECORDING_MAX_S:g})"}, status_code=400)
        if what not in RECORDING_WHAT:
            return JSONResponse({"error": f"what {what!r} is not one of {', '.join(RECORDING_WHAT)}"}, status_code=400)
        try:
            rec = await asyncio.to_thread(fetch_recording, host, what, last_s)
        except Exception as exc:  # refused, unavailable, no answer: the page shows why
            return JSONResponse({"error": str(exc)}, status_code=502)
        return JSONResponse(recording_json(rec, axis))

    async def stream(request: Request) -> Response:
        async def events() -> AsyncIterator[str]:
            version = 0
            idle = 0.0
            first = True  # the page's first message comes at once, also from an empty fleet
            while not stopping() and not await request.is_disconnected():
                changes = view.changes_since(version)
                if first or changes["version"] != version:
                    first = False
                    version = changes["version"]
                    idle = 0.0
                    yield f"data: {json.dumps(changes, separators=(',', ':'))}\n\n"
                elif idle >= KEEPALIVE_S:
                    idle = 0.0
                    yield ": keepalive\n\n"
                await asyncio.sleep(STREAM_PERIOD_S)
                idle += STREAM_PERIOD_S
        return StreamingResponse(events(), media_type="text/event-stream",
                                 headers={"Cache-Control": "no-cache", "X-Accel-Buffering": "no"})

    async def metrics(_: Request) -> Response:
        body = await asyncio.to_thread(render, registry)
        return Response(body, media_type=CONTENT_TYPE)

    async def command(request: Request) -> Response:
        if run_command is None:
            return JSONResponse({"error": "read-only dashboard: start it with --commands to send commands"},
                                status_code=403)
        refusal = cross_site_refusal(request.headers)
        if refusal:
            return JSONResponse({"error": refusal}, status_code=403 if "origin" in refusal else 415)
        op = request.path_params["op"]
        if op not in PAGE_OPS:
            return JSONResponse({"error": f"op {op!r} is not one of {', '.join(PAGE_OPS)}"}, status_code=400)
        try:
            body = await request.json()
            selector = body["selector"]
            args = body.get("args", {})
            if not isinstance(selector, str) or not isinstance(args, dict):
                raise ValueError("selector must be a string, args a map")
        except (ValueError, KeyError, TypeError) as exc:
            return JSONResponse({"error": f"bad request body: {exc}"}, status_code=400)
        try:
            result = await asyncio.to_thread(run_command, op, selector, args)
        except ValueError as exc:
            return JSONResponse({"error": str(exc)}, status_code=400)
        return JSONResponse(result)

    routes = [
        Route("/", index),
        Route("/drive/{host}/{axis}", drive_page),
        Route("/recording/{host}", recording_page),
        Route("/api/fleet", api_fleet),
        Route("/api/drive/{host}/{axis}", api_drive),
        Route("/api/recording/{host}", api_recording),
        Route("/api/stream", stream),
        Route("/api/command/{op}", command, methods=["POST"]),
        Route("/metrics", metrics),
        Mount("/static", app=StaticFiles(directory=STATIC), name="static"),
    ]
    return Starlette(routes=routes)
