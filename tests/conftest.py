"""Test-wide settings: one torch/OpenMP thread, in this process and every subprocess the tests start (``make test``
runs the files on pytest-xdist workers, one per core).

On a 2-core machine two threads per process collapse as soon as anything else runs (see docs/performance.md);
one thread is also what the exact-resume guarantee is stated for. The ``fake_s3`` fixture gives ``fakes3://`` URLs:
a local folder with an object store's semantics, for the results-at-a-URL tests. ``rank_events_run`` is the tiny
run with rank events that three test files read, trained once per process instead of once per file.
"""

import os

os.environ.setdefault("OMP_NUM_THREADS", "1")
os.environ.setdefault("MKL_NUM_THREADS", "1")
os.environ.setdefault("MUJOCO_GL", "egl")
# Ray runs its workers at nice 15 by default; beside a second pytest-xdist worker at nice 0 they would get a few
# percent of a core, and a Ray test would take ten times as long.
os.environ.setdefault("RAY_worker_niceness", "0")

import pytest  # noqa: E402
import torch  # noqa: E402
from fsspec.implementations.local import LocalFileSystem  # noqa: E402

torch.set_num_threads(1)


class FakeS3(LocalFileSystem):
    """A local folder with object-store semantics: no rename, no append, no links; writes are logged in order."""

    protocol = ("fakes3",)
    writes: list[tuple[str, str]] = []

    def mv(self, path1, path2, recursive=True, **kwargs):  # S3: copy, then delete
        self.cp_file(path1, path2)
        self.rm_file(path1)
        self.writes.append(("mv", self._strip_protocol(path2)))

    def pipe_file(self, path, value, mode="overwrite", **kwargs):
        self.writes.append(("put", self._strip_protocol(path)))
        return super().pipe_file(path, value, mode=mode, **kwargs)

    def put_file(self, path1, path2, callback=None, **kwargs):
        self.writes.append(("put", self._strip_protocol(path2)))
        return super().put_file(path1, path2, callback=callback, **kwargs)

    def _open(self, path, mode="rb", **kwargs):
        if "a" in mode:
            raise NotImplementedError("object stores cannot append")
        return super()._open(path, mode, **kwargs)

    def link(self, src, dst, **kwargs):
        raise NotImplementedError("object stores have no links")

    symlink = link


@pytest.fixture(scope="session")
def rank_events_run(tmp_path_factory):
    """``adarl run quickstart tiny(*RANK_EVENTS) --quiet`` (1600 frames, rank events that truncate the actor's second
    layer), trained once per test process for the three files that read it, each as its module's tiny run:
    test_cli_e2e.py (the run folder, eval), test_policy.py (load_policy, play) and test_export.py. Returns the run
    folder and the finished ``adarl run`` process. (Only test_cli_e2e writes eval_nominal.json into it and only
    test_export the default policy.pt; nothing else a test of these files writes there is read by another.)"""
    from _helpers import RANK_EVENTS, adarl, tiny

    out = tmp_path_factory.mktemp("rank_events") / "run"
    proc = adarl("run", "quickstart", *tiny(*RANK_EVENTS), "-o", str(out), "--quiet")
    assert proc.returncode == 0, proc.stderr[-3000:]
    return out, proc


@pytest.fixture
def fake_s3():
    """``fakes3://<absolute path>`` URLs, in this process (the local launcher runs its uploads here)."""
    import fsspec

    fsspec.register_implementation("fakes3", FakeS3, clobber=True)
    FakeS3.writes = []
    return FakeS3
