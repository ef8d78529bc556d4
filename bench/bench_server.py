#!/usr/bin/env python3
"""Load benchmark of `splatstream serve` against nginx serving the same ROOT at the same URLs.

Builds a scene root (small payloads and 64 MiB payloads), starts our server and nginx (config generated from the
snippet in format_spec/http.md) on 127.0.0.1, checks both answer the same bytes and headers, then runs wrk:
requests/s with p50/p99 latency for small files at 64 connections, MB/s for large payloads, server RSS before and
after. Both servers are stopped at the end. Needs `wrk` and `nginx` (Debian: apt-get install -y wrk nginx).

    .venv/bin/python bench/bench_server.py [--workers 2] [--duration 5] [--rounds 3] [--json out.json]
"""
from __future__ import annotations

import argparse
import hashlib
import http.client
import json
import os
import re
import shutil
import signal
import socket
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from server.testing import write_fake_scene  # noqa: E402

SMALL_SIZES = [4096] * 16  # small payloads (and the manifest)
LARGE_SIZES = [64 << 20] * 2
CORS_ORIGIN = "https://viewer.example"

NGINX_CONF = """\
worker_processes {workers};
daemon off;
pid {prefix}/nginx.pid;
error_log {prefix}/error.log warn;
events {{ worker_connections 4096; }}
http {{
    access_log {prefix}/access.log;
    client_body_temp_path {prefix}/tmp; proxy_temp_path {prefix}/tmp; fastcgi_temp_path {prefix}/tmp;
    uwsgi_temp_path {prefix}/tmp; scgi_temp_path {prefix}/tmp;
    sendfile on;
    tcp_nopush on;
    keepalive_requests 100000;
    map $http_origin $splat_cors_origin {{ default ""; "{origin}" $http_origin; }}
    server {{
        listen 127.0.0.1:{port};
{snippet}
    }}
}}
"""

# The server-block part; format_spec/http.md shows the same lines with /srv/splats for the root.
NGINX_SNIPPET = r"""
    # splatstream scenes under {root} at /scenes/<scene id>/... (format_spec/http.md)
    location ~ "^/scenes/((?:[A-Za-z0-9_-][A-Za-z0-9._-]*/){{1,8}})manifest\.msgpack$" {{
        alias {root}/$1manifest.msgpack;
        disable_symlinks on from={root};
        types {{ }}
        default_type application/vnd.msgpack;
        add_header Cache-Control "no-cache";
        add_header Access-Control-Allow-Origin $splat_cors_origin always;
        add_header Access-Control-Expose-Headers "ETag, Content-Range, Content-Length, Content-Encoding, Accept-Ranges" always;
        add_header Access-Control-Allow-Methods "GET, HEAD, OPTIONS" always;
        add_header Access-Control-Allow-Headers "Range, If-None-Match, If-Match, If-Range, Accept-Encoding" always;
        add_header Access-Control-Max-Age 86400 always;
        add_header Vary Origin always;
        if ($request_method = OPTIONS) {{ return 204; }}
    }}
    location ~ "^/scenes/((?:[A-Za-z0-9_-][A-Za-z0-9._-]*/){{1,8}}data/(?:[0-9a-f]{{32}}|[0-9a-f]{{64}})\.bin)$" {{
        alias {root}/$1;
        disable_symlinks on from={root};
        types {{ }}
        default_type application/octet-stream;
        gzip off;
        add_header Cache-Control "public, max-age=31536000, immutable";
        add_header Access-Control-Allow-Origin $splat_cors_origin always;
        add_header Access-Control-Expose-Headers "ETag, Content-Range, Content-Length, Content-Encoding, Accept-Ranges" always;
        add_header Access-Control-Allow-Methods "GET, HEAD, OPTIONS" always;
        add_header Access-Control-Allow-Headers "Range, If-None-Match, If-Match, If-Range, Accept-Encoding" always;
        add_header Access-Control-Max-Age 86400 always;
        add_header Vary Origin always;
        if ($request_method = OPTIONS) {{ return 204; }}
    }}
    location /scenes/ {{ return 404; }}   # anything else: hidden build directories, listings, other files
"""  # noqa: E501 - nginx lines are not split

WRK_LUA = """\
local paths = {{{paths}}}
local i = 0
request = function()
    i = i + 1
    return wrk.format("GET", paths[(i % #paths) + 1])
end
"""


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def wait_port(port: int, proc: subprocess.Popen, timeout: float = 20.0) -> None:
    end = time.monotonic() + timeout
    while time.monotonic() < end:
        if proc.poll() is not None:
            raise RuntimeError(f"server exited with {proc.returncode}")
        try:
            socket.create_connection(("127.0.0.1", port), timeout=0.5).close()
            return
        except OSError:
            time.sleep(0.1)
    raise RuntimeError(f"nothing listens on port {port}")


def tree_rss_kib(pid: int) -> int:
    """VmRSS of a process and its direct children (our workers, nginx's workers)."""
    pids = [pid]
    for d in os.listdir("/proc"):
        if d.isdigit():
            try:
                with open(f"/proc/{d}/stat") as f:
                    if int(f.read().rsplit(")", 1)[1].split()[1]) == pid:
                        pids.append(int(d))
            except (OSError, IndexError, ValueError):
                pass
    total = 0
    for p in pids:
        try:
            with open(f"/proc/{p}/status") as f:
                m = re.search(r"VmRSS:\s+(\d+) kB", f.read())
                total += int(m.group(1)) if m else 0
        except OSError:
            pass
    return total


_UNIT = {"us": 1e-3, "ms": 1.0, "s": 1e3, "m": 60e3}
_BYTES = {"B": 1, "KB": 1 << 10, "MB": 1 << 20, "GB": 1 << 30, "TB": 1 << 40}


def parse_wrk(out: str) -> dict:
    def lat(label: str) -> float | None:
        m = re.search(rf"^\s*{label}\s+([\d.]+)(us|ms|s|m)\s*$", out, re.M)
        return float(m.group(1)) * _UNIT[m.group(2)] if m else None

    rps = float(re.search(r"Requests/sec:\s+([\d.]+)", out).group(1))
    m = re.search(r"Transfer/sec:\s+([\d.]+)(B|KB|MB|GB|TB)", out)
    mbps = float(m.group(1)) * _BYTES[m.group(2)] / (1 << 20)
    bad = re.search(r"Non-2xx or 3xx responses:\s+(\d+)", out)
    err = re.search(r"Socket errors:(.*)", out)
    return {"rps": rps, "MiB_s": mbps, "p50_ms": lat("50%"), "p99_ms": lat("99%"),
            "non_2xx": int(bad.group(1)) if bad else 0, "socket_errors": err.group(1).strip() if err else ""}


def wrk(port: int, paths: list[str], connections: int, duration: int, workdir: Path) -> dict:
    script = workdir / f"paths_{abs(hash(tuple(paths)))}.lua"
    script.write_text(WRK_LUA.format(paths=", ".join(f'"{p}"' for p in paths)))
    cmd = ["wrk", "-t2", f"-c{connections}", f"-d{duration}s", "--latency", "-s", str(script),
           f"http://127.0.0.1:{port}"]
    out = subprocess.run(cmd, capture_output=True, text=True, timeout=duration + 60, check=True).stdout
    return parse_wrk(out)


def fetch(port: int, path: str, headers: dict | None = None) -> tuple[int, dict, bytes]:
    c = http.client.HTTPConnection("127.0.0.1", port, timeout=30)
    try:
        c.request("GET", path, headers=headers or {})
        r = c.getresponse()
        return r.status, {k.lower(): v for k, v in r.getheaders()}, r.read()
    finally:
        c.close()


def conformance(ours: int, nginx: int, small: list[str], large: list[str]) -> list[str]:
    """The two servers answer the bench URLs with the same bytes and the same caching/type/CORS headers."""
    problems = []
    for path in (small[0], large[0]):
        a, b = fetch(ours, path, {"Origin": CORS_ORIGIN}), fetch(nginx, path, {"Origin": CORS_ORIGIN})
        if a[0] != 200 or b[0] != 200 or a[2] != b[2]:
            problems.append(f"{path}: status {a[0]} vs {b[0]} or different bytes")
        if "/data/" in path and hashlib.sha256(a[2]).hexdigest() != path.rsplit("/", 1)[1][:64]:
            problems.append(f"{path}: bytes do not match the name")
        for h in ("cache-control", "content-type", "content-length", "access-control-allow-origin"):
            if a[1].get(h) != b[1].get(h):
                problems.append(f"{path}: {h}: {a[1].get(h)!r} vs nginx {b[1].get(h)!r}")
    for path in ("/scenes/.hidden.tmp/manifest.msgpack", "/scenes/../etc/passwd", "/scenes/bench/"):
        a, b = fetch(ours, path), fetch(nginx, path)
        if a[0] < 400 or b[0] < 400:
            problems.append(f"{path}: {a[0]} vs nginx {b[0]} (expected an error)")
    return problems


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--workers", type=int, default=2, help="worker processes for both servers (default 2)")
    ap.add_argument("--duration", type=int, default=5, help="seconds per wrk run (default 5)")
    ap.add_argument("--rounds", type=int, default=3, help="interleaved rounds; medians are reported (default 3)")
    ap.add_argument("--connections", type=int, default=64, help="wrk connections for small files (default 64)")
    ap.add_argument("--large-connections", type=int, default=8, help="wrk connections for large files (default 8)")
    ap.add_argument("--no-access-log", action="store_true", help="run both servers without access logs")
    ap.add_argument("--json", help="also write the results here")
    args = ap.parse_args()
    for tool in ("wrk", "nginx"):
        if not shutil.which(tool) and not os.path.exists(f"/usr/sbin/{tool}"):
            print(f"bench_server: {tool} not found (apt-get install -y wrk nginx)", file=sys.stderr)
            return 2
    nginx_bin = shutil.which("nginx") or "/usr/sbin/nginx"

    work = Path(tempfile.mkdtemp(prefix="splat_bench_"))
    work.chmod(0o755)  # nginx workers run as an unprivileged user
    procs: list[subprocess.Popen] = []
    try:
        root = work / "root"
        small_sha = write_fake_scene(root / "bench", SMALL_SIZES, seed=1)
        large_sha = write_fake_scene(root / "large", LARGE_SIZES, seed=2)
        write_fake_scene(root / ".hidden.tmp", [10], seed=3)
        small = ["/scenes/bench/manifest.msgpack"] + [f"/scenes/bench/data/{s}.bin" for s in small_sha]
        large = [f"/scenes/large/data/{s}.bin" for s in large_sha]

        p_ours, p_nginx = free_port(), free_port()
        log = open(work / "ours.log", "w")  # noqa: SIM115 - closed with the process
        cmd = [sys.executable, "-m", "cli", "serve", str(root), "--port", str(p_ours),
               "--workers", str(args.workers), "--cors-origin", CORS_ORIGIN]
        cmd += ["--no-access-log"] if args.no_access_log else []
        ours = subprocess.Popen(cmd, cwd=REPO, stdout=log, stderr=log)
        procs.append(ours)
        (work / "nginx").mkdir()
        (work / "nginx" / "tmp").mkdir()
        conf = NGINX_CONF.format(workers=args.workers, prefix=work / "nginx", port=p_nginx, origin=CORS_ORIGIN,
                                 snippet=NGINX_SNIPPET.format(root=root))
        if args.no_access_log:
            conf = conf.replace(f"access_log {work / 'nginx'}/access.log;", "access_log off;")
        (work / "nginx" / "nginx.conf").write_text(conf)
        nginx = subprocess.Popen([nginx_bin, "-p", str(work / "nginx"), "-c", str(work / "nginx" / "nginx.conf")],
                                 stdout=subprocess.DEVNULL, stderr=subprocess.PIPE)
        procs.append(nginx)
        wait_port(p_ours, ours)
        wait_port(p_nginx, nginx)

        problems = conformance(p_ours, p_nginx, small, large)
        for p in problems:
            print(f"conformance: {p}", file=sys.stderr)

        results: dict = {"workers": args.workers, "duration_s": args.duration, "rounds": args.rounds,
                         "connections": args.connections, "large_connections": args.large_connections,
                         "access_log": not args.no_access_log, "cpus": os.cpu_count(),
                         "loadavg_before": os.getloadavg(), "conformance_problems": problems}
        servers = {"ours": (p_ours, ours.pid), "nginx": (p_nginx, nginx.pid)}
        runs: dict = {name: {"small": [], "large": []} for name in servers}
        for name, (port, pid) in servers.items():
            for p in small + large:
                fetch(port, p)  # warm the page cache and the servers
            results[name] = {"rss_kib_before": tree_rss_kib(pid)}
        # Interleaved rounds (ours, nginx, ours, ...) so that drift in the shared machine's load hits both alike;
        # the summary is the median round.
        for rnd in range(args.rounds):
            for test, paths, conns in (("small", small, args.connections), ("large", large, args.large_connections)):
                for name, (port, pid) in servers.items():
                    r = wrk(port, paths, conns, args.duration, work)
                    r["rss_kib_after"] = tree_rss_kib(pid)
                    runs[name][test].append(r)
                    print(f"round {rnd + 1} {name:6s} {test:6s} {json.dumps(r)}", file=sys.stderr, flush=True)
        for name, (_, pid) in servers.items():
            for test in ("small", "large"):
                results[name][test] = {k: statistics.median(r[k] for r in runs[name][test])
                                       for k in ("rps", "MiB_s", "p50_ms", "p99_ms")}
                results[name][test]["non_2xx"] = sum(r["non_2xx"] for r in runs[name][test])
                results[name][test]["runs"] = runs[name][test]
            results[name]["rss_kib_after"] = tree_rss_kib(pid)
        results["loadavg_after"] = os.getloadavg()
        results["ratio"] = {
            "small_rps": results["ours"]["small"]["rps"] / results["nginx"]["small"]["rps"],
            "large_MiB_s": results["ours"]["large"]["MiB_s"] / results["nginx"]["large"]["MiB_s"],
            "large_MiB_s_per_round": [a["MiB_s"] / b["MiB_s"]
                                      for a, b in zip(runs["ours"]["large"], runs["nginx"]["large"], strict=True)],
        }
        summary = {name: {t: {k: results[name][t][k] for k in ("rps", "MiB_s", "p50_ms", "p99_ms")}
                          for t in ("small", "large")} | {"rss_kib": [results[name]["rss_kib_before"],
                                                                      results[name]["rss_kib_after"]]}
                   for name in servers}
        print(json.dumps({"summary": summary, "ratio": results["ratio"],
                          "loadavg": [results["loadavg_before"], results["loadavg_after"]]}, indent=1),
              file=sys.stderr)
        print(json.dumps(results, indent=2))
        if args.json:
            Path(args.json).write_text(json.dumps(results, indent=2) + "\n")
        return 1 if problems else 0
    finally:
        for p in procs:
            if p.poll() is None:
                p.send_signal(signal.SIGTERM)
        for p in procs:
            try:
                p.wait(timeout=30)
            except subprocess.TimeoutExpired:
                p.kill()
                p.wait()
        shutil.rmtree(work, ignore_errors=True)


if __name__ == "__main__":
    sys.exit(main())
