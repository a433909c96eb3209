"""The operator dashboard: rendering and escaping in-process, and end to end in headless
Chromium (Debian's chromium + chromedriver, driven by Selenium): log in with an operator key,
watch a job move to done without reloading, see its preview."""

from __future__ import annotations

import shutil
import time

import httpx
import pytest

try:
    from selenium.common.exceptions import NoSuchElementException, StaleElementReferenceException
except ImportError:  # the browser test skips without selenium; the other tests still run
    NoSuchElementException = StaleElementReferenceException = RuntimeError

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


@pytest.mark.slow
def _text(browser, css: str, tries: int = 20) -> str:
    """Text of the element at ``css``, retried while the live refresh swaps the DOM under it."""
    from selenium.webdriver.common.by import By

    for _ in range(tries):
        try:
            return browser.find_element(By.CSS_SELECTOR, css).text
        except (StaleElementReferenceException, NoSuchElementException):
            time.sleep(0.2)
    return browser.find_element(By.CSS_SELECTOR, css).text


def test_dashboard_end_to_end_in_chromium(settings, tmp_path, browser):
    from selenium.webdriver.common.by import By
    from selenium.webdriver.support import expected_conditions as EC
    from selenium.webdriver.support.ui import WebDriverWait

    procs = []
    try:
        gw, base = start_gateway(settings, tmp_path / "gateway.log")
        procs.append(gw)
        procs.append(start_worker(settings, tmp_path / "worker.log"))
        c = httpx.Client(base_url=base, headers={"Authorization": f"Bearer {OPERATOR_KEY}"}, timeout=30)
        # big enough that the export takes several seconds even on an idle machine, so the page is
        # seen showing the job queued or running before it is done
        z = zip_bundle(make_bundle(tmp_path / "b", frames=80, width=160, height=120, test_frames=8), tmp_path / "b.zip")
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
        assert states & {"queued", "running"}, f"the job was never seen before it finished: {states}"
        assert browser.execute_script("return window.__noReload;") == marker, "the page was reloaded"
        assert _text(browser, row + " .pct") == "100%"
        assert _text(browser, row + " td:nth-child(6)") == "upload"
        # the preview image is served to the logged-in browser and decodes
        img = WebDriverWait(browser, 20).until(EC.presence_of_element_located(
            (By.CSS_SELECTOR, f"#previews figure[data-job-id='{jid}'] img.preview")))
        WebDriverWait(browser, 20).until(lambda d: d.execute_script(
            "return arguments[0].complete && arguments[0].naturalWidth > 0", img))
        w = browser.execute_script("return arguments[0].naturalWidth", img)
        assert w == 3 * 160, w  # the G-buffer mosaic: three frames wide
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
