"""Where PreparedSource.open's time goes for a scene directory served on loopback (the first frame's 'manifest'
step): the server's reply, the parse in the fetch thread (lazy, as the fetcher parses) and the rest, each scene in
turn, several rounds. Usage: python bench/device/probe_manifest_open.py SCENE_DIR [SCENE_DIR ...]"""
import cProfile
import io
import os
import pstats
import sys
import time
import urllib.request

HERE = os.path.dirname(os.path.abspath(__file__))
sys.path.insert(0, os.path.dirname(os.path.dirname(HERE)))
sys.path.insert(0, os.path.dirname(HERE))

from bench_stream import serve_scene  # noqa: E402

import client_gl.stream.fetch as fetch  # noqa: E402
from client_gl.streaming import PreparedSource, ViewOptions  # noqa: E402

real_parse = fetch.parse_manifest
spent: list[float] = []
profiles: list[cProfile.Profile] = []


def timed_parse(*a, **k):
    pr = cProfile.Profile()
    t = time.perf_counter()
    pr.enable()
    try:
        return real_parse(*a, **k)
    finally:
        pr.disable()
        spent.append(time.perf_counter() - t)
        profiles.append(pr)


fetch.parse_manifest = timed_parse
for scene in sys.argv[1:]:
    proc, url = serve_scene(scene)
    try:
        gets = []
        for _ in range(3):
            t = time.perf_counter()
            urllib.request.urlopen(url + "/manifest.msgpack").read()
            gets.append(round((time.perf_counter() - t) * 1e3, 1))
        opens = []
        for _ in range(4):
            spent.clear()
            t = time.perf_counter()
            p = PreparedSource.open(url, ViewOptions(cache=False))
            opens.append((round((time.perf_counter() - t) * 1e3, 1), [round(s * 1e3, 1) for s in spent]))
            p.fetcher.close()
        print(os.path.basename(scene), "GET ms", gets, "open ms (parse ms)", opens, flush=True)
        s = io.StringIO()
        pstats.Stats(profiles[-1], stream=s).sort_stats("cumtime").print_stats(14)
        print(s.getvalue()[-2600:], flush=True)
    finally:
        proc.terminate()
