"""The operator dashboard: plain HTML pages with vanilla JavaScript, served by the API under ``/ui``.

Everything the pages need ships in ``static/`` (no CDN, no web fonts: the lab PC may be offline).
The pages are thin: each one calls the JSON API with the token the operator entered (kept in
``sessionStorage``, or ``localStorage`` when "remember" is ticked) as ``Authorization: Bearer``, and
draws its plots with the small canvas plotter in ``static/plot.js``.  Pages:

* ``/ui/``                   benches with their live state, runs with status and progress
* ``/ui/start``              start a run from a procedure's parameter form (schema + defaults from ``GET /procedures``)
* ``/ui/runs/{id}``          one run: state, pause / resume / stop / abort, live plots (``/runs/{id}/data``,
                             SSE ``/runs/{id}/events``), events
* ``/ui/gyros``, ``/ui/gyros/{gyro_id}``   coefficients (``/gyros/{id}/coefficients``) and fit versions
* ``/ui/fits``                every fit version, filtered by gyro, model and date (``GET /fits``)
* ``/ui/fits/{id}``          one fit version and its HTML report (``/fits/{id}/report``)
* ``/ui/close-loop``, ``/ui/close-loop/{id}``   past analyses filtered by gyro, model and date (``GET
                             /close-loop``), start one, read its report

Include with ``app.include_router(api.dashboard.router)``.  The routes are left out of the OpenAPI
document; the pages themselves need no token (they hold no data), the API calls they make do.
"""
from __future__ import annotations

from pathlib import Path

from fastapi import APIRouter
from fastapi.responses import FileResponse, HTMLResponse, RedirectResponse

from api.problems import Problem

STATIC_DIR = Path(__file__).with_name("static")
_MEDIA_TYPES = {".js": "text/javascript; charset=utf-8", ".css": "text/css; charset=utf-8",
                ".svg": "image/svg+xml", ".ico": "image/x-icon"}
# Pages: name -> (title, page script).  The shell loads common.js, plot.js and the page script.
PAGES = {
    "overview": ("Benches and runs", "overview.js"),
    "start": ("Start a run", "start.js"),
    "run": ("Run", "run.js"),
    "gyro": ("Gyro coefficients", "gyro.js"),
    "fits": ("Fits", "fits.js"),
    "fit": ("Fit", "fit.js"),
    "closeloop": ("Close the loop", "closeloop.js"),
}
# Scripts and styles only from this server; fetches only to this server.  Inline styles stay allowed
# for the fit report shown in a sandboxed iframe (it carries its own <style>); its scripts do not run.
CSP = ("default-src 'self'; script-src 'self'; style-src 'self' 'unsafe-inline'; img-src 'self' data: blob:; "
       "connect-src 'self'; frame-src 'self' blob:; object-src 'none'; base-uri 'none'; form-action 'self'; "
       "frame-ancestors 'self'")
SECURITY_HEADERS = {"Content-Security-Policy": CSP, "X-Content-Type-Options": "nosniff",
                    "Referrer-Policy": "no-referrer", "Cache-Control": "no-cache"}

router = APIRouter(prefix="/ui", include_in_schema=False)


def render_page(page: str) -> str:
    """The HTML shell of ``page`` (one of ``PAGES``) with its title and script filled in."""
    title, script = PAGES[page]
    shell = (STATIC_DIR / "shell.html").read_text(encoding="utf-8")
    return (shell.replace("{{TITLE}}", title).replace("{{PAGE}}", page).replace("{{SCRIPT}}", script))


def _page(page: str) -> HTMLResponse:
    return HTMLResponse(render_page(page), headers=SECURITY_HEADERS)


@router.get("")
def ui_root() -> RedirectResponse:
    return RedirectResponse("/ui/", status_code=307)


def _page_route(page: str, with_id: bool):
    """GET handler of a page; ``with_id``: the path ends in an integer id (422 when it is not one)."""
    if with_id:
        def page_with_id(item_id: int) -> HTMLResponse:
            return _page(page)
        return page_with_id

    def page_plain() -> HTMLResponse:
        return _page(page)
    return page_plain


# path -> (page script, path ends in an integer id)
_ROUTES = {"/": ("overview", False), "/start": ("start", False), "/runs/{item_id}": ("run", True),
         "/gyros": ("gyro", False), "/gyros/{gyro_id}": ("gyro", False), "/fits": ("fits", False),
         "/fits/{item_id}": ("fit", True),
         "/close-loop": ("closeloop", False), "/close-loop/{item_id}": ("closeloop", True)}
for _path, (_name, _with_id) in _ROUTES.items():
    router.add_api_route(_path, _page_route(_name, _with_id), methods=["GET"], response_class=HTMLResponse)


def static_files() -> dict[str, Path]:
    """The servable assets: the files directly in ``static/`` with a known media type."""
    return {p.name: p for p in STATIC_DIR.iterdir() if p.is_file() and p.suffix in _MEDIA_TYPES}


@router.get("/static/{name}")
def static_asset(name: str) -> FileResponse:
    """A file of ``static/`` by its plain name (no sub-paths, so nothing outside the folder is reachable)."""
    path = static_files().get(name)
    if path is None:
        raise Problem(404, "Not found", f"no dashboard asset {name!r}")
    return FileResponse(path, media_type=_MEDIA_TYPES[path.suffix], headers=SECURITY_HEADERS)
