"""Prometheus metrics in the text exposition format (version 0.0.4), written here: request
counts and latency histograms recorded by an ASGI middleware, and gauges read at scrape time
(jobs by state, scenes, queue depths, workers, Redis up)."""

from __future__ import annotations

import threading
import time
from collections import defaultdict

BUCKETS = (0.005, 0.01, 0.025, 0.05, 0.1, 0.25, 0.5, 1.0, 2.5, 5.0, 10.0)


def _esc(v: str) -> str:
    return str(v).replace("\\", "\\\\").replace("\n", "\\n").replace('"', '\\"')


def _labels(d: dict[str, str]) -> str:
    return "{" + ",".join(f'{k}="{_esc(v)}"' for k, v in d.items()) + "}" if d else ""


class Registry:
    def __init__(self):
        self._lock = threading.Lock()
        self.requests: dict[tuple[str, str, str], int] = defaultdict(int)
        self.hist: dict[tuple[str, str], list[float]] = {}  # bucket counts..., sum, count

    def observe(self, method: str, route: str, status: int, seconds: float) -> None:
        with self._lock:
            self.requests[(method, route, str(status))] += 1
            h = self.hist.get((method, route))
            if h is None:
                h = self.hist[(method, route)] = [0.0] * (len(BUCKETS) + 2)
            for i, b in enumerate(BUCKETS):
                if seconds <= b:
                    h[i] += 1
            h[-2] += seconds
            h[-1] += 1

    def render(self, gauges: list[tuple[str, str, list[tuple[dict, float]]]]) -> str:
        out = ["# HELP brdf_http_requests_total HTTP requests by method, route template and status.",
               "# TYPE brdf_http_requests_total counter"]
        with self._lock:
            reqs = dict(self.requests)
            hist = {k: list(v) for k, v in self.hist.items()}
        for (m, r, s), n in sorted(reqs.items()):
            out.append(f"brdf_http_requests_total{_labels({'method': m, 'route': r, 'status': s})} {n}")
        out += ["# HELP brdf_http_request_duration_seconds HTTP request latency.",
                "# TYPE brdf_http_request_duration_seconds histogram"]
        for (m, r), h in sorted(hist.items()):
            for i, b in enumerate(BUCKETS):
                out.append(f"brdf_http_request_duration_seconds_bucket{_labels({'method': m, 'route': r, 'le': repr(b)})} {int(h[i])}")
            out.append(f"brdf_http_request_duration_seconds_bucket{_labels({'method': m, 'route': r, 'le': '+Inf'})} {int(h[-1])}")
            out.append(f"brdf_http_request_duration_seconds_sum{_labels({'method': m, 'route': r})} {h[-2]:.6f}")
            out.append(f"brdf_http_request_duration_seconds_count{_labels({'method': m, 'route': r})} {int(h[-1])}")
        for name, help_, samples, *kind in gauges:
            out += [f"# HELP {name} {help_}", f"# TYPE {name} {kind[0] if kind else 'gauge'}"]
            for labels, v in samples:
                out.append(f"{name}{_labels(labels)} {v:g}")
        return "\n".join(out) + "\n"


class MetricsMiddleware:
    """Pure ASGI middleware (no BaseHTTPMiddleware overhead): times each HTTP request and labels
    it with the matched route template (so ids do not explode the label set). Also rejects
    non-upload bodies larger than ``max_body`` by their Content-Length."""

    def __init__(self, app, registry: Registry, max_body: int, upload_paths: tuple[str, ...]):
        self.app = app
        self.registry = registry
        self.max_body = max_body
        self.upload_paths = upload_paths

    async def __call__(self, scope, receive, send):
        if scope["type"] != "http":
            return await self.app(scope, receive, send)
        t0 = time.perf_counter()
        status = [500]
        if scope["path"] not in self.upload_paths:
            for k, v in scope.get("headers", ()):
                if k == b"content-length" and v.isdigit() and int(v) > self.max_body:
                    body = (b'{"detail":"request body of %d bytes exceeds the limit of %d bytes","errors":[]}'
                            % (int(v), self.max_body))
                    await send({"type": "http.response.start", "status": 413,
                                "headers": [(b"content-type", b"application/json"),
                                            (b"content-length", str(len(body)).encode())]})
                    await send({"type": "http.response.body", "body": body})
                    self.registry.observe(scope["method"], "(body too large)", 413, time.perf_counter() - t0)
                    return

        async def _send(msg):
            if msg["type"] == "http.response.start":
                status[0] = msg["status"]
            await send(msg)

        try:
            await self.app(scope, receive, _send)
        finally:
            route = scope.get("route")
            path = getattr(route, "path", None) or "(unmatched)"
            self.registry.observe(scope["method"], path, status[0], time.perf_counter() - t0)
