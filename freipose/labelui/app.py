"""The ASGI application of ``freipose label``: the page, its static files and the JSON API.

Every request must carry the access token, as the query parameter ``token``, the header
``X-FreiPose-Token`` or the cookie that the page sets on the first visit; requests without
it get 403. The client names an instant by its index and a camera by its name, never a
path; request bodies larger than :data:`~freipose.labelui.schema.MAX_BODY_BYTES` get 413,
bodies that break the schema 422, a save of a stale version 409 (with the current state),
a save that cannot be written (full disk, read-only folder) 507 with a message that says
what to do (nothing changes: the page keeps the edits, the file keeps what was saved).

Routes:

* ``GET /``: the page; ``GET /static/<name>``: its script and style sheet;
* ``GET /api/config``: skeleton, cameras (calibration), sessions, instants, thresholds;
* ``GET /api/instant/<i>``: labels, predictions, 3D points, projections, residuals, bones;
* ``POST /api/instant/<i>``: save the instant's labels (body: see :mod:`.schema`);
* ``GET /api/frame/<i>/<camera>``: the camera's image at instant i (JPEG);
* ``GET /api/progress``: labeled instants, per keypoint.
"""

from __future__ import annotations

import colorsys
import json
import secrets
from importlib import resources
from typing import Any
from urllib.parse import parse_qs

from starlette.applications import Starlette
from starlette.concurrency import run_in_threadpool
from starlette.requests import Request
from starlette.responses import JSONResponse, PlainTextResponse, Response
from starlette.routing import Route
from starlette.types import ASGIApp, Receive, Scope, Send

from freipose.errors import OutputWriteError, filesystem_message
from freipose.io.video import MediaError
from freipose.labelui.frames import FrameCache
from freipose.labelui.schema import MAX_BODY_BYTES, BodyError, parse_body
from freipose.labelui.store import LabelStore, StaleVersionError

COOKIE = "freipose_label_token"
HEADER = "x-freipose-token"
STATIC_FILES = {"label.js": "text/javascript", "geom.js": "text/javascript",
                "label.css": "text/css", "index.html": "text/html"}  # fmt: skip


def keypoint_colors(n: int) -> list[str]:
    """``n`` distinct CSS colours (evenly spaced hues), one per keypoint."""
    out = []
    for k in range(n):
        r, g, b = colorsys.hls_to_rgb(k / max(n, 1), 0.55, 0.9)
        out.append(f"#{int(r * 255):02x}{int(g * 255):02x}{int(b * 255):02x}")
    return out


def _static() -> dict[str, bytes]:
    root = resources.files("freipose.labelui") / "static"
    return {name: (root / name).read_bytes() for name in STATIC_FILES}


class TokenGate:
    """ASGI middleware: refuse (403) every HTTP request that lacks the access token."""

    def __init__(self, app: ASGIApp, token: str):
        self.app = app
        self.token = token

    def _given(self, scope: Scope) -> list[str]:
        found = []
        headers = {k.decode("latin-1").lower(): v.decode("latin-1") for k, v in scope["headers"]}
        if HEADER in headers:
            found.append(headers[HEADER])
        for part in headers.get("cookie", "").split(";"):
            name, _, value = part.strip().partition("=")
            if name == COOKIE:
                found.append(value)
        found += parse_qs(scope.get("query_string", b"").decode("latin-1")).get("token", [])
        return found

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        """Pass a request with the token on to the application; answer 403 otherwise."""
        if scope["type"] == "http":
            ok = any(secrets.compare_digest(t.encode(), self.token.encode())
                     for t in self._given(scope))  # fmt: skip
            if not ok:
                resp = PlainTextResponse(
                    "403 Forbidden: this labeling server needs its access token; open the URL "
                    "that `freipose label` printed (it ends in ?token=...)",
                    status_code=403,
                )
                await resp(scope, receive, send)
                return
        await self.app(scope, receive, send)


async def _read_body(request: Request) -> bytes:
    """The request body, refusing (413) more than MAX_BODY_BYTES, announced or streamed."""
    length = request.headers.get("content-length")
    if length is not None and (not length.isdigit() or int(length) > MAX_BODY_BYTES):
        raise _TooLarge()
    chunks, size = [], 0
    async for chunk in request.stream():
        size += len(chunk)
        if size > MAX_BODY_BYTES:
            raise _TooLarge()
        chunks.append(chunk)
    return b"".join(chunks)


class _TooLarge(Exception):
    pass


def _index(request: Request, store: LabelStore) -> int | None:
    try:
        i = int(request.path_params["index"])
    except (KeyError, ValueError):
        return None
    return i if 0 <= i < len(store) else None


def _config(store: LabelStore) -> dict[str, Any]:
    skel = store.skeleton
    cams: dict[str, Any] = {}
    for s in store.sessions.values():
        for cam in s.rig:
            cams[f"{s.name}/{cam.name}"] = {
                "name": cam.name, "size": list(cam.size), "K": cam.K.tolist(),
                "dist": cam.dist.tolist(), "R": cam.R.tolist(), "t": cam.t.tolist(),
            }  # fmt: skip
    return {
        "keypoints": list(skel.keypoints),
        "colors": keypoint_colors(skel.num_keypoints),
        "limbs": [[list(a), list(b)] for a, b in skel.limbs],
        "cameras": cams,
        "sessions": [{"name": s.name, "cameras": list(s.cameras)} for s in store.sessions.values()],
        "instants": [
            {
                "session": x.session,
                "frame": x.frame,
                "individual": x.individual,
                "confidence": None if x.confidence != x.confidence else round(x.confidence, 4),
            }
            for x in store.instants
        ],  # fmt: skip
        "animals": list(dict.fromkeys(x.individual for x in store.instants if x.individual)),
        "max_residual": store.settings.max_residual,
        "bone_tolerance": store.settings.bone_tolerance,
        "output": store.output.name,
    }


def least_confident_key(confidence: float, index: int) -> tuple[float, int]:
    """Sort key of "least confident first": unknown confidence after every known one."""
    return (confidence if confidence == confidence else 2.0, index)


def _next_instants(store: LabelStore, i: int) -> list[int]:
    """Instants the page may show after ``i``: the next two, the previous, least confident."""
    done = store.done()
    todo = [j for j in range(len(store)) if not done[j] and j != i]
    out = [i, i + 1, i + 2, i - 1]
    if todo:
        out.append(min(todo, key=lambda j: least_confident_key(store.instants[j].confidence, j)))
    return out


def create_app(store: LabelStore, frames: FrameCache, token: str) -> ASGIApp:
    """The labeling application for ``store``, guarded by ``token``."""
    static = _static()
    config_json = json.dumps(_config(store)).encode()

    def page(request: Request) -> Response:
        resp = Response(static["index.html"], media_type="text/html")
        resp.set_cookie(COOKIE, token, httponly=True, samesite="strict")
        resp.headers["Cache-Control"] = "no-store"
        return resp

    def static_file(request: Request) -> Response:
        name = request.path_params["name"]
        if name not in static or name == "index.html":
            return PlainTextResponse("404 Not Found", status_code=404)
        return Response(static[name], media_type=STATIC_FILES[name])

    def config(request: Request) -> Response:
        return Response(config_json, media_type="application/json")

    def progress(request: Request) -> Response:
        return JSONResponse(store.progress())

    def frame(request: Request) -> Response:
        i = _index(request, store)
        cam = request.path_params["camera"]
        if i is None or cam not in store.session(i).cameras:
            return PlainTextResponse("404 Not Found: no such instant or camera", status_code=404)
        try:
            data = frames.jpeg(i, cam)
        except MediaError as exc:
            return PlainTextResponse(f"500: {exc}", status_code=500)
        return Response(data, media_type="image/jpeg", headers={"Cache-Control": "max-age=3600"})

    async def instant(request: Request) -> Response:
        i = _index(request, store)
        if i is None:
            return JSONResponse({"error": f"no instant; indices are 0..{len(store) - 1}"}, 404)
        if request.method == "GET":
            frames.prefetch(_next_instants(store, i))
            return JSONResponse(await run_in_threadpool(store.state, i))
        try:
            raw = await _read_body(request)
        except _TooLarge:
            return JSONResponse({"error": f"body larger than {MAX_BODY_BYTES} bytes"}, 413)
        try:
            version, points, status = parse_body(
                raw, store.session(i).rig, store.skeleton.keypoints
            )
        except BodyError as exc:
            return JSONResponse({"error": str(exc)}, 422)
        try:
            state = await run_in_threadpool(store.save, i, version, points, status)
        except StaleVersionError as exc:
            return JSONResponse({"error": "stale version", "current": exc.current}, 409)
        except OutputWriteError as exc:  # a full disk or a read-only folder: nothing changed
            why = filesystem_message(OSError(exc.errno, "", exc.path), then="save again")
            msg = f"{why or exc}; your edits are kept in this page until a save succeeds"
            return JSONResponse({"error": msg, "write_error": True}, 507)
        return JSONResponse(state)

    routes = [
        Route("/", page),
        Route("/static/{name}", static_file),
        Route("/api/config", config),
        Route("/api/progress", progress),
        Route("/api/instant/{index}", instant, methods=["GET", "POST"]),
        Route("/api/frame/{index}/{camera}", frame),
    ]
    return TokenGate(Starlette(routes=routes), token)
