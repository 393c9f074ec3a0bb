"""The league's web app (Starlette): leaderboard, entrant and match pages, uploads and the JSON API.

Pages: `/` the leaderboard (it polls `/api/leaderboard` and redraws itself when results arrive),
`/entrants/{name}`, `/matches/{id}` (results, lap chart, race video, rerun's web viewer), `/submit` (the upload
form). API: `GET /api/leaderboard`, `/api/entrants`, `/api/entrants/{name}`, `/api/matches`,
`/api/matches/{id}`; `POST /api/submissions` with `Authorization: Bearer TOKEN` and the agent file as the
body or as the multipart field `file`. There are no admin routes: entrants are made with the CLI.
"""
from __future__ import annotations

import threading
from pathlib import Path
from urllib.parse import quote

from markupsafe import Markup, escape
from starlette.applications import Starlette
from starlette.concurrency import run_in_threadpool
from starlette.datastructures import UploadFile
from starlette.middleware import Middleware
from starlette.requests import Request
from starlette.responses import FileResponse, JSONResponse, Response
from starlette.routing import Mount, Route
from starlette.staticfiles import StaticFiles
from starlette.templating import Jinja2Templates

from ..config import LeagueError
from ..entrants import entrant_for_token, remove_stale_uploads, upload_version
from ..store import connect
from ..submissions import MAX_SUBMISSION_BYTES
from .charts import lap_chart_svg, rating_chart_svg
from .media import match_video
from .queries import League, deepracer_rankings
from .security import (CSRF_COOKIE, CSRF_FIELD, BodyLimit, RateLimiter, SecurityHeaders, bearer_token, csrf_ok,
                       new_csrf_token)
from .viewer import viewer_assets

HERE = Path(__file__).resolve().parent
MULTIPART_OVERHEAD = 64 * 1024  # room for the form's other fields and part headers
VALIDATIONS_AT_ONCE = 2


class Uploads:
    """The upload policy of one app: who may upload how often, what is too large, how many validate at once."""

    def __init__(self, league: League, limit: int, per_hour: int):
        self.league, self.limit = league, limit
        self.per_entrant = RateLimiter(per_hour, 3600.0)
        self.bad_tokens = RateLimiter(30, 600.0)  # failed tokens per client address
        self.validating = threading.BoundedSemaphore(VALIDATIONS_AT_ONCE)

    def entrant(self, request: Request, token) -> str:
        """The entrant a token belongs to; LeagueError (401 or 429) for a missing, wrong or abused token."""
        client = request.client.host if request.client else "?"
        if not token:
            raise _Refused(401, "refused: no token (send your entrant token; the organiser gave it to you)")
        conn = connect(self.league.folder)
        try:
            name = entrant_for_token(conn, token)
        finally:
            conn.close()
        if name is None:
            if not self.bad_tokens.allow(client):
                raise _Refused(429, "refused: too many wrong tokens from this address; try again later")
            raise _Refused(401, "refused: this token belongs to no entrant of this league")
        return name

    async def accept(self, name: str, data: bytes) -> dict:
        """Validate and store an upload as the entrant's new version (refusals as _Refused)."""
        if not data:
            raise _Refused(400, "refused: the upload is empty (attach your agent .pt file)")
        if len(data) > self.limit:
            raise _Refused(413, f"refused: the file is over {self.limit // 2**20} MB (the upload limit)")
        if not self.per_entrant.allow(name):
            raise _Refused(429, "refused: too many uploads from this entrant in the last hour; try again later")
        try:
            return await run_in_threadpool(self._validate_and_store, name, data)
        except LeagueError as exc:
            raise _Refused(422, str(exc)) from None

    def _validate_and_store(self, name: str, data: bytes) -> dict:
        with self.validating:  # the others wait their turn: each validation is a subprocess
            return upload_version(self.league.folder, name, data)


class _Refused(Exception):
    def __init__(self, status: int, message: str):
        super().__init__(message)
        self.status, self.message = status, message


async def _read_file_field(form) -> bytes:
    upload = form.get("file")
    if not isinstance(upload, UploadFile):
        raise _Refused(400, "refused: no file attached (the form field is 'file')")
    return await upload.read()


def create_app(folder, upload_limit: int = MAX_SUBMISSION_BYTES, uploads_per_hour: int = 20,
               viewer_cache: Path | None = None) -> Starlette:
    """The web app of the league in `folder` (the store is checked first: a damaged league is refused)."""
    league = League(folder)
    connect(league.folder).close()
    remove_stale_uploads(league.folder)
    templates = Jinja2Templates(directory=str(HERE / "templates"))
    templates.env.globals.update(league_name=league.name, fmt=_fmt)
    templates.env.filters["wbr"] = lambda text: Markup(escape(text).replace("_", Markup("_<wbr>")))

    def page(request, name, context, status=200):
        return templates.TemplateResponse(request, name, context, status_code=status)

    routes = _api_routes(league) + _page_routes(league, page) + _upload_routes(
        Uploads(league, upload_limit, uploads_per_hour), page) + [
        Mount("/static", StaticFiles(directory=str(HERE / "static")), name="static"),
        Mount("/viewer", StaticFiles(directory=str(viewer_assets(viewer_cache)), html=True), name="viewer"),
    ]
    middleware = [Middleware(SecurityHeaders), Middleware(BodyLimit, limit=upload_limit + MULTIPART_OVERHEAD)]
    return Starlette(routes=routes, middleware=middleware)


def _page_routes(league: League, page) -> list:
    """The leaderboard, entrant and match pages, and a match's video and replay."""
    def leaderboard_page(request):
        return page(request, "leaderboard.html", {"table": league.leaderboard()})

    def entrant_page(request):
        entrant = league.entrant(request.path_params["name"])
        if entrant is None:
            return page(request, "missing.html", {"what": "entrant"}, 404)
        return page(request, "entrant.html", {"e": entrant, "chart": rating_chart_svg(entrant["rating_history"])})

    def match_page(request):
        match = league.match(request.path_params["match_id"])
        if match is None:
            return page(request, "missing.html", {"what": "match"}, 404)
        return page(request, "match.html", {"m": match, "chart": lap_chart_svg(match["cars"])})

    def video(request):
        match_id = request.path_params["match_id"]
        replay = league.replay_path(match_id)
        if replay is None:
            return Response("no replay for this match", status_code=404)
        return FileResponse(match_video(league.folder, match_id, replay), media_type="video/mp4")

    def replay(request):
        path = league.replay_path(request.path_params["match_id"])
        if path is None:
            return Response("no replay for this match", status_code=404)
        return FileResponse(path, media_type="application/octet-stream")

    return [Route("/", leaderboard_page), Route("/entrants/{name}", entrant_page),
            Route("/matches/{match_id}", match_page), Route("/matches/{match_id}/video.mp4", video),
            Route("/matches/{match_id}/replay.rrd", replay)]


def _upload_routes(uploads: Uploads, page) -> list:
    """The upload form (with its CSRF token) and the upload API."""
    async def submit_form(request):
        token = new_csrf_token()
        response = page(request, "submit.html", {"csrf": token, "field": CSRF_FIELD})
        response.set_cookie(CSRF_COOKIE, token, httponly=True, samesite="strict", path="/submit")
        return response

    async def submit_post(request):
        form = await request.form(max_files=1, max_fields=4)
        fresh = new_csrf_token()
        try:
            if not csrf_ok(request, form):
                raise _Refused(403, "refused: the form has expired or came from another site; reload the page "
                                    "and send it again")
            name = uploads.entrant(request, str(form.get("token", "")).strip())
            result = await uploads.accept(name, await _read_file_field(form))
            context, status = {"accepted": result}, 201
        except _Refused as exc:
            context, status = {"error": exc.message}, exc.status
        response = page(request, "submit.html", {**context, "csrf": fresh, "field": CSRF_FIELD}, status)
        response.set_cookie(CSRF_COOKIE, fresh, httponly=True, samesite="strict", path="/submit")
        return response

    async def api_submit(request):
        try:
            name = uploads.entrant(request, bearer_token(request))
            if request.headers.get("content-type", "").startswith("multipart/form-data"):
                data = await _read_file_field(await request.form(max_files=1, max_fields=4))
            else:
                data = await request.body()
            result = await uploads.accept(name, data)
        except _Refused as exc:
            return JSONResponse({"error": exc.message}, status_code=exc.status)
        return JSONResponse({"name": result["name"], "version": result["version"], "sha256": result["sha256"],
                             "agent": result["metadata"].get("name"), "url": f"/entrants/{quote(result['name'])}"},
                            status_code=201)

    return [Route("/submit", submit_form, methods=["GET"]), Route("/submit", submit_post, methods=["POST"]),
            Route("/api/submissions", api_submit, methods=["POST"])]


def _api_routes(league: League) -> list:
    """The read-only JSON API."""
    def leaderboard(request):
        return JSONResponse(deepracer_rankings(league.leaderboard(), league.versions_by_entrant()))

    def entrants(request):
        table = league.leaderboard()
        rank = {s["entrant"]: s["rank"] for s in table["standings"]}
        out = [{"name": name, "rank": rank.get(name), "versions": len(vs),
                "racing_sha256": next((v["sha256"] for v in vs if v["racing"]), None)}
               for name, vs in league.versions_by_entrant().items()]
        return JSONResponse({"entrants": out})

    def entrant(request):
        found = league.entrant(request.path_params["name"])
        return JSONResponse(found) if found else JSONResponse({"error": "no such entrant"}, status_code=404)

    def matches(request):
        return JSONResponse({"matches": league.matches(entrant=request.query_params.get("entrant"), limit=500)})

    def match(request):
        found = league.match(request.path_params["match_id"])
        return JSONResponse(found) if found else JSONResponse({"error": "no such match"}, status_code=404)

    return [Route("/api/leaderboard", leaderboard), Route("/api/entrants", entrants),
            Route("/api/entrants/{name}", entrant), Route("/api/matches", matches),
            Route("/api/matches/{match_id}", match)]


def _fmt(value, digits: int = 3) -> str:
    """A number for a table cell ('–' for none)."""
    if value is None:
        return "–"
    if isinstance(value, float):
        return f"{value:.{digits}f}"
    return str(value)
