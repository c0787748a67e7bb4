"""Test-wide settings: one torch/OpenMP thread, in this process and every subprocess the tests start (``make test``
runs the files on pytest-xdist workers, one per core).

On a 2-core machine two threads per process collapse as soon as anything else runs (see docs/performance.md);
one thread is also what the exact-resume guarantee is stated for. The ``fake_s3`` fixture gives ``fakes3://`` URLs:
a local folder with an object store's semantics, for the results-at-a-URL tests.
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


@pytest.fixture
def fake_s3():
    """``fakes3://<absolute path>`` URLs, in this process (the local launcher runs its uploads here)."""
    import fsspec

    fsspec.register_implementation("fakes3", FakeS3, clobber=True)
    FakeS3.writes = []
    return FakeS3
