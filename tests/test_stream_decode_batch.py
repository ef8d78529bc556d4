"""The engine's batch decode and its fewer decode threads while the camera moves (client_gl/stream/engine.py):
a real encoded scene in memory, the same planes as one payload at a time, the same residency, no clocks."""
import threading
from dataclasses import astuple

import numpy as np
import pytest
from conftest import real
from test_stream_engine import CountingPool, StepFetcher, orbit, run_until_converged

from client_gl.stream import engine as engine_module
from client_gl.stream.engine import StreamEngine, StreamOptions, decode_batch_job, decode_job
from client_gl.stream.selection import SelectionOptions
from splatstream.encode import EncodeOptions, encode_in_memory
from splatstream.ply import read_gaussians_ply
from splatstream.store import read_manifest


@pytest.fixture(scope="module")
def store():
    g = read_gaussians_ply(real("fruit_drops_sh3.ply"))
    return encode_in_memory(g, EncodeOptions(preset="medium", max_leaf_splats=300))


@pytest.fixture(scope="module")
def codebook_store():
    g = read_gaussians_ply(real("fruit_drops_sh3.ply"))
    return encode_in_memory(g, EncodeOptions(preset="low", max_leaf_splats=300))


def _jobs(store, group: str, with_mirror: bool = False):
    m = read_manifest(store)
    jobs = []
    for t in m.tiles:
        entry = t.groups[group]
        codebook = m.uses_codebook
        jobs.append((store.read_payload(entry), entry, group, f"scene/{entry.file}", codebook, t.splats,
                     m.sh_codebook.entries if codebook else 0, with_mirror))
    return jobs


def _same(a, b) -> None:
    assert not isinstance(a, str) and not isinstance(b, str), (a, b)
    (pa, ma), (pb, mb) = a, b
    assert pa.keys() == pb.keys()
    for name in pa:
        assert len(pa[name].layers) == len(pb[name].layers)
        for x, y in zip(pa[name].layers, pb[name].layers, strict=True):
            assert np.asarray(x).dtype == np.asarray(y).dtype and bytes(x) == bytes(y)
        ra, rb = pa[name].ranges, pb[name].ranges
        assert (ra is None) == (rb is None)
        if ra is not None:
            assert ra.tobytes() == rb.tobytes()
    if ma is None or mb is None:
        assert ma is mb
    else:
        for x, y in zip(astuple(ma), astuple(mb), strict=True):
            assert np.asarray(x).tobytes() == np.asarray(y).tobytes()


@pytest.mark.parametrize("group", ["base", "sh1", "sh3"])
def test_a_batch_decodes_what_one_payload_at_a_time_does(store, group):
    jobs = _jobs(store, group, with_mirror=group == "base")
    assert len(jobs) > 10
    calls = []
    batch = decode_batch_job(jobs, between=lambda: calls.append(1))
    assert calls  # the decode thread's wait for the frame loop runs between the batch's steps
    for job, got in zip(jobs, batch, strict=True):
        _same(got, decode_job(*job))


def test_a_batch_of_a_codebook_scenes_indices_decodes_and_checks_them(codebook_store):
    m = read_manifest(codebook_store)
    assert m.uses_codebook
    jobs = _jobs(codebook_store, "sh1")
    for job, got in zip(jobs, decode_batch_job(jobs), strict=True):
        _same(got, decode_job(*job))


def test_a_payload_that_does_not_decode_is_named_and_the_rest_of_its_batch_kept(store):
    jobs = _jobs(store, "base")[:6]
    data = bytearray(jobs[3][0])
    data[len(data) // 2] ^= 0xFF  # a flipped byte: the checksum no longer matches
    jobs[3] = (bytes(data),) + jobs[3][1:]
    out = decode_batch_job(jobs)
    assert isinstance(out[3], str) and jobs[3][3] in out[3]
    for k, job in enumerate(jobs):
        if k != 3:
            _same(out[k], decode_job(*job))


class LateFetcher(StepFetcher):
    """Nothing in the first frame, then `per_frame` payloads a frame."""

    def want(self, requests):
        if not self.wants:
            self.wants.append([k for _, k, _ in requests])
            return
        super().want(requests)


def test_batches_and_one_thread_while_moving_reach_the_same_residency(store, monkeypatch):
    """The payloads of a collect are decoded as batches, one job at a time while the camera moves (the orbit turns
    every frame), then all threads once it rests; the residency reached is the one of a payload a job."""
    m = read_manifest(store)
    running, most, batches = [0], [0], [0]
    lock = threading.Lock()

    def counted(fn, is_batch):
        def run(*args, **kwargs):
            with lock:
                running[0] += 1
                most[0] = max(most[0], running[0])
                batches[0] += is_batch
            try:
                return fn(*args, **kwargs)
            finally:
                with lock:
                    running[0] -= 1
        return run

    results = []
    for batch in (False, True):
        monkeypatch.setattr(engine_module, "decode_job", counted(decode_job, 0))
        monkeypatch.setattr(engine_module, "decode_batch_job", counted(decode_batch_job, 1))
        running[0] = most[0] = batches[0] = 0
        pool = CountingPool(10_000)
        engine = StreamEngine(LateFetcher(store, per_frame=6), pool,
                              StreamOptions(SelectionOptions(max_sse=1.0), decode_batch=batch, decode_workers=2,
                                            decode_workers_moving=1, fill_root_bytes=0))  # coarse to fine: enough
        # payloads that the view has not converged when the camera comes to rest
        for frame in range(12):  # moving: at most one decode job at a time
            engine.update(orbit(m, 1.6, 0.3 + 0.01 * frame))
            engine.wait(0.05)
            assert engine._decode_limit == (2 if frame == 0 else 1)  # the first frame has no camera before it
        assert most[0] == 1 and engine.moving_frames == 11
        assert (batches[0] > 0) == batch
        cam = orbit(m, 1.6, 0.5)
        _, u = run_until_converged(engine, cam)
        assert engine._decode_limit == 2  # resting: every thread
        results.append((sorted(u.draw), {t: pool.bands[t] for t in u.draw}))
        engine.close()
    assert results[0] == results[1]


def test_a_batch_holds_at_most_decode_batch_splats(store, monkeypatch):
    """A collect's payloads go in consecutive jobs of at most decode_batch_splats splats (a larger payload alone),
    so that a decode step stays short; the residency is the one of a payload a job."""
    m = read_manifest(store)
    shares = []
    results = []
    for batch in (False, True):
        pool = CountingPool(10_000)
        engine = StreamEngine(StepFetcher(store, per_frame=12), pool,
                              StreamOptions(SelectionOptions(max_sse=1.0), decode_batch=batch,
                                            decode_batch_splats=1000))
        many = engine._decode_many
        monkeypatch.setattr(engine, "_decode_many", lambda items, many=many: (shares.append(items), many(items)))
        _, u = run_until_converged(engine, orbit(m, 1.6, 0.3))
        results.append((sorted(u.draw), {t: pool.bands[t] for t in u.draw}))
        assert engine.decode_jobs <= engine.decode_job_payloads
        engine.close()
    assert shares
    for items in shares:
        assert len(items) >= 2 and sum(m.tile(key[0]).splats for key, _, _ in items) <= 1000
        assert len({key[1] for key, _, _ in items}) == 1  # one group a job
    assert results[0] == results[1]
