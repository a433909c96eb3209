"""The operator dashboard at ``/dashboard``: server-rendered HTML, refreshed by a few lines of
JavaScript that re-fetch the live fragment every 2 s (no Node build).

Login with an operator API key (``POST /dashboard/login``) creates a server-side session
(HttpOnly, SameSite=Strict cookie). Every value shown is HTML-escaped: scene names and errors
come from users.
"""


import html
from urllib.parse import parse_qs

import redis
from fastapi import FastAPI, Request
from fastapi.responses import HTMLResponse, RedirectResponse, Response
from sqlalchemy import func, select
from sqlalchemy.orm import selectinload

from services.auth import SESSION_COOKIE, Principal
from worker.db import Artifact, Job, Scene, utcnow
from worker.queue import list_workers, queue_stats

esc = html.escape

CSS = """
body{font:14px system-ui,sans-serif;margin:0;background:#f5f6f8;color:#1b1f24}
header{background:#1b2a41;color:#fff;padding:10px 20px;display:flex;justify-content:space-between;align-items:center}
header h1{font-size:18px;margin:0} main{padding:16px 20px} section{background:#fff;border-radius:6px;
padding:10px 14px;margin-bottom:14px;box-shadow:0 1px 2px #0002} h2{font-size:15px;margin:4px 0 8px}
table{border-collapse:collapse;width:100%} th,td{text-align:left;padding:4px 8px;border-bottom:1px solid #eee;
vertical-align:middle} th{font-weight:600;color:#555} .bar{background:#e4e7eb;border-radius:3px;width:140px;height:10px}
.bar>div{background:#2f80ed;height:10px;border-radius:3px} .state{padding:1px 7px;border-radius:9px;font-size:12px}
.queued{background:#eee}.running{background:#d6e8ff}.done{background:#d4f5dd}.failed{background:#ffd9d9}
.canceled{background:#f1e7c8} .err{color:#a00;font-family:monospace;font-size:12px;white-space:pre-wrap}
.previews{display:flex;flex-wrap:wrap;gap:10px} .previews figure{margin:0} img.preview{max-width:360px;
image-rendering:pixelated;border:1px solid #ccc} .grid{display:grid;grid-template-columns:1fr 1fr;gap:14px}
.muted{color:#777} form.login{max-width:420px;margin:60px auto;background:#fff;padding:20px;border-radius:6px}
input[type=password]{width:100%;padding:6px;margin:8px 0} button{padding:6px 14px}
"""

JS = """
async function refresh(){
  try{
    const r = await fetch('/dashboard/fragment', {credentials:'same-origin', cache:'no-store'});
    if(r.status === 401){ location.reload(); return; }
    if(r.ok){ document.getElementById('live').innerHTML = await r.text();
              document.getElementById('updated').textContent = new Date().toLocaleTimeString(); }
  }catch(e){ document.getElementById('updated').textContent = 'offline: ' + e; }
}
setInterval(refresh, 2000);
"""


def _page(title: str, body: str, status: int = 200) -> HTMLResponse:
    return HTMLResponse(f"<!doctype html><html><head><meta charset='utf-8'><title>{esc(title)}</title>"
                        f"<style>{CSS}</style></head><body>{body}</body></html>", status_code=status,
                        headers={"Cache-Control": "no-store", "X-Frame-Options": "DENY",
                                 "Content-Security-Policy": "default-src 'self'; style-src 'unsafe-inline'; "
                                                            "script-src 'unsafe-inline'; img-src 'self'"})


def _login_page(error: str = "", status: int = 200) -> HTMLResponse:
    msg = f"<p class='err' id='login-error'>{esc(error)}</p>" if error else ""
    return _page("BRDFusion: operator login", f"""
<form class="login" method="post" action="/dashboard/login">
<h2>BRDFusion operator dashboard</h2>{msg}
<label>Operator API key<input type="password" name="key" id="key" autocomplete="off" required></label>
<button type="submit" id="login">Log in</button></form>""", status)


def sparkline(values: list[float], w: int = 160, h: int = 36) -> str:
    """A small SVG polyline of a curve (loss by iteration)."""
    vals = [float(v) for v in values if v == v and abs(v) != float("inf")]
    if len(vals) < 2:
        return ""
    lo, hi = min(vals), max(vals)
    span = (hi - lo) or 1.0
    pts = " ".join(f"{i * (w - 2) / (len(vals) - 1) + 1:.1f},{h - 1 - (v - lo) / span * (h - 2):.1f}"
                   for i, v in enumerate(vals))
    return (f"<svg class='curve' width='{w}' height='{h}' viewBox='0 0 {w} {h}'><polyline fill='none' "
            f"stroke='#2f80ed' stroke-width='1.5' points='{pts}'/></svg>")


def _age(t) -> str:
    if t is None:
        return "-"
    s = (utcnow() - t).total_seconds()
    return f"{s:.0f} s ago" if s < 120 else f"{s / 60:.0f} min ago" if s < 7200 else t.strftime("%Y-%m-%d %H:%M")


def render_fragment(app: FastAPI) -> str:
    db = app.state.db
    out = []
    with db.session() as s:
        counts = dict(s.execute(select(Job.state, func.count()).group_by(Job.state)).all())
        jobs = s.scalars(select(Job).options(selectinload(Job.stages)).order_by(Job.created_at.desc()).limit(50)).all()
        failed = s.scalars(select(Job).where(Job.state == "failed").order_by(Job.finished_at.desc()).limit(20)).all()
        scenes = s.scalars(select(Scene).order_by(Scene.created_at.desc()).limit(50)).all()
        scene_names = {sc.id: sc.name for sc in scenes}
        done_ids = [j.id for j in jobs if j.state == "done"]
        previews = {a.job_id: a.name for a in s.scalars(
            select(Artifact).where(Artifact.job_id.in_(done_ids), Artifact.kind == "png")).all()} if done_ids else {}
    summary = " · ".join(f"<span class='state {st}'>{st}: {counts.get(st, 0)}</span>"
                         for st in ("queued", "running", "done", "failed", "canceled"))
    out.append(f"<section id='summary'><h2>Jobs</h2>{summary} <span class='muted'>· scenes: {len(scenes)}</span></section>")

    try:
        conn = app.state.rconn()
        qs, ws, rmsg = queue_stats(conn), list_workers(conn), "ok"
    except redis.RedisError as e:
        qs, ws, rmsg = [], [], f"unreachable: {e}"
    qrows = "".join(f"<tr data-queue='{esc(q['name'])}'><td>{esc(q['name'])}</td><td class='depth'>{q['queued']}</td>"
                    f"<td>{q['started']}</td><td>{q['failed']}</td></tr>" for q in qs)
    def hb(w) -> str:
        return "-" if w["heartbeat_age_s"] is None else f"{w['heartbeat_age_s']:.0f} s ago"

    wrows = "".join(
        f"<tr class='worker'><td>{esc(w['name'])}</td><td>{esc(w['state'])}</td><td>{esc(','.join(w['queues']))}</td>"
        f"<td>{esc(w['current_job'] or '-')}</td><td>{hb(w)}</td></tr>"
        for w in ws) or "<tr><td colspan='5' class='muted'>no worker registered</td></tr>"
    out.append(f"<div class='grid'><section id='queues'><h2>Queues <span class='muted'>(redis: {esc(rmsg)})</span></h2>"
               f"<table><tr><th>queue</th><th>waiting</th><th>running</th><th>failed</th></tr>{qrows}</table></section>"
               f"<section id='workers'><h2>Workers</h2><table><tr><th>name</th><th>state</th><th>queues</th>"
               f"<th>job</th><th>heartbeat</th></tr>{wrows}</table></section></div>")

    jrows = []
    for j in jobs:
        pct = int(round(100 * min(max(j.progress or 0, 0), 1)))
        curves = "".join(f"<div title='{esc(st.name)}: {esc(k)}'>{sparkline(v)}</div>"
                         for st in j.stages for k, v in (st.metrics or {}).items() if isinstance(v, list))
        eta = f"{j.eta_s:.0f} s" if j.state == "running" and j.eta_s is not None else "-"
        jrows.append(
            f"<tr class='job' data-job-id='{esc(j.id)}' data-state='{esc(j.state)}'><td><code>{esc(j.id)}</code></td>"
            f"<td>{esc(j.type)}</td><td>{esc(scene_names.get(j.scene_id, j.scene_id or '-'))}</td>"
            f"<td>{esc(j.tenant)}</td><td><span class='state {esc(j.state)}'>{esc(j.state)}</span></td>"
            f"<td>{esc(j.stage or '-')}</td><td><div class='bar' title='{pct}%'><div style='width:{pct}%'></div></div>"
            f"<span class='pct'>{pct}%</span></td><td>{eta}</td><td>{j.attempts}/{j.max_attempts}</td>"
            f"<td>{_age(j.created_at)}</td><td>{curves}</td></tr>")
    out.append("<section id='jobs'><h2>Recent jobs</h2><table><tr><th>id</th><th>type</th><th>scene</th>"
               "<th>tenant</th><th>state</th><th>stage</th><th>progress</th><th>ETA</th><th>attempt</th>"
               "<th>created</th><th>curves</th></tr>" + ("".join(jrows) or
                                                         "<tr><td colspan='11' class='muted'>no jobs yet</td></tr>")
               + "</table></section>")

    figs = "".join(f"<figure data-job-id='{esc(jid)}'><img class='preview' alt='preview of job {esc(jid)}' "
                   f"src='/jobs/{esc(jid)}/artifacts/{esc(name)}'><figcaption><code>{esc(jid)}</code></figcaption></figure>"
                   for jid, name in list(previews.items())[:8])
    out.append(f"<section id='previews'><h2>Previews</h2><div class='previews'>{figs or '<span class=muted>none yet</span>'}"
               "</div></section>")

    frows = "".join(f"<tr class='failure' data-job-id='{esc(j.id)}'><td><code>{esc(j.id)}</code></td><td>{esc(j.type)}</td>"
                    f"<td>{_age(j.finished_at)}</td><td class='err'>{esc(j.error or '')}</td></tr>" for j in failed)
    out.append("<section id='failures'><h2>Failures</h2><table><tr><th>job</th><th>type</th><th>when</th><th>error</th>"
               f"</tr>{frows or '<tr><td colspan=4 class=muted>none</td></tr>'}</table></section>")

    srows = "".join(f"<tr class='scene'><td><code>{esc(sc.id)}</code></td><td>{esc(sc.name)}</td><td>{esc(sc.tenant)}</td>"
                    f"<td>{sc.frames} ({sc.train_frames} train / {sc.test_frames} test)</td>"
                    f"<td>{'yes' if sc.has_ground_truth else 'no'}</td><td>{_age(sc.created_at)}</td></tr>" for sc in scenes)
    out.append("<section id='scenes'><h2>Scenes</h2><table><tr><th>id</th><th>name</th><th>tenant</th><th>frames</th>"
               f"<th>ground truth</th><th>uploaded</th></tr>{srows or '<tr><td colspan=6 class=muted>none</td></tr>'}"
               "</table></section>")
    return "".join(out)


def mount_dashboard(app: FastAPI) -> None:
    auth = app.state.auth
    settings = app.state.settings

    def session_operator(request: Request) -> Principal | None:
        p = auth.from_session(request.cookies.get(SESSION_COOKIE, ""))
        return p if p is not None and p.operator else None

    @app.get("/dashboard", response_class=HTMLResponse, include_in_schema=False)
    def dashboard(request: Request):
        if session_operator(request) is None:
            return _login_page()
        return _page("BRDFusion dashboard", f"""
<header><h1>BRDFusion operator dashboard</h1><div><span class="muted">updated <span id="updated">now</span></span>
<form method="post" action="/dashboard/logout" style="display:inline"><button id="logout">Log out</button></form></div></header>
<main id="live">{render_fragment(app)}</main><script>{JS}</script>""")

    @app.get("/dashboard/fragment", response_class=HTMLResponse, include_in_schema=False)
    def fragment(request: Request):
        if session_operator(request) is None:
            return HTMLResponse("login required", status_code=401)
        return HTMLResponse(render_fragment(app), headers={"Cache-Control": "no-store"})

    @app.post("/dashboard/login", include_in_schema=False)
    async def login(request: Request):
        body = (await request.body())[:4096].decode("utf-8", "replace")
        key = (parse_qs(body).get("key") or [""])[0].strip()
        p = auth.from_key(key) if key else None
        if p is None or not p.operator:
            return _login_page("That key is not a valid operator key.", status=401)
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
