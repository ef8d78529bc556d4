"""`splatstream serve ROOT [--host H] [--port P] [--cors-origin ORIGIN ...] [--workers N] [connection limits]
[--throttle-mbps R] [--latency-ms L]`."""
from __future__ import annotations

import argparse
import re
import sys

# An Origin header's value: scheme://host[:port] (RFC 6454), which is all a browser sends; a trailing slash is
# dropped by the server. Anything else (a bare host name, a URL with a path) would never match a request's Origin.
ORIGIN = re.compile(r"[A-Za-z][A-Za-z0-9+.-]*://[^/\s?#]+/?")


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "serve", help="serve every encoded scene under a directory over HTTP",
        description="Serve every scene directory under ROOT (any directory holding manifest.msgpack; its id is its "
                    "path below ROOT) at /scenes/<id>/..., the scene list at /api/scenes and /healthz, and every "
                    "3D Tiles tileset export-3dtiles wrote (a directory holding tileset.json) at "
                    "/scenes/<id>/tileset.json. Streamed SOGs and .rad files are not served (a static web server "
                    "that answers Range requests serves them). The protocol, and how to serve the same ROOT from "
                    "nginx or a CDN, is in format_spec/http.md.")
    p.add_argument("root", metavar="ROOT", help="directory holding scene directories and 3D Tiles tilesets")
    p.add_argument("--host", default="127.0.0.1", help="address to listen on (default: %(default)s; 0.0.0.0 for all)")
    p.add_argument("--port", type=int, default=8000, help="TCP port (default: %(default)s; 0 picks a free one)")
    p.add_argument("--cors-origin", action="append", default=[], metavar="ORIGIN",
                   help="let pages from ORIGIN (e.g. https://viewer.example.com, or * for any) read the scenes; "
                        "repeat for several")
    p.add_argument("--workers", type=int, default=1, metavar="N",
                   help="worker processes sharing the port (default: %(default)s; about one per CPU core)")
    p.add_argument("--no-access-log", dest="access_log", action="store_false",
                   help="do not write one line per request to stderr")
    limits = p.add_argument_group("connection limits (per worker; format_spec/http.md section 11)")
    limits.add_argument("--max-connections", type=int, default=1024, metavar="N",
                        help="open connections per worker (default: %(default)s); at the cap, idle ones are closed to "
                             "make room, and a small reserve beyond it answers /healthz and 503 for anything else")
    limits.add_argument("--header-timeout", type=float, default=10.0, metavar="SECONDS",
                        help="a request's headers must arrive within this time of its first byte, or of the "
                             "connection's opening (default: %(default)s)")
    limits.add_argument("--keepalive-timeout", type=float, default=30.0, metavar="SECONDS",
                        help="close a keep-alive connection idle for this long (default: %(default)s)")
    limits.add_argument("--send-timeout", type=float, default=60.0, metavar="SECONDS",
                        help="abort a response whose client reads nothing (less than 1 MiB of a large file) for this "
                             "long (default: %(default)s)")
    p.add_argument("--throttle-mbps", type=float, default=None, metavar="R",
                   help="test tool: send response bodies over a simulated link of R Mbit/s shared by all "
                        "connections (needs --workers 1)")
    p.add_argument("--latency-ms", type=float, default=0.0, metavar="L",
                   help="test tool: add L ms before each response starts (default: %(default)s)")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    # The server (aiohttp) is imported only when serving, so that other commands start without it.
    from server.limits import MIN_CONNECTIONS, Limits
    from server.run import serve

    def bad(option: str, value: object, expected: str) -> int:
        print(f"splatstream serve: error: {option} {value}: expected {expected}", file=sys.stderr)
        return 2

    if not 0 <= args.port <= 65535:
        return bad("--port", args.port, "0..65535")
    if args.workers < 1:
        return bad("--workers", args.workers, "at least 1")
    for origin in args.cors_origin:
        if origin not in ("*", "null") and not ORIGIN.fullmatch(origin):
            return bad("--cors-origin", origin, "an origin like https://viewer.example (scheme and host, no path), "
                       "or * for any")
    if args.max_connections < MIN_CONNECTIONS:
        return bad("--max-connections", args.max_connections, f"at least {MIN_CONNECTIONS}")
    for option in ("header_timeout", "keepalive_timeout", "send_timeout"):
        value = getattr(args, option)
        if not 0 < value <= 86400:  # also refuses nan
            return bad("--" + option.replace("_", "-"), value, "seconds, more than 0 and at most 86400")
    if args.throttle_mbps is not None and not (args.throttle_mbps > 0 and args.throttle_mbps < float("inf")):
        return bad("--throttle-mbps", args.throttle_mbps, "a positive number")
    if not 0 <= args.latency_ms < float("inf"):
        return bad("--latency-ms", args.latency_ms, "0 or more")
    if (args.throttle_mbps is not None or args.latency_ms) and args.workers != 1:
        print("splatstream serve: error: --throttle-mbps and --latency-ms need --workers 1 (the simulated link "
              "is shared within one process)", file=sys.stderr)
        return 2
    from server.throttle import Link  # only when serving: see run

    limits = Limits(max_connections=args.max_connections, header_timeout=args.header_timeout,
                    keepalive_timeout=args.keepalive_timeout, send_timeout=args.send_timeout)
    return serve(args.root, host=args.host, port=args.port, cors_origins=args.cors_origin, workers=args.workers,
                 access_log=args.access_log, limits=limits,
                 throttle=Link.from_args(args.throttle_mbps, args.latency_ms))
