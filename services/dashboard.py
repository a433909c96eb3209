"""The operator dashboard at ``/dashboard``: server-rendered HTML from Jinja2 templates
(``services/templates``, autoescaped: scene names, parameters and errors come from users),
refreshed by a few lines of JavaScript that re-fetch the live fragment every 2 s (no Node build).

- ``/dashboard``: a red banner when jobs wait and no live worker serves their queue; job counts;
  queues and workers; the jobs, filtered by state, type, tenant and scene, with paging; failures;
  previews; scenes.
- ``/dashboard/jobs/{id}``: one job: cancel / retry buttons, the request's parameters, the stage
  timeline with durations and each stage's metrics, the quality figures of a reconstruction, the
  loss curves (axes, values, stage boundaries), the attempts with the reason for each retry, and
  the artifacts with an inline MP4 player.

Login with an operator API key (``POST /dashboard/login``) creates a server-side session
(HttpOnly, SameSite=Strict cookie). The buttons call the public API (``DELETE /jobs/{id}``,
``POST /jobs/{id}/retry``) with the session's CSRF token (:func:`services.auth.csrf_token`), so
they are authorised exactly as a client's request is.
"""


import math
from pathlib import Path
from urllib.parse import parse_qs, urlencode

import jinja2
import redis
from fastapi import FastAPI, Request
from fastapi.responses import HTMLResponse, RedirectResponse, Response
from sqlalchemy import func, select
from sqlalchemy.orm import selectinload

from services.auth import SESSION_COOKIE, Principal, csrf_token
from worker.db import Artifact, Job, JobAttempt, Scene, utcnow
from worker.queue import list_workers, live_workers, queue_stats

TEMPLATES = Path(__file__).resolve().parent / "templates"
STATES = ("queued", "running", "done", "failed", "canceled")
PAGE_SIZE = 20
#: Stage metrics shown as the quality of a reconstruction (in this order, where a stage has them).
QUALITY = (("test_psnr", "test PSNR (dB)"), ("test_ssim", "test SSIM"), ("train_psnr", "train PSNR (dB)"),
           ("photometric_psnr_prior", "photometric PSNR, prior map (dB)"),
           ("photometric_psnr_fitted", "photometric PSNR, fitted map (dB)"), ("gaussians", "Gaussians"),
           ("sky_floaters_pruned", "sky floaters pruned"))
CSP = ("default-src 'self'; style-src 'unsafe-inline'; script-src 'unsafe-inline'; img-src 'self'; "
       "media-src 'self'")

env = jinja2.Environment(loader=jinja2.FileSystemLoader(TEMPLATES), autoescape=True,
                         undefined=jinja2.StrictUndefined, trim_blocks=True, lstrip_blocks=True)


def _age(t) -> str:
    if t is None:
        return "-"
    s = (utcnow() - t).total_seconds()
    return f"{s:.0f} s ago" if s < 120 else f"{s / 60:.0f} min ago" if s < 7200 else t.strftime("%Y-%m-%d %H:%M")


def _dur(s) -> str:
    if s is None:
        return "-"
    return f"{s:.1f} s" if s < 120 else f"{s / 60:.1f} min" if s < 7200 else f"{s / 3600:.1f} h"


def _num(v) -> str:
    if isinstance(v, bool) or v is None or isinstance(v, str):
        return "-" if v is None else str(v)
    if isinstance(v, int):
        return f"{v:,}"
    if not math.isfinite(v):
        return str(v)
    return f"{v:.4g}" if abs(v) < 1e5 else f"{v:,.0f}"


def _size(n: int) -> str:
    for unit in ("B", "KB", "MB", "GB"):
        if n < 1024 or unit == "GB":
            return f"{n:.0f} {unit}" if unit == "B" else f"{n:.1f} {unit}"
        n /= 1024
    return str(n)


env.filters.update(age=_age, dur=_dur, num=_num, size=_size)


def sparkline(values: list[float], w: int = 160, h: int = 36) -> str:
    """A small SVG polyline of a curve (loss by iteration), for the jobs table."""
    vals = [float(v) for v in values if v == v and abs(v) != float("inf")]
    if len(vals) < 2:
        return ""
    lo, hi = min(vals), max(vals)
    span = (hi - lo) or 1.0
    pts = " ".join(f"{i * (w - 2) / (len(vals) - 1) + 1:.1f},{h - 1 - (v - lo) / span * (h - 2):.1f}"
                   for i, v in enumerate(vals))
    return (f"<svg class='curve' width='{w}' height='{h}' viewBox='0 0 {w} {h}'><polyline fill='none' "
            f"stroke='#2f80ed' stroke-width='1.5' points='{pts}'/></svg>")


def _nice_ticks(lo: float, hi: float, n: int = 5) -> list[float]:
    if hi <= lo:
        hi = lo + (abs(lo) or 1.0)
    raw = (hi - lo) / n
    mag = 10 ** math.floor(math.log10(raw))
    step = min((m * mag for m in (1, 2, 2.5, 5, 10) if m * mag >= raw), default=10 * mag)
    first = math.ceil(lo / step) * step
    return [first + i * step for i in range(int((hi - first) / step + 1e-9) + 1)]


def loss_chart(curves: list[tuple[str, list[float]]], w: int = 720, h: int = 260) -> dict | None:
    """The loss curves of a job's stages, one after the other on a shared axis: a dict the
    template draws as SVG (polylines per stage, x and y ticks with values, dashed stage
    boundaries with the stage names, first/last/min values). None without two finite points."""
    ml, mr, mt, mb = 64, 16, 22, 40
    pts_all = []
    x0 = 0
    segs = []
    for name, vals in curves:
        v = [float(x) for x in vals if isinstance(x, (int, float)) and math.isfinite(x)]
        if not v:
            continue
        segs.append((name, x0, v))
        x0 += len(v)
        pts_all += v
    if len(pts_all) < 2:
        return None
    lo, hi = min(pts_all), max(pts_all)
    yt = _nice_ticks(lo, hi)
    ylo, yhi = min(yt[0], lo), max(yt[-1], hi)
    if yhi <= ylo:
        yhi = ylo + 1.0
    n = max(x0 - 1, 1)
    X = lambda i: ml + (w - ml - mr) * i / n  # noqa: E731
    Y = lambda v: mt + (h - mt - mb) * (1 - (v - ylo) / (yhi - ylo))  # noqa: E731
    colours = ("#2f80ed", "#eb5757", "#27ae60", "#9b51e0", "#f2994a")
    lines, bounds = [], []
    for k, (name, start, v) in enumerate(segs):
        lines.append({"stage": name, "colour": colours[k % len(colours)], "n": len(v),
                      "first": v[0], "last": v[-1], "min": min(v),
                      "points": " ".join(f"{X(start + i):.1f},{Y(val):.1f}" for i, val in enumerate(v))})
        bounds.append({"stage": name, "x": X(start), "label_x": X(start) + 4})
    xt = [round(x) for x in _nice_ticks(0, n, 6) if x <= n]
    return {"w": w, "h": h, "ml": ml, "mr": mr, "mt": mt, "mb": mb, "x_axis_y": h - mb,
            "yticks": [{"y": Y(t), "label": _num(t)} for t in yt if ylo <= t <= yhi],
            "xticks": [{"x": X(t), "label": str(t)} for t in xt],
            "lines": lines, "bounds": bounds, "points": len(pts_all), "min": lo, "max": hi}


def _page(template: str, status: int = 200, **ctx) -> HTMLResponse:
    return HTMLResponse(env.get_template(template).render(**ctx), status_code=status,
                        headers={"Cache-Control": "no-store", "X-Frame-Options": "DENY",
                                 "Content-Security-Policy": CSP})


def _filters(request: Request) -> dict:
    q = request.query_params
    f = {k: (q.get(k) or "").strip()[:64] for k in ("state", "type", "tenant", "scene")}
    if f["state"] not in STATES:
        f["state"] = ""
    try:
        f["offset"] = max(int(q.get("offset") or 0), 0)
    except ValueError:
        f["offset"] = 0
    return f


def _system(app: FastAPI) -> dict:
    try:
        conn = app.state.rconn()
        qs, ws = queue_stats(conn), list_workers(conn)
        live = live_workers(ws, app.state.settings)
        unserved = app.state.unserved_queues()
        rmsg = "ok"
    except redis.RedisError as e:
        qs, ws, live, unserved, rmsg = [], [], {}, [], f"unreachable: {e}"
    stale = app.state.settings.worker_stale_s
    for w in ws:
        w["live"] = w["heartbeat_age_s"] is not None and w["heartbeat_age_s"] <= stale
    return {"queues": qs, "workers": ws, "live": live, "unserved": unserved, "redis": rmsg}


def overview(app: FastAPI, f: dict) -> dict:
    """Everything the overview fragment shows, for filters ``f``."""
    db = app.state.db
    with db.session() as s:
        counts = dict(s.execute(select(Job.state, func.count()).group_by(Job.state)).all())
        q = select(Job)
        if f["state"]:
            q = q.where(Job.state == f["state"])
        if f["type"]:
            q = q.where(Job.type == f["type"])
        if f["tenant"]:
            q = q.where(Job.tenant == f["tenant"])
        if f["scene"]:
            q = q.where(Job.scene_id == f["scene"])
        total = s.scalar(select(func.count()).select_from(q.subquery()))
        jobs = s.scalars(q.options(selectinload(Job.stages)).order_by(Job.created_at.desc(), Job.id)
                         .limit(PAGE_SIZE).offset(f["offset"])).all()
        failed = s.scalars(select(Job).where(Job.state == "failed").order_by(Job.finished_at.desc()).limit(10)).all()
        scenes = s.scalars(select(Scene).order_by(Scene.created_at.desc()).limit(50)).all()
        n_scenes = s.scalar(select(func.count()).select_from(Scene))
        scene_names = dict(s.execute(select(Scene.id, Scene.name).where(
            Scene.id.in_({j.scene_id for j in jobs if j.scene_id}))).all()) if jobs else {}
        tenants = sorted(t for (t,) in s.execute(select(Job.tenant).distinct()).all())
        types = sorted(t for (t,) in s.execute(select(Job.type).distinct()).all())
        done_ids = [j.id for j in jobs if j.state == "done"]
        previews = {a.job_id: a.name for a in s.scalars(
            select(Artifact).where(Artifact.job_id.in_(done_ids), Artifact.kind == "png")
            .order_by(Artifact.name)).all()} if done_ids else {}
    rows = []
    for j in jobs:
        quality = None
        for st in j.stages:
            if isinstance((st.metrics or {}).get("test_psnr"), (int, float)):
                quality = f"{st.metrics['test_psnr']:.2f} dB ({st.name})"
        rows.append({"job": j, "pct": int(round(100 * min(max(j.progress or 0, 0), 1))),
                     "scene_name": scene_names.get(j.scene_id, j.scene_id or "-"), "quality": quality,
                     "curves": [(st.name, k, sparkline(v)) for st in j.stages for k, v in (st.metrics or {}).items()
                                if isinstance(v, list)]})

    def link(**over) -> str:
        d = {k: v for k, v in {**f, **over}.items() if v not in ("", 0, None)}
        return "/dashboard" + ("?" + urlencode(d) if d else "")

    off = f["offset"]
    paging = {"total": total, "first": off + 1 if rows else 0, "last": off + len(rows),
              "newer": link(offset=max(off - PAGE_SIZE, 0)) if off > 0 else None,
              "older": link(offset=off + PAGE_SIZE) if off + PAGE_SIZE < total else None}
    return {"counts": {st: counts.get(st, 0) for st in STATES}, "rows": rows, "failed": failed, "scenes": scenes,
            "n_scenes": n_scenes, "previews": list(previews.items())[:8], "f": f, "tenants": tenants,
            "types": types, "states": STATES, "paging": paging, **_system(app)}


def job_detail(app: FastAPI, job_id: str) -> dict | None:
    db = app.state.db
    with db.session() as s:
        j = s.scalar(select(Job).options(selectinload(Job.stages)).where(Job.id == job_id))
        if j is None:
            return None
        attempts = s.scalars(select(JobAttempt).where(JobAttempt.job_id == job_id)
                             .order_by(JobAttempt.attempt)).all()
        arts = s.scalars(select(Artifact).where(Artifact.job_id == job_id).order_by(Artifact.name)).all()
        scene = s.get(Scene, j.scene_id) if j.scene_id else None
    now = utcnow()
    t0 = j.created_at
    stages = []
    for st in j.stages:
        end = st.finished_at or (now if st.state == "running" and st.started_at else None)
        dur = (end - st.started_at).total_seconds() if st.started_at and end else None
        m = st.metrics or {}
        stages.append({"s": st, "duration": dur, "offset": (st.started_at - t0).total_seconds() if st.started_at else None,
                       "figures": {k: v for k, v in m.items() if not isinstance(v, (list, dict))},
                       "curves": {k: len(v) for k, v in m.items() if isinstance(v, list)}})
    span = max([x["offset"] + x["duration"] for x in stages if x["offset"] is not None and x["duration"]] + [1e-9])
    for x in stages:
        x["bar"] = ({"left": 100 * x["offset"] / span, "width": max(100 * x["duration"] / span, 0.5)}
                    if x["offset"] is not None and x["duration"] is not None else None)
    quality = [{"key": k, "label": label, "per_stage": [(st.name, (st.metrics or {})[k]) for st in j.stages
                                                       if isinstance((st.metrics or {}).get(k), (int, float))]}
               for k, label in QUALITY]
    quality = [q for q in quality if q["per_stage"]]
    chart = loss_chart([(st.name, (st.metrics or {}).get("loss") or []) for st in j.stages])
    att = []
    for a in attempts:
        run = ((a.finished_at or now) - a.started_at).total_seconds() if a.started_at else None
        wait = ((a.started_at or now) - a.queued_at).total_seconds() if a.queued_at else None
        att.append({"a": a, "run": run, "wait": wait})
    params = j.params or {}
    flat = []

    def walk(prefix, v):
        if isinstance(v, dict) and v:
            for k, x in v.items():
                walk(f"{prefix}.{k}" if prefix else str(k), x)
        elif isinstance(v, list) and v and any(isinstance(x, (dict, list)) for x in v):
            for i, x in enumerate(v):
                walk(f"{prefix}[{i}]", x)
        else:
            flat.append((prefix, v))

    walk("", params)
    return {"j": j, "scene": scene, "stages": stages, "quality": quality, "chart": chart, "attempts": att,
            "params": flat, "artifacts": arts, "videos": [a for a in arts if a.kind == "mp4"],
            "images": [a for a in arts if a.kind == "png"][:6],
            "can_cancel": j.state in ("queued", "running"), "can_retry": j.state in ("failed", "canceled"),
            "run_s": ((j.finished_at or now) - j.started_at).total_seconds() if j.started_at else None,
            **_system(app)}


def mount_dashboard(app: FastAPI) -> None:
    auth = app.state.auth
    settings = app.state.settings

    def session(request: Request) -> tuple[Principal | None, str]:
        tok = request.cookies.get(SESSION_COOKIE, "")
        p = auth.from_session(tok)
        return (p if p is not None and p.operator else None), tok

    @app.get("/dashboard", response_class=HTMLResponse, include_in_schema=False)
    def dashboard(request: Request):
        p, tok = session(request)
        if p is None:
            return _page("login.html", error="")
        f = _filters(request)
        return _page("overview.html", csrf=csrf_token(tok), query=request.url.query, **overview(app, f))

    @app.get("/dashboard/fragment", response_class=HTMLResponse, include_in_schema=False)
    def fragment(request: Request):
        if session(request)[0] is None:
            return HTMLResponse("login required", status_code=401)
        return _page("_overview.html", **overview(app, _filters(request)))

    @app.get("/dashboard/jobs/{job_id}", response_class=HTMLResponse, include_in_schema=False)
    def job_page(job_id: str, request: Request):
        p, tok = session(request)
        if p is None:
            return _page("login.html", error="")
        d = job_detail(app, job_id[:64])
        if d is None:
            return _page("notfound.html", status=404, what=f"job {job_id[:64]}")
        return _page("job.html", csrf=csrf_token(tok), **d)

    @app.get("/dashboard/jobs/{job_id}/fragment", response_class=HTMLResponse, include_in_schema=False)
    def job_fragment(job_id: str, request: Request):
        if session(request)[0] is None:
            return HTMLResponse("login required", status_code=401)
        d = job_detail(app, job_id[:64])
        if d is None:
            return HTMLResponse("job not found", status_code=404)
        return _page("_job.html", **d)

    @app.post("/dashboard/login", include_in_schema=False)
    async def login(request: Request):
        body = (await request.body())[:4096].decode("utf-8", "replace")
        key = (parse_qs(body).get("key") or [""])[0].strip()
        p = auth.from_key(key) if key else None
        if p is None or not p.operator:
            return _page("login.html", status=401, error="That key is not a valid operator key.")
        token = auth.new_session(p)
        r = RedirectResponse("/dashboard", status_code=303)
        r.set_cookie(SESSION_COOKIE, token, max_age=settings.session_ttl_s, httponly=True, samesite="strict",
                     secure=settings.cookie_secure, path="/")
        return r

    @app.post("/dashboard/logout", include_in_schema=False)
    def logout(request: Request) -> Response:
        tok = request.cookies.get(SESSION_COOKIE, "")
        if tok:
            auth.end_session(tok)
        r = RedirectResponse("/dashboard", status_code=303)
        r.delete_cookie(SESSION_COOKIE, path="/")
        return r

