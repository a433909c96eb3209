"""The operator dashboard: rendering and escaping in-process, and end to end in headless
Chromium (Debian's chromium + chromedriver, driven by Selenium): log in with an operator key,
watch a job move to done without reloading, see its preview."""

from __future__ import annotations

import shutil
import time

import httpx
import pytest

try:
    from selenium.common.exceptions import NoSuchElementException, StaleElementReferenceException, TimeoutException
except ImportError:  # the browser test skips without selenium; the other tests still run
    NoSuchElementException = StaleElementReferenceException = TimeoutException = RuntimeError

from conftest_shared import OPERATOR_KEY
from svc_support import make_bundle, start_gateway, start_worker, zip_bundle


def test_login_required_and_wrong_keys_refused(client, keys):
    anon = {"Authorization": ""}
    r = client.get("/dashboard", headers=anon)
    assert r.status_code == 200 and 'name="key"' in r.text and "Recent jobs" not in r.text
    assert client.get("/dashboard/fragment", headers=anon).status_code == 401
    r = client.post("/dashboard/login", data={"key": keys["acme"]}, headers=anon)  # a client key
    assert r.status_code == 401 and "not a valid operator key" in r.text
    r = client.post("/dashboard/login", data={"key": "brdf_nope"}, headers=anon)
    assert r.status_code == 401


def test_dashboard_escapes_user_content(client, tmp_path):
    z = zip_bundle(make_bundle(tmp_path / "b"), tmp_path / "b.zip")
    r = client.post("/scenes", params={"name": "<script>alert(1)</script>"}, content=z.read_bytes(),
                    headers={"Content-Type": "application/zip"})
    assert r.status_code == 201
    client.cookies.clear()
    r = client.post("/dashboard/login", data={"key": OPERATOR_KEY}, headers={"Authorization": ""},
                    follow_redirects=False)
    assert r.status_code == 303 and "httponly" in r.headers["set-cookie"].lower()
    assert "samesite=strict" in r.headers["set-cookie"].lower()
    page = client.get("/dashboard", headers={"Authorization": ""})
    assert "Recent jobs" in page.text
    assert "<script>alert(1)</script>" not in page.text and "&lt;script&gt;alert(1)&lt;/script&gt;" in page.text
    # the session cookie reads but never writes: a state-changing call without a key is refused
    scene_id = r = client.get("/scenes").json()["items"][0]["id"]
    assert client.post(f"/scenes/{scene_id}/render", json={}, headers={"Authorization": ""}).status_code == 401
    assert client.post("/dashboard/logout", headers={"Authorization": ""}).status_code in (200, 303)
    assert client.get("/dashboard/fragment", headers={"Authorization": ""}).status_code == 401


def test_sparkline_draws_loss_curves():
    from services.dashboard import sparkline

    svg = sparkline([1.0, 0.5, 0.25, float("nan"), 0.2])
    assert svg.startswith("<svg") and svg.count(",") == 4
    assert sparkline([1.0]) == ""


@pytest.fixture
def browser(tmp_path):
    if not (shutil.which("chromium") and shutil.which("chromedriver")):
        pytest.fail("chromium and chromedriver are missing: run scripts/setup.sh as root "
                    "(apt-get install chromium chromium-driver)")
    from selenium import webdriver
    from selenium.webdriver.chrome.service import Service

    opts = webdriver.ChromeOptions()
    opts.binary_location = shutil.which("chromium")
    # no background traffic: this browser talks to the loopback gateway only
    for a in ("--headless=new", "--no-sandbox", "--disable-gpu", "--disable-dev-shm-usage", "--window-size=1400,1800",
              "--disable-quic", "--no-first-run", "--disable-background-networking", "--disable-component-update",
              "--disable-sync", "--disable-default-apps", "--disable-extensions", "--no-default-browser-check",
              f"--user-data-dir={tmp_path / 'chromium-profile'}"):
        opts.add_argument(a)
    d = webdriver.Chrome(service=Service(executable_path=shutil.which("chromedriver")), options=opts)
    d.set_page_load_timeout(30)
    yield d
    d.quit()


def _text(browser, css: str, tries: int = 20) -> str:
    """Text of the element at ``css``, retried while the live refresh swaps the DOM under it."""
    from selenium.webdriver.common.by import By

    for _ in range(tries):
        try:
            return browser.find_element(By.CSS_SELECTOR, css).text
        except (StaleElementReferenceException, NoSuchElementException):
            time.sleep(0.2)
    return browser.find_element(By.CSS_SELECTOR, css).text


@pytest.mark.slow
def test_dashboard_end_to_end_in_chromium(settings, tmp_path, browser):
    from selenium.webdriver.common.by import By
    from selenium.webdriver.support import expected_conditions as EC
    from selenium.webdriver.support.ui import WebDriverWait

    procs = []
    try:
        gw, base = start_gateway(settings, tmp_path / "gateway.log")
        procs.append(gw)
        c = httpx.Client(base_url=base, headers={"Authorization": f"Bearer {OPERATOR_KEY}"}, timeout=30)
        # the worker starts only once the page shows the job queued, so that state is seen however
        # fast the export runs (a fast CI machine once finished it between two polls)
        z = zip_bundle(make_bundle(tmp_path / "b", frames=20, width=320, height=240, test_frames=4, with_gt=False),
                       tmp_path / "b.zip")
        sid = c.post("/scenes", content=z.read_bytes(), headers={"Content-Type": "application/zip"}).json()["id"]

        browser.get(base + "/dashboard")
        browser.find_element(By.ID, "key").send_keys("brdf_wrong-key")
        browser.find_element(By.ID, "login").click()
        err = WebDriverWait(browser, 20).until(EC.presence_of_element_located((By.ID, "login-error")))
        assert "not a valid operator key" in err.text
        browser.find_element(By.ID, "key").send_keys(OPERATOR_KEY)
        browser.find_element(By.ID, "login").click()
        WebDriverWait(browser, 20).until(EC.presence_of_element_located((By.ID, "jobs")))
        assert "no jobs yet" in _text(browser, "#jobs")

        jid = c.post(f"/scenes/{sid}/render", json={}).json()["id"]
        row = f"tr.job[data-job-id='{jid}']"
        # the page refreshes itself: the job appears, then reaches done, with no reload
        marker = browser.execute_script("window.__noReload = 1; return window.__noReload;")
        states = set()
        deadline = time.time() + 60
        while time.time() < deadline and "queued" not in states:
            try:
                els = browser.find_elements(By.CSS_SELECTOR, row)
                if els:
                    states.add(els[0].get_attribute("data-state"))
            except StaleElementReferenceException:
                pass
            time.sleep(0.3)
        assert states == {"queued"}, f"with no worker running the page showed {states}\n{gw.tail()}"
        procs.append(start_worker(settings, tmp_path / "worker.log"))
        deadline = time.time() + 120
        while time.time() < deadline:
            try:  # the live refresh replaces the table: an element may go stale between calls
                els = browser.find_elements(By.CSS_SELECTOR, row)
                if els:
                    states.add(els[0].get_attribute("data-state"))
                    if "done" in states:
                        break
            except StaleElementReferenceException:
                pass
            time.sleep(0.3)
        assert "done" in states, f"states seen: {states}\n{gw.tail()}"
        assert browser.execute_script("return window.__noReload;") == marker, "the page was reloaded"
        assert _text(browser, row + " .pct") == "100%"
        assert _text(browser, row + " td:nth-child(6)") == "upload"
        # the preview image is served to the logged-in browser and decodes
        img = WebDriverWait(browser, 20).until(EC.presence_of_element_located(
            (By.CSS_SELECTOR, f"#previews figure[data-job-id='{jid}'] img.preview")))
        WebDriverWait(browser, 20).until(lambda d: d.execute_script(
            "return arguments[0].complete && arguments[0].naturalWidth > 0", img))
        w = browser.execute_script("return arguments[0].naturalWidth", img)
        assert w == 320, w  # the first captured frame, full width
        # queues and workers with heartbeats
        assert browser.find_element(By.CSS_SELECTOR, "#queues tr[data-queue='render']")
        worker_rows = browser.find_elements(By.CSS_SELECTOR, "#workers tr.worker")
        assert len(worker_rows) == 1 and "s ago" in worker_rows[0].text
        assert "render,train" in worker_rows[0].text
        browser.save_screenshot(str(tmp_path / "dashboard.png"))
        browser.find_element(By.ID, "logout").click()
        WebDriverWait(browser, 10).until(EC.presence_of_element_located((By.ID, "key")))
    finally:
        for p in procs:
            p.stop()


# --- the job page, filters, paging and the no-worker banner (in-process) ---------------------------

def _login(client):
    r = client.post("/dashboard/login", data={"key": OPERATOR_KEY}, headers={"Authorization": ""},
                    follow_redirects=False)
    assert r.status_code == 303


def _upload(client, tmp_path, seed=0) -> str:
    z = zip_bundle(make_bundle(tmp_path / f"b{seed}", seed=seed), tmp_path / f"b{seed}.zip")
    r = client.post("/scenes", content=z.read_bytes(), headers={"Content-Type": "application/zip"})
    assert r.status_code == 201, r.text
    return r.json()["id"]


def test_loss_chart_axes_values_and_stage_boundaries():
    from services.dashboard import loss_chart

    c = loss_chart([("volume", [1.0, 0.5, float("nan"), 0.25]), ("pbr", []), ("joint", [0.3, 0.2])])
    assert [line["stage"] for line in c["lines"]] == ["volume", "joint"]
    assert c["points"] == 5 and c["min"] == 0.2 and c["max"] == 1.0
    assert [b["stage"] for b in c["bounds"]] == ["volume", "joint"]
    assert c["bounds"][0]["x"] == c["ml"] < c["bounds"][1]["x"] < c["w"] - c["mr"]
    labels = [float(t["label"]) for t in c["yticks"]]
    assert labels == sorted(labels) and labels[0] <= 0.2 + 1e-9 and labels[-1] >= 1.0 - 1e-9
    ys = [t["y"] for t in c["yticks"]]
    assert all(c["mt"] - 1e-6 <= y <= c["x_axis_y"] + 1e-6 for y in ys) and ys == sorted(ys, reverse=True)
    assert [t["label"] for t in c["xticks"]][0] == "0"
    assert c["lines"][1]["last"] == 0.2 and c["lines"][0]["first"] == 1.0
    assert loss_chart([("volume", [1.0])]) is None and loss_chart([]) is None


def test_job_page_shows_what_happened(client, app, tmp_path):
    """A reconstruct job as the workers leave it (stage rows with curves and figures, two
    attempts, an MP4 artifact): the page shows each part."""
    from worker.db import Artifact, Job, JobAttempt, JobStage, utcnow

    sid = _upload(client, tmp_path)
    db, store = app.state.db, app.state.store
    now = utcnow()
    from datetime import timedelta

    t = [now - timedelta(seconds=s) for s in (100, 95, 60, 58, 20, 5)]
    mp4 = tmp_path / "clip.mp4"
    mp4.write_bytes(b"\0" * 64)
    store.put_file(mp4, "jobs/j1/pbr.a2/relit.mp4")
    with db.session() as s:
        s.add(Job(id="j1", tenant="acme", scene_id=sid, type="reconstruct", queue="train", state="done",
                  params={"profile": "tiny", "stages": ["volume", "pbr"], "iterations_scale": 0.5},
                  attempts=2, max_attempts=3, created_at=t[0], started_at=t[1], finished_at=t[5], progress=1.0))
        s.flush()
        s.add(JobStage(job_id="j1", name="volume", state="done", progress=1.0, started_at=t[1], finished_at=t[3],
                       metrics={"loss": [0.9, 0.5, 0.3], "test_psnr": 21.5, "gaussians": 12345, "seconds": 30.0}))
        s.add(JobStage(job_id="j1", name="pbr", state="done", progress=1.0, started_at=t[4], finished_at=t[5],
                       metrics={"loss": [0.2, 0.15], "photometric_psnr_fitted": 18.25}))
        s.add(JobAttempt(job_id="j1", attempt=1, queued_at=t[0], started_at=t[1], finished_at=t[2], outcome="retried",
                         worker_name="w1", reason="work horse 42 of worker w1 killed by signal 9 (SIGKILL)"))
        s.add(JobAttempt(job_id="j1", attempt=2, queued_at=t[2], started_at=t[3], finished_at=t[5], outcome="done",
                         worker_name="w2"))
        s.add(Artifact(job_id="j1", name="pbr/relit.mp4", kind="mp4", content_type="video/mp4", size_bytes=64,
                       storage_key="jobs/j1/pbr.a2/relit.mp4"))
    _login(client)
    anon = {"Authorization": ""}
    page = client.get("/dashboard/jobs/j1", headers=anon)
    assert page.status_code == 200
    h = page.text
    assert 'data-stage="volume" data-state="done"' in h and 'class="duration">37.0 s<' in h  # 95 -> 58 s ago
    assert 'data-key="test_psnr">test_psnr: <b>21.5</b>' in h and "12,345" in h
    assert 'id="quality"' in h and "test PSNR (dB)" in h and "photometric PSNR, fitted map (dB)" in h
    assert 'id="loss-chart"' in h and h.count('class="boundary"') == 2 and h.count('<polyline class="loss"') == 2
    assert 'class="ytick"' in h and 'class="xtick"' in h and ">loss</text>" in h
    assert 'data-key="profile"><th>profile</th><td><code>"tiny"</code>' in h and 'data-key="iterations_scale"' in h
    assert 'data-attempt="1" data-outcome="retried"' in h and "killed by signal 9 (SIGKILL)" in h
    assert '<video controls preload="metadata" src="/jobs/j1/artifacts/pbr/relit.mp4"' in h
    assert 'id="retry"' not in h and 'id="cancel"' not in h  # done: nothing to do
    assert client.get("/dashboard/jobs/j1/fragment", headers=anon).text.count('id="loss-chart"') == 1
    assert client.get("/dashboard/jobs/nope", headers=anon).status_code == 404
    client.cookies.clear()
    assert 'name="key"' in client.get("/dashboard/jobs/j1", headers=anon).text  # login first
    assert client.get("/dashboard/jobs/j1/fragment", headers=anon).status_code == 401


def test_filters_paging_and_the_no_worker_banner(client, app, keys, tmp_path):
    import re

    from sqlalchemy import update

    from worker.db import Job

    sids = {t: None for t in ("acme", "globex")}
    for i, t in enumerate(sids):
        z = zip_bundle(make_bundle(tmp_path / f"b{t}", seed=i), tmp_path / f"{t}.zip")
        sids[t] = client.post("/scenes", content=z.read_bytes(), headers={"Content-Type": "application/zip",
                                                                         "Authorization": f"Bearer {keys[t]}"}).json()["id"]
    ids = {"acme": [], "globex": []}
    for i in range(26):
        t = "acme" if i % 2 else "globex"
        r = client.post(f"/scenes/{sids[t]}/render", json={"fps": 1 + i}, headers={"Authorization": f"Bearer {keys[t]}"})
        ids[t].append(r.json()["id"])
    with app.state.db.session() as s:
        s.execute(update(Job).where(Job.id.in_(ids["acme"][:4])).values(state="failed", error="boom"))
    _login(client)
    anon = {"Authorization": ""}

    def rows(url):
        h = client.get(url, headers=anon).text
        return h, re.findall(r'<tr class="job" data-job-id="(\w+)" data-state="(\w+)" data-type="(\w+)" '
                             r'data-tenant="(\w+)" data-scene="(\w*)"', h)

    h, r = rows("/dashboard")
    assert len(r) == 20 and 'id="older"' in h and 'id="newer"' not in h and ">1-20 of 26<" in h
    assert 'id="no-worker-banner"' in h and "queue &#39;render&#39;: 22 job(s) waiting" in h
    h2, r2 = rows("/dashboard?offset=20")
    assert len(r2) == 6 and 'id="newer"' in h2 and ">21-26 of 26<" in h2
    assert not {x[0] for x in r} & {x[0] for x in r2}
    h, r = rows("/dashboard?tenant=acme")
    assert len(r) == 13 and {x[3] for x in r} == {"acme"} and "tenant=acme" in h
    h, r = rows(f"/dashboard?scene={sids['globex']}")
    assert len(r) == 13 and {x[4] for x in r} == {sids["globex"]}
    h, r = rows("/dashboard?state=failed&tenant=acme&type=render")
    assert sorted(x[0] for x in r) == sorted(ids["acme"][:4]) and {x[1] for x in r} == {"failed"}
    h, r = rows("/dashboard?type=reconstruct")
    assert r == [] and "no jobs yet" in h
    # the live fragment honours the same filters
    frag = client.get("/dashboard/fragment?state=failed", headers=anon).text
    assert frag.count('<tr class="job"') == 4
    # no job waits: no banner
    with app.state.db.session() as s:
        s.execute(update(Job).where(Job.state == "queued").values(state="canceled"))
    assert 'id="no-worker-banner"' not in client.get("/dashboard", headers=anon).text


@pytest.mark.slow
def test_dashboard_operations_in_chromium(settings, tmp_path, browser, tiny_scene):
    """The operator's view of faults and results in headless Chromium: the red banner while a job
    waits with no worker; a killed work horse's retry and its reason; the finished job's stage
    timeline, artifacts and inline MP4 player; cancel and retry buttons (through the public API);
    a reconstruction's loss curves and quality; filters."""
    import os
    import signal

    from selenium.webdriver.common.by import By
    from selenium.webdriver.support.ui import Select, WebDriverWait

    st = settings.model_copy(update={"stale_after_s": 300.0})  # retries come from the worker, not the heartbeat check
    procs = []

    def wait(cond, timeout=60, what=""):
        def ok(d):
            try:
                return cond(d)
            except (StaleElementReferenceException, NoSuchElementException):
                return False
        return WebDriverWait(browser, timeout, poll_frequency=0.2).until(ok, what)

    def css(sel):
        return browser.find_elements(By.CSS_SELECTOR, sel)

    def read_all(sel, expr):
        """``expr`` (JavaScript of ``e``) of every element at ``sel``, read in one script: the live
        refresh (every 2 s) cannot swap the DOM between two elements' reads."""
        return browser.execute_script(
            f"return Array.from(document.querySelectorAll(arguments[0])).map(e => {expr});", sel)

    def settled(read, tries=25):
        """``read()`` retried while the live refresh swaps the DOM under the elements it reads."""
        for _ in range(tries - 1):
            try:
                return read()
            except (StaleElementReferenceException, NoSuchElementException):
                time.sleep(0.2)
        return read()

    def db_writable() -> bool:
        """No process holds the SQLite database's write lock (a horse stopped inside a write
        transaction would hold it for as long as it is stopped: the gateway's cancel then failed
        with 'database is locked' after its 30 s busy timeout, once in CI)."""
        import sqlite3

        if not st.db_url.startswith("sqlite"):
            return True
        # mode=rw: a wrong path is an error, not a new empty database that is always writable
        con = sqlite3.connect(f"file:{st.db_url.split('///', 1)[1]}?mode=rw", uri=True, timeout=0.2)
        try:
            con.execute("BEGIN IMMEDIATE")
            con.rollback()
            return True
        except sqlite3.OperationalError:
            return False
        finally:
            con.close()

    def hold_when_running(job_id, timeout=60):
        """SIGSTOP the work horse once the API reports the job running, at a moment it holds no
        database write lock; returns its pid."""
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            kids = w.descendants()
            if not kids:
                time.sleep(0.01)
                continue
            os.kill(kids[0], signal.SIGSTOP)
            if c.get(f"/jobs/{job_id}").json()["state"] == "running" and db_writable():
                return kids[0]
            os.kill(kids[0], signal.SIGCONT)
            time.sleep(0.02)
        raise AssertionError(f"job {job_id} never ran: {c.get(f'/jobs/{job_id}').json()['state']}")

    try:
        gw, base = start_gateway(st, tmp_path / "gateway.log")
        procs.append(gw)
        c = httpx.Client(base_url=base, headers={"Authorization": f"Bearer {OPERATOR_KEY}"}, timeout=30)
        z = zip_bundle(make_bundle(tmp_path / "b", frames=40, width=320, height=240, test_frames=5, with_gt=False),
                       tmp_path / "b.zip")
        sid = c.post("/scenes", content=z.read_bytes(), headers={"Content-Type": "application/zip"}).json()["id"]
        tz = zip_bundle(tiny_scene, tmp_path / "tiny.zip")
        tiny = c.post("/scenes", content=tz.read_bytes(), headers={"Content-Type": "application/zip"}).json()["id"]
        browser.get(base + "/dashboard")
        browser.find_element(By.ID, "key").send_keys(OPERATOR_KEY)
        browser.find_element(By.ID, "login").click()
        wait(lambda d: css("#jobs"), 20, "the dashboard")
        assert not css("#no-worker-banner")

        # 1. a job waits and no worker exists: the red banner says so; a worker starting clears it
        a = c.post(f"/scenes/{sid}/render", json={}).json()["id"]
        banner = wait(lambda d: css("#no-worker-banner"), 20, "the no-worker banner")[0]
        assert "queue 'render': 1 job(s) waiting" in banner.text and "no live worker serves it" in banner.text
        assert banner.value_of_css_property("background-color") == "rgba(198, 40, 40, 1)"
        w = start_worker(st, tmp_path / "worker.log")
        procs.append(w)
        # the job runs about 2 s: its horse is held (SIGSTOP) once the API reports it running, so
        # that the page can show it running before it ends
        horse = hold_when_running(a)
        wait(lambda d: not css("#no-worker-banner"), 30, "the banner to go once a worker runs")

        # 2. the work horse is killed mid-job: the job page shows the retry and why
        browser.get(f"{base}/dashboard/jobs/{a}")
        wait(lambda d: css("#job-summary[data-state='running']"), 30, "job A's page to show it running")
        assert css("#cancel") and not css("#retry")
        os.kill(horse, signal.SIGKILL)
        retried = "#attempts tr.attempt[data-attempt='1'][data-outcome='retried']"
        wait(lambda d: css(retried), 15, "the retried attempt")
        assert "killed by signal 9 (SIGKILL)" in settled(lambda: css(retried + " .reason")[0].text)
        wait(lambda d: css("#job-summary[data-state='done']"), 120, "job A to finish")
        # the page keeps refreshing itself after the job ends: each read is retried as a whole
        assert read_all("#attempts tr.attempt", "e.dataset.outcome") == ["retried", "done"]
        durations = dict(read_all("#timeline tr.stage",
                                  "[e.dataset.stage, e.querySelector('.duration').innerText.trim()]"))
        assert list(durations) == ["fetch", "export", "upload"] and all(v.endswith(" s") for v in durations.values())
        names = [x["name"] for x in c.get(f"/jobs/{a}/artifacts").json()["items"]]
        links = read_all("#artifacts tr.artifact a", "[e.innerText.trim(), e.href]")
        assert [t for t, _ in links] == names and "test.mp4" in names
        assert links[0][1].endswith(f"/jobs/{a}/artifacts/{names[0]}")
        # the inline player loads the MP4 through the artifact route (cookie session, Range); the
        # element is looked up inside each script, so a refresh between two calls cannot stale it
        video_js = "const v = document.querySelector('#artifacts video'); "
        wait(lambda d: d.execute_script(video_js + "return v !== null && (v.readyState >= 1 || v.error !== null)"),
             30, "the video's metadata")
        assert browser.execute_script(video_js + "return v.error") is None, "the MP4 did not decode"
        assert browser.execute_script(video_js + "return v.duration") > 0
        assert css("#params tr.param[data-key='split']")

        # 3. cancel and retry buttons go through the API
        zb = zip_bundle(make_bundle(tmp_path / "b2", frames=120, width=320, height=240, test_frames=5, with_gt=False,
                                    seed=1),
                        tmp_path / "b2.zip")  # long enough that it is still running when the button is pressed
        sid_b = c.post("/scenes", content=zb.read_bytes(), headers={"Content-Type": "application/zip"}).json()["id"]
        b = c.post(f"/scenes/{sid_b}/render", json={"fps": 5}).json()["id"]
        horse_b = hold_when_running(b)  # held so that it is still running when the button is pressed
        browser.get(f"{base}/dashboard/jobs/{b}")
        wait(lambda d: css("#job-summary[data-state='running']"), 60, "job B to run")
        # clicked by script: the live refresh may replace the button between finding and clicking it
        browser.execute_script("document.getElementById('cancel').click()")
        try:
            wait(lambda d: "cancel: job is canceled" in d.find_element(By.ID, "action-result").text, 60, "the cancel")
        except TimeoutException as e:  # say what the page and the API showed
            raise AssertionError(f"the cancel: page says {browser.find_element(By.ID, 'action-result').text!r}, "
                                 f"job B is {c.get(f'/jobs/{b}').json()['state']}") from e
        try:
            os.kill(horse_b, signal.SIGCONT)  # let it see the cancel and stop (if it was not killed)
        except ProcessLookupError:
            pass
        assert c.get(f"/jobs/{b}").json()["state"] == "canceled"
        wait(lambda d: css("#retry"), 10, "the retry button")
        browser.execute_script("document.getElementById('retry').click()")
        wait(lambda d: "retry: job is queued" in d.find_element(By.ID, "action-result").text, 20, "the retry")
        wait(lambda d: css("#job-summary[data-state='done']"), 120, "the retried job B to finish")
        reasons = read_all("#attempts tr.attempt .reason", "e.innerText.trim()")
        assert reasons[0].startswith("canceled by request; then retried by request (operator key"), reasons

        # 4. a reconstruction: loss curves with axes and stage boundaries, and its quality figures
        r = c.post(f"/scenes/{tiny}/reconstruct", json={"profile": "tiny", "stages": ["volume", "pbr"]}).json()["id"]
        browser.get(f"{base}/dashboard/jobs/{r}")
        wait(lambda d: css("#job-summary[data-state='done']") or css("#job-summary[data-state='failed']"), 300,
             "the reconstruction to finish")
        assert css("#job-summary[data-state='done']"), settled(lambda: css("#job-summary")[0].text)
        assert read_all("#loss-chart polyline.loss", "e.dataset.stage") == ["volume", "pbr"]
        assert read_all("#loss-chart line.boundary", "e.dataset.stage") == ["volume", "pbr"]
        yticks = [float(t.replace(",", "")) for t in read_all("#loss-chart text.ytick", "e.textContent.trim()")]
        assert len(yticks) >= 2 and yticks == sorted(yticks)
        api_loss = {s["name"]: s["metrics"]["loss"] for s in c.get(f"/jobs/{r}").json()["stages"]}
        last = settled(lambda: css("#loss tr.loss-row[data-stage='volume'] .last")[0].text)
        assert float(last) == pytest.approx(api_loss["volume"][-1], rel=1e-3)
        psnr = settled(lambda: css("#quality tr.figure[data-key='test_psnr'] span[data-stage='volume'] b")[0].text)
        assert float(psnr) == pytest.approx(
            next(s for s in c.get(f"/jobs/{r}").json()["stages"] if s["name"] == "volume")["metrics"]["test_psnr"],
            abs=1e-2)

        # 5. filters and paging on the overview
        browser.get(base + "/dashboard")
        Select(browser.find_element(By.ID, "f-type")).select_by_value("reconstruct")
        browser.find_element(By.ID, "apply-filters").click()
        wait(lambda d: "type=reconstruct" in d.current_url, 10, "the filtered page")
        assert read_all("#jobs tr.job", "e.dataset.jobId") == [r]
        Select(browser.find_element(By.ID, "f-type")).select_by_value("render")
        Select(browser.find_element(By.ID, "f-scene")).select_by_value(sid)
        browser.find_element(By.ID, "apply-filters").click()
        wait(lambda d: "type=render" in d.current_url, 10, "the filtered page")
        time.sleep(2.5)  # a live refresh keeps the filter
        assert read_all("#jobs tr.job", "e.dataset.jobId") == [a]
        assert "1-1 of 1" in settled(lambda: browser.find_element(By.ID, "page-info").text)
        browser.save_screenshot(str(tmp_path / "dashboard-ops.png"))
    finally:
        for p in procs:
            p.stop()
