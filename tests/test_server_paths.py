"""Unit tests of the server's pure parts: path validation (server.paths) and HTTP rules (server.http)."""
from __future__ import annotations

import pytest

from server import http as h
from server.paths import (
    PathRejected,
    is_inside,
    is_valid_scene_id,
    parse_scene_path,
    parse_scene_path_general,
    percent_decode,
)

SHA = "ab" * 32


@pytest.mark.parametrize("raw, scene, rel, kind", [
    ("/scenes/a/manifest.msgpack", "a", "manifest.msgpack", "manifest"),
    ("/scenes/a/b/c/manifest.msgpack", "a/b/c", "manifest.msgpack", "manifest"),
    (f"/scenes/a/data/{SHA}.bin", "a", f"data/{SHA}.bin", "payload"),
    (f"/scenes/x.y_z-1/data/data/{SHA}.bin", "x.y_z-1/data", f"data/{SHA}.bin", "payload"),
    ("/scenes/%61/manifest.msgpack", "a", "manifest.msgpack", "manifest"),  # harmless escapes decode
])
def test_accepts(raw, scene, rel, kind):
    sp = parse_scene_path(raw)
    assert (sp.scene_id, sp.rel, sp.kind) == (scene, rel, kind)
    assert sp.sha256 == (SHA if kind == "payload" else None)
    assert parse_scene_path_general(raw) == sp  # the fast path agrees with the general one


@pytest.mark.parametrize("raw", [
    "/scenes/manifest.msgpack/manifest.msgpack", f"/scenes/a/data/data/{SHA}.bin", f"/scenes/data/data/{SHA}.bin",
    "/scenes/data/manifest.msgpack", "/scenes/" + "a/" * 8 + "manifest.msgpack",
    "/scenes/" + "x" * 255 + "/manifest.msgpack",
    f"/scenes/-/_/data/{SHA}.bin",
])
def test_fast_path_agrees(raw):
    assert parse_scene_path(raw) == parse_scene_path_general(raw)


@pytest.mark.parametrize("raw, status", [
    ("/scenes/../etc/passwd", 400),
    ("/scenes/a/../a/manifest.msgpack", 400),
    ("/scenes/./a/manifest.msgpack", 400),
    ("/scenes/%2e%2e/%2e%2e/etc/passwd", 400),
    ("/scenes/%2E%2E/a/manifest.msgpack", 400),
    ("/scenes/.%2e/a/manifest.msgpack", 400),
    ("/scenes/a%2Fmanifest.msgpack", 400),
    ("/scenes/a%2fmanifest.msgpack", 400),
    ("/scenes/%2Fetc%2Fpasswd/manifest.msgpack", 400),
    ("/scenes/%252e%252e/a/manifest.msgpack", 400),  # double encoding
    ("/scenes/a%252Fmanifest.msgpack", 400),
    ("/scenes/a%5Cmanifest.msgpack", 400),
    ("/scenes/a\\manifest.msgpack", 400),
    ("/scenes/..\\..\\etc/manifest.msgpack", 400),
    ("/scenes/a%00/manifest.msgpack", 400),
    ("/scenes/a\x00/manifest.msgpack", 400),
    ("/scenes/a%0a/manifest.msgpack", 400),
    ("/scenes/a%/manifest.msgpack", 400),
    ("/scenes/a%zz/manifest.msgpack", 400),
    ("/scenes/%C3%A9/manifest.msgpack", 400),
    ("/scenes/a b/manifest.msgpack", 400),
    ("/scenes/a:b/manifest.msgpack", 400),
    ("/scenes/" + "a" * 3000 + "/manifest.msgpack", 400),
    ("/scenes//etc/passwd", 404),  # absolute path after the prefix: empty segment
    ("/scenes//manifest.msgpack", 404),
    ("/scenes/.a.tmp/manifest.msgpack", 404),  # hidden build directories
    ("/scenes/a/.hidden/manifest.msgpack", 404),
    ("/scenes/%2ea.tmp/manifest.msgpack", 404),
    ("/scenes/a/", 404),  # no directory listing
    ("/scenes/a", 404),
    ("/scenes/a/data/", 404),
    ("/scenes/a/data", 404),
    ("/scenes/manifest.msgpack", 404),  # the root is no scene
    (f"/scenes/data/{SHA}.bin", 404),
    ("/scenes/a/other.txt", 404),
    (f"/scenes/a/data/{SHA.upper()}.bin", 404),
    (f"/scenes/a/data/{SHA[:-1]}.bin", 404),
    (f"/scenes/a/{SHA}.bin", 404),
    ("/scenes/" + "a/" * 9 + "manifest.msgpack", 404),
    ("/scenes/" + "x" * 256 + "/manifest.msgpack", 400),
    ("/etc/passwd", 404),
])
def test_rejects(raw, status):
    for parse in (parse_scene_path, parse_scene_path_general):
        with pytest.raises(PathRejected) as info:
            parse(raw)
        assert info.value.status == status
        assert info.value.message


def test_percent_decode():
    assert percent_decode("abc") == "abc"
    assert percent_decode("%41%2e%2D") == "A.-"
    for bad in ("%2F", "%5c", "%25", "%00", "%1f", "%7F", "%", "%4", "%g0", "%FF"):
        with pytest.raises(PathRejected):
            percent_decode(bad)


def test_scene_ids():
    assert is_valid_scene_id("a")
    assert is_valid_scene_id("a/b-1/c_2.v3")
    for bad in ("", "/a", "a/", ".a", "a/..", "a//b", "a\\b", "a b", "/".join("a" * 9)):
        assert not is_valid_scene_id(bad), bad


def test_is_inside():
    assert is_inside("/srv/root/a/manifest.msgpack", "/srv/root")
    assert is_inside("/srv/root/a", "/srv/root/")
    assert not is_inside("/srv/root", "/srv/root")
    assert not is_inside("/srv/rootx/a", "/srv/root")
    assert not is_inside("/etc/passwd", "/srv/root")
    assert is_inside("/a", "/")


@pytest.mark.parametrize("header, size, expected", [
    (None, 100, None),
    ("bytes=0-9", 100, (0, 9)),
    ("bytes=10-", 100, (10, 99)),
    ("bytes=-10", 100, (90, 99)),
    ("bytes=-1000", 100, (0, 99)),
    ("bytes=90-1000", 100, (90, 99)),
    ("bytes=99-99", 100, (99, 99)),
    (" Bytes = 0-0 ", 100, (0, 0)),
    ("bytes=9-5", 100, None),  # invalid: ignored (RFC 9110 14.2)
    ("bytes=0-1,5-6", 100, None),  # several ranges: served whole
    ("items=0-5", 100, None),
    ("bytes=a-b", 100, None),
    ("bytes=-", 100, None),
    ("bytes=", 100, None),
    ("bytes 0-5", 100, None),
    # RFC 9110 puts no limit on the digits (issue 37): a huge last is clipped, a huge first is beyond the end
    ("bytes=0-99999999999999999999", 100, (0, 99)),
    ("bytes=0000000000000000000000000000005-6", 100, (5, 6)),
])
def test_parse_range(header, size, expected):
    r = h.parse_range(header, size)
    assert (None if r is None else (r.start, r.end)) == expected
    if r is not None:
        assert r.length == r.end - r.start + 1
        assert r.content_range(size) == f"bytes {r.start}-{r.end}/{size}"


@pytest.mark.parametrize("header, size", [
    ("bytes=100-", 100), ("bytes=100-200", 100), ("bytes=-0", 100), ("bytes=0-", 0), ("bytes=-5", 0),
])
def test_range_not_satisfiable(header, size):
    with pytest.raises(h.RangeNotSatisfiable):
        h.parse_range(header, size)


def test_etags():
    tag = h.strong_etag("abc")
    assert tag == '"abc"'
    assert h.parse_etags('W/"a", "b" ,"c"') == [(True, "a"), (False, "b"), (False, "c")]
    assert h.parse_etags("*") is None
    assert h.none_match('"abc"', tag)
    assert h.none_match('W/"abc"', tag)  # weak comparison
    assert h.none_match('"x", "abc"', tag)
    assert h.none_match("*", tag)
    assert not h.none_match('"abcd"', tag)
    assert not h.none_match(None, tag)
    assert not h.none_match("abc", tag)  # unquoted: not an entity tag
    assert h.match(None, tag)
    assert h.match('"abc"', tag)
    assert h.match("*", tag)
    assert not h.match('W/"abc"', tag)  # strong comparison
    assert not h.match('"x"', tag)
    assert h.if_range_allows(None, tag)
    assert h.if_range_allows('"abc"', tag)
    assert not h.if_range_allows('W/"abc"', tag)
    assert not h.if_range_allows('"x"', tag)
    assert not h.if_range_allows("Sat, 21 Nov 2026 04:00:00 GMT", tag)
    assert not h.if_range_allows('"abc"', h.weak_etag("abc"))


@pytest.mark.parametrize("header, ok", [
    (None, False), ("", False), ("gzip", True), ("deflate, gzip;q=0.5", True), ("GZIP", True),
    ("gzip;q=0", False), ("br", False), ("*", True), ("*;q=0", False), ("gzip;q=0, *", False),
    ("*, gzip;q=0", False), ("identity", False), ("x-gzip", True), ("gzip;q=bad", False),
])
def test_accepts_gzip(header, ok):
    assert h.accepts_gzip(header) is ok


def test_error_body():
    assert h.error_body(404, "no") == {"error": {"status": 404, "message": "no"}}


@pytest.mark.parametrize("header", ["bytes=18446744073709551616-", "bytes=100-", "bytes=" + "9" * 5000 + "-"])
def test_parse_range_beyond_the_end(header):
    with pytest.raises(h.RangeNotSatisfiable):
        h.parse_range(header, 100)
