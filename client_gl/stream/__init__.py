"""The streaming client's GL-free side: where scene bytes come from (sources), the disk cache, the fetcher, the
tile selection and the engine that ties them together. Nothing here imports moderngl or client_gl.gpu: it is
unit-tested without a GL context (ARCHITECTURE.md)."""
