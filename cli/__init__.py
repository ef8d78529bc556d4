"""The `splatstream` command-line layer: a shell beside `server/` and `client_gl/`. It parses arguments, wires the
core to the shells (renderers, the server, the viewer) and turns library errors into messages and exit codes; the
core never imports it (ARCHITECTURE.md, the import contracts in pyproject.toml)."""
