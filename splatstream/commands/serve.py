"""`splatstream serve ROOT [--host H] [--port P] [--cors-origin ORIGIN ...] [--workers N]
[--throttle-mbps R] [--latency-ms L]`."""
from __future__ import annotations

import argparse
import sys


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "serve", help="serve every encoded scene under a directory over HTTP",
        description="Serve every scene directory under ROOT (any directory holding manifest.msgpack; its id is its "
                    "path below ROOT) at /scenes/<id>/..., the scene list at /api/scenes and /healthz. "
                    "The protocol, and how to serve the same ROOT from nginx or a CDN, is in format_spec/http.md.")
    p.add_argument("root", metavar="ROOT", help="directory holding scene directories")
    p.add_argument("--host", default="127.0.0.1", help="address to listen on (default: %(default)s; 0.0.0.0 for all)")
    p.add_argument("--port", type=int, default=8000, help="TCP port (default: %(default)s; 0 picks a free one)")
    p.add_argument("--cors-origin", action="append", default=[], metavar="ORIGIN",
                   help="let pages from ORIGIN (e.g. https://viewer.example.com, or * for any) read the scenes; "
                        "repeat for several")
    p.add_argument("--workers", type=int, default=1, metavar="N",
                   help="worker processes sharing the port (default: %(default)s; about one per CPU core)")
    p.add_argument("--no-access-log", dest="access_log", action="store_false",
                   help="do not write one line per request to stderr")
    p.add_argument("--throttle-mbps", type=float, default=None, metavar="R",
                   help="test tool: send response bodies over a simulated link of R Mbit/s shared by all "
                        "connections (needs --workers 1)")
    p.add_argument("--latency-ms", type=float, default=0.0, metavar="L",
                   help="test tool: add L ms before each response starts (default: %(default)s)")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from server.run import serve  # aiohttp is imported only when serving

    if not 0 <= args.port <= 65535:
        print(f"splatstream serve: error: --port {args.port}: expected 0..65535", file=sys.stderr)
        return 2
    if args.workers < 1:
        print(f"splatstream serve: error: --workers {args.workers}: expected at least 1", file=sys.stderr)
        return 2
    if args.throttle_mbps is not None and not (args.throttle_mbps > 0 and args.throttle_mbps < float("inf")):
        print(f"splatstream serve: error: --throttle-mbps {args.throttle_mbps}: expected a positive number",
              file=sys.stderr)
        return 2
    if not 0 <= args.latency_ms < float("inf"):
        print(f"splatstream serve: error: --latency-ms {args.latency_ms}: expected 0 or more", file=sys.stderr)
        return 2
    if (args.throttle_mbps is not None or args.latency_ms) and args.workers != 1:
        print("splatstream serve: error: --throttle-mbps and --latency-ms need --workers 1 (the simulated link "
              "is shared within one process)", file=sys.stderr)
        return 2
    from server.throttle import Link

    return serve(args.root, host=args.host, port=args.port, cors_origins=args.cors_origin, workers=args.workers,
                 access_log=args.access_log, throttle=Link.from_args(args.throttle_mbps, args.latency_ms))
