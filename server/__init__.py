"""splatstream's HTTP server: serves every encoded scene directory under a root (format_spec/http.md).

`server.app.create_app(root, cors_origins=...)` builds the aiohttp application; `server.run.serve(...)` runs it
(the `splatstream serve` command). The request handlers are thin: path validation (`server.paths`) and the
HTTP rules (`server.http`) are pure functions with their own unit tests.
"""
